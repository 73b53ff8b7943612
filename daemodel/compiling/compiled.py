"""The compiled DAE: what every backend consumes.

A :class:`CompiledDAE` is frozen: the checked semi-explicit system (right-hand sides,
constraints with their derivative chains and index), consistent initial values, aliases,
invariants for drift, and what pruning dropped.  Backends ask it for batched torch
functions or casadi's DAE dict.
"""

from __future__ import annotations

import hashlib
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np
import sympy as sp

from daemodel.compiling.codegen import (
    CasadiConverter,
    build_torch_functions,
    local_names,
    torch_source,
)
from daemodel.compiling.structure import Constraint
from daemodel.declaring.functions import check_supported
from daemodel.errors import ReductionError, UnsupportedFunctionError

# Most nonzeros of d(f, g)/d(y, z) emitted as symbolic derivatives: sympy takes ~10 ms per
# derivative on real models (20 s for the 1,798 of a 600-unknown grid, 170 s for a dense
# 160-unknown system), while forward-mode AD over a column colouring needs a few directions.
SYMBOLIC_JACOBIAN_MAX_ENTRIES = 400
# The fields a copy may change and still share its model's cache: the initial values (a piece of a solve is the
# model from where the last ended, and every cached entry is made from the rest).  A copy that changes any other
# field (``dataclasses.replace(compiled, rhs=...)``) gets a cache of its own (CompiledDAE.__post_init__).
INITIAL_FIELDS = ("t0", "y0", "z0")
# The cache's entry that holds the fields its other entries were made from (a key no entry's can equal).
_MADE_FROM = ("made from",)


class Labels(Sequence):
    """``count`` strings made when read, ``make(i)`` the i-th: a generated function's labels and comments."""

    def __init__(self, count: int, make):
        self.count, self.make = count, make

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self.make(k) for k in range(*i.indices(self.count))]
        if not -self.count <= i < self.count:
            raise IndexError(f"label {i} of {self.count}")
        return self.make(i % self.count)


@dataclass(frozen=True, eq=False)
class CompiledDAE:
    """A checked, initialised, pruned semi-explicit DAE ``y' = f(t, y, z, p), 0 = g(t, y, z, p)``.

    Attributes
    ----------
    name : str
    t : sympy.Symbol
    t0 : float
        Initial time.
    states, algebraics, parameters : tuple of sympy.Symbol
    parameter_values : ndarray, shape (k,)
    rhs : tuple of sympy.Expr
        ``f``, one per state.
    ode_numbers : tuple of int
        Declaration number of each ODE.
    constraints : tuple of Constraint
        Each with its derivative chain; ``g`` is ``chain[0]``.
    determined_by : tuple of int
        For each algebraic variable, the constraint matched to it.
    aliases : tuple of (name, expr, label)
        Eliminated alias variables as expressions of the kept ones.
    invariants : tuple of (name, expr)
        The original constraints (and, for index 3, their velocity level) whose drift a
        solution can report; unchanged by :meth:`reduced`.
    y0, z0 : ndarray
        Consistent initial values (float64).
    notes : tuple of str
        What initialisation changed.
    dropped : dict str -> tuple of str
        What output-driven pruning removed, by kind.
    events : tuple of daemodel.declaring.events.Event
        The declared events (``Model.event``), on this model's symbols.
    arrays : dict str -> tuple of int
        The shape of each declared array of variables (``m.states("u", 1000)``) by its name, whose
        elements ``u[0]``, ... are among the variables (or were pruned): ``sol["u"]`` gathers them.
    """

    name: str
    t: sp.Symbol
    t0: float
    states: tuple
    algebraics: tuple
    parameters: tuple
    parameter_values: np.ndarray
    rhs: tuple
    ode_numbers: tuple
    constraints: tuple
    determined_by: tuple
    aliases: tuple
    invariants: tuple
    y0: np.ndarray
    z0: np.ndarray
    notes: tuple = ()
    dropped: dict = field(default_factory=dict)
    reduced_from: int | None = None
    events: tuple = ()
    arrays: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        for array in (self.parameter_values, self.y0, self.z0):
            array.flags.writeable = False
        # dataclasses.replace hands a copy its model's cache: kept where the copy changed only the initial values,
        # else a cache of its own (a copy with other right-hand sides solved the original's: exp(-1) for exp(-2))
        made_from = self._made_from()
        kept = self._cache.get(_MADE_FROM)
        if kept is None and not self._cache:
            self._cache[_MADE_FROM] = made_from
        elif kept is None or len(kept) != len(made_from) or not all(map(operator.is_, kept, made_from)):
            object.__setattr__(self, "_cache", {_MADE_FROM: made_from})

    def _made_from(self) -> tuple:
        """The fields every cached entry is made from (all but :data:`INITIAL_FIELDS`), as objects."""
        return tuple(getattr(self, f.name) for f in fields(self) if f.name not in (*INITIAL_FIELDS, "_cache"))

    def __getstate__(self) -> dict:
        # Generated functions live in the cache and do not pickle; a copy regenerates them.
        return {**self.__dict__, "_cache": {}}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__dict__["_cache"] = {_MADE_FROM: self._made_from()}

    def kept_copy(self, key, build) -> CompiledDAE:
        """A copy of this model with other equations (``build()``, given ``_cache={}``), made once and kept in
        its cache under ``key``, returned with this model's initial values: a copy of this one that changed
        only those (a piece of a solve) gets the same copy, with its own t0, y0 and z0, and its generated code."""
        if key not in self._cache:
            self._cache[key] = build()
        return self.rebased(self._cache[key])

    def rebased(self, copy: CompiledDAE) -> CompiledDAE:
        """``copy`` (a model made from this one) with this model's initial values, sharing its cache."""
        if all(getattr(copy, name) is getattr(self, name) for name in INITIAL_FIELDS):
            return copy
        return replace(copy, **{name: getattr(self, name) for name in INITIAL_FIELDS})

    def fingerprints(self) -> dict[str, str]:
        """Hashes of what a saved result belongs to, by field: ``"equations"`` (the names and the
        equations), ``"events"`` (each declared event's name, function, direction, reset and
        terminal flag) and ``"parameter values"``, so that a loader can say which of them differs."""

        def hash_equations() -> str:
            # (printed once per model, kept: every print of 10^5 equations took ~0.3 ms each, and a save
            # asked for it twice, a load again; each shape of equation is printed once, the text str gives)
            # (the garbage collector paused: its collections walked every tree alive, as many more times as
            # the model is larger: a first save of the reaction-diffusion family took 2.2 s at 10^4 unknowns
            # and 32 s at 10^5, now 0.47 and 3.8 s)
            from daemodel.compiling.texts import texts
            from daemodel.declaring.stencils import paused_collection

            symbols = (self.t, *self.states, *self.algebraics, *self.parameters)
            with paused_collection():
                equations = (
                    self.state_names,
                    self.algebraic_names,
                    self.parameter_names,
                    texts(self.rhs, symbols),
                    texts(self.g, symbols),
                )
            return hashlib.sha256(repr(equations).encode()).hexdigest()

        from daemodel.compiling.texts import exact_str

        events = [
            (
                e.name,
                exact_str(e.when),
                e.direction,
                [(self.state_names[i], exact_str(x)) for i, x in e.reset],
                e.terminal,
            )
            for e in self.events
        ]
        values = [float(v).hex() for v in np.asarray(self.parameter_values, dtype=float)]
        return {
            "equations": self.cached("fingerprint of the equations", hash_equations),
            **{
                name: hashlib.sha256(repr(part).encode()).hexdigest()
                for name, part in (("events", events), ("parameter values", values))
            },
        }

    def fingerprint(self, *, parameter_values: bool = True) -> str:
        """A hash of the equations, names, events and (unless ``parameter_values=False``: a trained
        surrogate that takes the parameters as inputs) parameter values: what a saved solution,
        ensemble or network belongs to (:meth:`fingerprints` by field)."""
        parts = self.fingerprints()
        kept = [parts["equations"]]
        if self.events:  # (a model without events keeps the hash of the versions before events)
            kept.append(parts["events"])
        if parameter_values and self.parameters:
            kept.append(parts["parameter values"])
        if len(kept) == 1:  # (the hash of the equations alone, as before events and parameter values counted)
            return kept[0]
        return hashlib.sha256(repr(kept).encode()).hexdigest()

    def cached(self, key, build, on: tuple | None = None):
        """``build()``, computed once per key and kept with this model (not pickled): generated
        functions that a solver would otherwise rebuild on every solve.  A copy by ``dataclasses.replace``
        shares it only where it changed nothing but the initial values (:meth:`__post_init__`); ``on``: the
        fields it is made from, kept beside it, and built anew where the model's are not those same objects."""
        if on is None:
            if key not in self._cache:
                self._cache[key] = build()
            return self._cache[key]
        kept = self._cache.get(key)
        if kept is None or len(kept[0]) != len(on) or any(a is not b for a, b in zip(kept[0], on, strict=True)):
            kept = self._cache[key] = (on, build())
        return kept[1]

    @property
    def numeric(self):
        """The model's :class:`~daemodel.compiling.init.NumericSystem` (numpy functions over ``(t, y, z, p)``), made
        once and kept with it: each function it makes is made once too, so a solution's ``at()`` and
        ``drift()``, the event functions and the initial-value checks share them."""
        from daemodel.compiling.init import NumericSystem

        return self.cached("numeric", lambda: NumericSystem(self.t, self.states, self.algebraics, self.parameters))

    # ---- names and structure ------------------------------------------------------------
    @property
    def index(self) -> int:
        """Highest index over the constraints (0 for a pure ODE), computed once per model (a solve asks
        several times: 70 ms a time over the 5 x 10^4 constraints of 10^5 unknowns)."""
        return self.cached("index", lambda: max((c.index for c in self.constraints), default=0), on=(self.constraints,))

    @property
    def constraint_index(self) -> dict[str, int]:
        """Index of each constraint, by name."""
        return {c.name: c.index for c in self.constraints}

    @property
    def state_names(self) -> tuple[str, ...]:
        # (made once: every solve reads them a few times, ~5 us each at 80 states)
        return self.cached("state-names", lambda: tuple(s.name for s in self.states), on=(self.states,))

    @property
    def algebraic_names(self) -> tuple[str, ...]:
        return self.cached("algebraic-names", lambda: tuple(s.name for s in self.algebraics), on=(self.algebraics,))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.parameters)

    @property
    def constraint_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.constraints)

    @property
    def alias_names(self) -> tuple[str, ...]:
        return tuple(name for name, _, _ in self.aliases)

    def dropped_names(self) -> frozenset:
        """Every name that output-driven pruning removed (variables, aliases, constraints, parameters)."""
        return frozenset(name for names in self.dropped.values() for name in names)

    @property
    def invariant_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.invariants)

    @property
    def g(self) -> tuple:
        """The constraints as posed, ``0 = g``."""
        return tuple(c.expr for c in self.constraints)

    # ---- index reduction ----------------------------------------------------------------
    def consistent(self, y0=None, parameters=None, fix=()) -> dict:
        """The nearest initial states that satisfy every constraint, for ``solve(y0=...)``.

        ``y0`` and ``parameters`` as :func:`daemodel.solve` takes them (by name or as arrays, one
        sample or a batch; default: the model's own).  Each sample is projected, with the least
        change of its states, onto every constraint level free of the algebraic variables (the
        constraints themselves and, at index 2 and 3, their time derivatives).  ``fix`` names
        states to hold at their given values: only the others move (with the least change).
        Returns a dict state name -> float, or -> array (B,) for a batch.

        Raises
        ------
        InconsistentInitialStateError
            When no nearby state satisfies the constraints (naming the sample and the level).
        FixedStateError
            When ``fix`` holds every state of an inconsistent sample, or the constraints have no
            solution with the fixed states held.
        ShapeError, UnknownSymbolError, InvalidValueError
            For malformed input, as ``solve`` does, and for a name in ``fix`` that is not a state.
        """
        from daemodel.compiling.initial_states import consistent_states

        return consistent_states(self, y0, parameters, fix)

    def reduced(self, index: int = 1) -> CompiledDAE:
        """Differentiate every constraint of higher index until it has ``index``.

        Each constraint of index k > ``index`` is replaced by its ``(k - index)``-th time
        derivative along the ODE (named with primes: ``rod'``); the original constraints
        stay available as :attr:`invariants` for drift.  Initial values are unchanged (they
        satisfy every level of each chain).

        Parameters
        ----------
        index : int
            Target index, 1 <= index <= current index.
        """
        if isinstance(index, bool) or not isinstance(index, int) or not 1 <= index <= max(self.index, 1):
            raise ReductionError(
                f"reduced(index={index!r}): the target must be an integer from 1 to the current "
                f"index {self.index} of '{self.name}'"
            )

        def build():
            constraints = tuple(
                Constraint(c.level_name(c.index - index), c.number, c.chain[c.index - index :])
                if c.index > index
                else c
                for c in self.constraints
            )
            pairs = zip(self.constraints, constraints, strict=True)
            changed = ", ".join(f"{a.name} -> {b.name}" for a, b in pairs if a is not b)
            note = f"reduced from index {self.index} to {index}: " + (changed or "nothing to differentiate")
            return replace(
                self,
                constraints=constraints,
                notes=(*self.notes, note),
                reduced_from=self.reduced_from or self.index,
                _cache={},
            )

        return self.kept_copy(("reduced", index), build)  # (the same reduction, with its generated code, every solve)

    # ---- code generation ----------------------------------------------------------------
    def _groups(self) -> dict:
        return {"y": self.states, "z": self.algebraics, "p": self.parameters}

    def _outputs(self) -> dict:
        """name -> (expressions, labels, comments, docstring) of every generated function, checked.

        ``labels`` name each expression in error messages (they may carry user names);
        ``comments`` and the docstring go into generated source and hold only positions and
        equation numbers, never user text.

        Raises
        ------
        UnsupportedFunctionError
            For an expression no emitter translates (e.g. ``Heaviside`` from differentiating
            ``Max`` in :meth:`reduced`), naming the function and the equation.
        """
        return dict(self.cached("checked outputs", self._checked_outputs))  # (checked once per model)

    def _checked_outputs(self) -> dict:
        # (labels and comments made when read: kept as lists they held 2 MB at 10^4 unknowns, a model's first solve)
        states, numbers, constraints = self.states, self.ode_numbers, self.constraints
        outputs = {
            "f": (
                self.rhs,
                Labels(len(states), lambda i: f"{states[i].name}' (#{numbers[i]})"),
                Labels(len(states), lambda i: f"f[{i}]: ODE #{numbers[i]}"),
                "ODE right-hand sides f, shape (..., n).",
            ),
            "g": (
                self.g,
                Labels(
                    len(constraints),
                    lambda i: f"{constraints[i].name} (#{constraints[i].number}, index {constraints[i].index})",
                ),
                Labels(
                    len(constraints),
                    lambda i: f"g[{i}]: constraint #{constraints[i].number}, index {constraints[i].index}",
                ),
                "Constraints g, shape (..., m).",
            ),
            "aliases": (
                tuple(e for _, e, _ in self.aliases),
                list(self.alias_names),
                Labels(len(self.aliases), lambda i: f"alias {i}"),
                "Eliminated alias variables, shape (..., a).",
            ),
            "invariants": (
                tuple(e for _, e in self.invariants),
                list(self.invariant_names),
                Labels(len(self.invariants), lambda i: f"invariant {i}"),
                "Original constraints (drift), shape (..., i).",
            ),
        }
        for fname, (exprs, labels, _, _) in outputs.items():
            for expr, label in zip(exprs, labels, strict=True):
                check_supported(expr, f"model '{self.name}', {fname}: {label}")
        return outputs

    def jacobian_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """``(rows, cols)`` of the entries of ``d(f, g)/d(y, z)`` that are not identically zero.

        Read from each equation's free symbols (no differentiation), in row-major order; a
        solver evaluates, stores and factors only these.  Cached.
        """
        if "pattern" not in self._cache:
            unknowns = {v: j for j, v in enumerate((*self.states, *self.algebraics))}
            rows, cols = [], []
            for i, row in enumerate((*self.rhs, *self.g)):
                found = sorted(unknowns[v] for v in row.free_symbols if v in unknowns)
                rows += [i] * len(found)
                cols += found
            self._cache["pattern"] = (np.array(rows, dtype=np.int64), np.array(cols, dtype=np.int64))
        return self._cache["pattern"]

    @property
    def algebraic_index(self) -> tuple[int, ...]:
        """The index of each algebraic variable, as RADAU5 counts them (NIND1/NIND2): the highest
        index among the constraints that move it through z's iteration matrix H_z (rows ``g_z``
        at index 1, ``g_y f_z`` at index 2), not only the one matched to it.

        Structurally, z_j depends on the constraint matched to z_k when the graph "z_a -> z_b if
        z_b occurs in the iteration row matched to z_a" has a path from j to k (the pattern of
        H_z^-1).  In a mechanism ``M w - f + G^T lam = 0, G v = 0`` every w and lam is coupled to
        the velocity constraints and so has index 2, though most are matched to index-1 rows.
        Cached.
        """
        if "algebraic_index" not in self._cache:
            self._cache["algebraic_index"] = self._algebraic_index()
        return self._cache["algebraic_index"]

    def _algebraic_index(self) -> tuple[int, ...]:
        """:attr:`algebraic_index`, computed in O(nonzeros of H_z): one search per index level above 1."""
        levels = sorted({c.index for c in self.constraints})
        if not self.algebraics or len(levels) == 1:  # (every z has its constraints' one index: nothing read)
            return (levels[0] if levels else 1,) * len(self.algebraics)
        states = set(self.states)
        position = {v: k for k, v in enumerate(self.algebraics)}
        in_f = [{position[v] for v in f.free_symbols if v in position} for f in self.rhs]
        state_rows = {v: i for i, v in enumerate(self.states)}
        rows = []  # the algebraic variables in each constraint's iteration row
        for c in self.constraints:
            if c.index == 1:
                rows.append({position[v] for v in c.expr.free_symbols if v in position})
            else:  # g_y f_z: the z in the right-hand sides of the states in g
                found = set()
                for v in c.expr.free_symbols & states:
                    found |= in_f[state_rows[v]]
                rows.append(found)
        owner = list(self.determined_by)  # variable -> its constraint
        # z_j's index is the highest index of a constraint owning a z that j reaches: for each level, the
        # variables that reach one owned at that level or above are found backwards from those, once each
        reached_from = [[] for _ in self.algebraics]  # reached_from[b]: the a with an edge a -> b
        for a in range(len(self.algebraics)):
            for b in rows[owner[a]]:
                reached_from[b].append(a)
        index = [levels[0]] * len(self.algebraics)  # (each z reaches its own constraint, at levels[0] or above)
        for level in levels[1:]:
            stack = [k for k in range(len(self.algebraics)) if self.constraints[owner[k]].index >= level]
            seen = set(stack)
            while stack:
                for a in reached_from[stack.pop()]:
                    if a not in seen:
                        seen.add(a)
                        stack.append(a)
            for k in seen:
                index[k] = level
        return tuple(index)

    def column_colouring(self) -> np.ndarray:
        """A colour per column of ``d(f, g)/d(y, z)`` such that no two columns of one colour share a
        row (greedy, largest columns first): one forward-mode AD direction per colour recovers the
        Jacobian.  Cached."""
        if "colouring" not in self._cache:
            rows, cols = self.jacobian_pattern()
            D = len(self.states) + len(self.algebraics)
            by_column = [[] for _ in range(D)]
            for i, j in zip(rows, cols, strict=True):
                by_column[j].append(int(i))
            colour = np.full(D, -1, dtype=np.int64)
            taken = {}  # row -> colours used by the columns coloured so far
            for j in sorted(range(D), key=lambda j: -len(by_column[j])):
                used = set().union(*(taken.get(i, set()) for i in by_column[j]))
                c = next(k for k in range(D + 1) if k not in used)
                colour[j] = c
                for i in by_column[j]:
                    taken.setdefault(i, set()).add(c)
            colour[colour < 0] = 0
            self._cache["colouring"] = colour
        return self._cache["colouring"]

    def _jacobian_output(self):
        """The nonzero entries of ``d(f, g)/d(y, z)`` (see :meth:`jacobian_pattern`), or None if a
        derivative is not emittable or there are more than :data:`SYMBOLIC_JACOBIAN_MAX_ENTRIES`
        (solvers then use forward-mode AD over the pattern's column colouring).  Each equation is
        differentiated only by the variables in it."""
        rows = [*self.rhs, *self.g]
        unknowns = [*self.states, *self.algebraics]
        row_names = self.state_names + self.constraint_names
        labels, comments, exprs = [], [], []
        if len(self.jacobian_pattern()[0]) > SYMBOLIC_JACOBIAN_MAX_ENTRIES:
            return None
        for i, j in zip(*self.jacobian_pattern(), strict=True):
            expr = sp.diff(rows[i], unknowns[j])
            try:
                check_supported(expr, "jacobian")
            except UnsupportedFunctionError:
                return None
            exprs.append(expr)
            labels.append(f"d {row_names[i]} / d {unknowns[j].name}")
            comments.append(f"row {i}, column {j}")
        doc = "Jacobian d(f, g)/d(y, z): the entries of jacobian_pattern, shape (..., nnz)."
        return tuple(exprs), labels, comments, doc

    def torch_functions(self, dtype=None, device=None):
        """Batched torch callables ``f``, ``g``, ``aliases``, ``invariants`` (cached).

        Parameters
        ----------
        dtype : torch.dtype, default float64
        device : str or torch.device, default "cpu"

        Returns
        -------
        TorchFunctions
            ``tf.f(t, y, z, p=None)`` with ``t (...)``, ``y (..., n)``, ``z (..., m)``,
            ``p (..., k)`` broadcastable, returns ``(..., n)``; likewise ``g`` ``(..., m)``.
        """
        import torch

        dtype = torch.float64 if dtype is None else dtype
        device = torch.device("cpu" if device is None else device)
        key = ("torch", dtype, str(device))
        if key not in self._cache:
            specs = {}
            outputs = self._outputs()
            jacobian = self._jacobian_output()
            if jacobian is not None:
                outputs["jacobian"] = jacobian
            for fname, (exprs, _, comments, doc) in outputs.items():
                doc = f"{doc} Generated by daemodel."
                specs[fname] = torch_source(fname, exprs, comments, self.t, self._groups(), doc)
            parameters = torch.tensor(self.parameter_values.copy(), dtype=dtype, device=device)
            sizes = (len(self.states), len(self.algebraics), len(self.parameters))
            pattern = self.jacobian_pattern() if jacobian is not None else None
            self._cache[key] = build_torch_functions(specs, sizes, parameters, self.name, pattern)
        return self._cache[key]

    def casadi_jacobian_pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """The rows and columns of the nonzeros of ``[f_y f_z; g_y g_z]``: casadi's structural sparsity of
        :meth:`casadi_dae`'s equations (no function is built; within :meth:`jacobian_pattern`'s), made once."""

        def build():
            import casadi

            dae = self.casadi_dae()
            equations, unknowns = casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(dae["x"], dae["z"])
            rows, cols = casadi.jacobian_sparsity(equations, unknowns).get_triplet()
            # (int32 where every index fits: half of the pattern's bytes, 2.4 MB at 10^5 unknowns, held with the
            # model; a product such as rows * D + cols must then be made in int64: D^2 passes 2^31 at 46,341)
            index = np.int32 if unknowns.numel() <= np.iinfo(np.int32).max else np.int64
            return np.asarray(rows, dtype=index), np.asarray(cols, dtype=index)

        return self.cached("jacobian-pattern", build)

    def casadi_dae(self) -> dict:
        """casadi's DAE dict ``{"x", "z", "p", "t", "ode", "alg"}`` of this system (SX).

        For casadi's integrators the system must have index 1: use
        ``c.reduced(index=1).casadi_dae()``.  Made once and kept with the model (the conversion from
        sympy cost casadi-idas 1-7 ms of setup on every call); each call returns a new dict of it.
        """
        return dict(self.cached("casadi_dae", self._make_casadi_dae))

    def _make_casadi_dae(self) -> dict:
        import casadi

        names = local_names(self._groups())  # (identifiers, never a user's string: u[3] is u_3)

        def column(symbols):
            return casadi.vertcat(*[casadi.SX.sym(names[s]) for s in symbols]) if symbols else casadi.SX(0, 1)

        x, z, p, t = column(self.states), column(self.algebraics), column(self.parameters), casadi.SX.sym("t")
        table = {self.t: t}
        for symbols, vector in ((self.states, x), (self.algebraics, z), (self.parameters, p)):
            # (vertsplit: one call for the elements, where vector[i] costs ~5 us each at 10^5)
            table.update(zip(symbols, casadi.vertsplit(vector) if symbols else (), strict=True))
        convert = CasadiConverter(table)
        outputs = self._outputs()
        both = convert.stack([*outputs["f"][0], *outputs["g"][0]])  # (one conversion: shared parts made once)
        ode, alg = casadi.vertsplit(both, [0, len(self.states), len(self.states) + len(self.algebraics)])
        return {"x": x, "z": z, "p": p, "t": t, "ode": ode, "alg": alg}

    # ---- report -------------------------------------------------------------------------
    def report(self, full: bool = False) -> str:
        """A human-readable account: variables, equations, index per constraint, switches, init, pruning.

        Parameters
        ----------
        full : bool
            List every entry.  By default a run of more than 50 entries of a section (an array's
            elements, or consecutive scalar names) shows its first three, a line counting the
            others, and its last (:mod:`daemodel.compiling.report`).
        """
        from daemodel.compiling.report import report

        return report(self, full)

    def __repr__(self) -> str:
        return (
            f"CompiledDAE({self.name!r}, index={self.index}, states={self.state_names}, "
            f"algebraics={self.algebraic_names}, parameters={self.parameter_names})"
        )
