"""The result type every method returns."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sympy as sp

from daemodel.declaring.arrays import compact_listing, element_name, element_names, split_element
from daemodel.errors import ComparisonError, SolutionFileError, UnknownSymbolError
from daemodel.files import (
    memory_limit,
    open_file,
    readable_path,
)
from daemodel.instants import TIME_MATCH_RTOL
from daemodel.stats import Stats


class Columns(Mapping):
    """``Solution.values`` as a backend makes it: each variable's values, by name, a view of one read-only block
    ``(variables, B, T)`` made when it is read (a dict of views held 1.5 MB of array objects at 10^4 unknowns,
    beside 0.88 MB of values: issue 44); names added later (the aliases) hold their own arrays."""

    def __init__(self, names: tuple, block: np.ndarray):
        if len(names) != len(block):
            raise ValueError(f"{len(names)} names for {len(block)} variables' values")
        self.names, self.block, self.added, self._index = tuple(names), block, {}, None

    def _position(self, name) -> int | None:
        if self._index is None:  # (made at the first read by name, not by the solve)
            self._index = {known: i for i, known in enumerate(self.names)}
        return self._index.get(name)

    def __getitem__(self, name) -> np.ndarray:
        if name in self.added:
            return self.added[name]
        i = self._position(name)
        if i is None:
            raise KeyError(name)
        return self.block[i]

    def __setitem__(self, name, values: np.ndarray) -> None:
        if self._position(name) is not None:
            raise ValueError(f"{name!r} has values already")
        self.added[name] = values

    def __contains__(self, name) -> bool:
        return name in self.added or self._position(name) is not None

    def __iter__(self):
        yield from self.names
        yield from self.added

    def __len__(self) -> int:
        return len(self.names) + len(self.added)

    def arrays(self) -> list:  # (the arrays it holds, not a view per name)
        return [self.block, *self.added.values()]


@dataclass(frozen=True, eq=False)
class Solution:
    """Values of every variable, by name, on a time grid, for one sample or a batch.

    Attributes
    ----------
    t : ndarray, shape (T,)
    method : str
        The backend that produced it.
    settings : dict
        The method's options as used (after defaults).
    solve_time : float
        Seconds the method spent producing the values from a ready method: integration for the
        classical solvers, evaluating the trained networks for ``pinn``.
    setup_time : float
        Seconds the method spent getting ready for this solve, apart from ``solve_time``: code
        generation and engine construction (radau), building casadi's integrator
        (casadi-collocation, casadi-idas), the model's numeric functions (reference), training
        (pinn).  What an earlier call left cached on the compiled model (code, casadi functions,
        index reductions) is not charged again.  torch's first use in the process (its import and
        first operations, 1-4 s) is charged to the setup of the torch solve that pays it
        (``stats["torch_warm_up_seconds"]``, 0 afterwards).  Initial-value checks are in neither clock.
        With ``sensitivities=``, generating their numeric Jacobians (once per model) is setup and the
        sensitivity pass is solve time (``stats["sensitivity_seconds"]``).
    stats : dict
        Method counters: steps, rejected steps, Newton iterations, Jacobians, ...
    compiled : CompiledDAE
        The system that was solved (after any index reduction the method needed).
    parameters : ndarray, shape (B, k)
    batched : bool
        Whether values keep a leading batch axis.
    status : str
        ``"success"`` when the method met its own accuracy criterion; otherwise what the user
        must know to trust the values (e.g. a Radau-PINN trained on a fixed budget states its
        final residual).  Shown by ``repr``.
    breakpoints : dict
        For a model with time switches (:mod:`daemodel.solving.switches`): ``"t"``, the breakpoints each
        sample's solve was cut at (B, K), and ``"before"``/``"after"``, each variable's values
        just before and just after each, name -> (B, K); NaN-padded where the samples of a batch
        switch at different times and some less often; ``"moved"``, how far the states were
        projected at each (B, K), 0 unless a switch inside a constraint moved its solution set.
        Values at a breakpoint in ``t`` are those after it.  Empty without time switches.
    events : dict
        For a model with declared events (``Model.event``): for each event's name, ``"t"`` its times
        (B, K), ``"before"``/``"after"`` each variable's values just before and after (name ->
        (B, K)) and ``"moved"`` how far the states were projected onto the constraints after the
        reset (B, K); NaN-padded across a batch.  Values at an event time in ``t`` are those after it.
    dense : AbstractDenseOutput or None
        The method's own continuous solution between the output times (:mod:`daemodel.dense`), which
        :meth:`at` evaluates: radau's and the Radau-PINN's collocation polynomials, ...; None where
        the method keeps none (then ``at()`` interpolates the outputs).  Saved by :meth:`save` where it
        is data (collocation polynomials), not where it runs the method again (the reference's, casadi's).
    sensitivities : dict
        With ``solve(..., sensitivities=[names])`` (radau): for each name, the derivatives of the
        states and algebraic variables at the output times with respect to it, ndarray (B, T, n+m);
        read them with :meth:`sensitivity`.  Empty otherwise.  Not saved by :meth:`save`.

    Examples
    --------
    >>> sol["y5"]            # (T,) or (B, T)
    >>> sol.errors(exact)    # {"y1": {"max": ..., "mean": ...}, ...}
    >>> sol.drift()          # {"invariant": max |g| along the solution}
    """

    t: np.ndarray
    values: Mapping = field(repr=False)  # (name -> (B, T): a dict, or a backend's Columns)
    method: str
    settings: dict
    solve_time: float
    stats: dict
    compiled: object = field(repr=False)
    parameters: np.ndarray = field(repr=False)
    batched: bool = False
    status: str = "success"
    setup_time: float = 0.0
    breakpoints: dict = field(default_factory=dict, repr=False)
    events: dict = field(default_factory=dict, repr=False)
    dense: object = field(default=None, repr=False)
    sensitivities: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.stats, Stats):
            object.__setattr__(self, "stats", Stats(self.stats))
        c = self.compiled
        if c.aliases and not set(c.alias_names) <= set(self.values):
            Y, Z, P, T = self._flat()
            numeric = c.numeric
            out = numeric.batch_function([e for _, e, _ in c.aliases])(T, Y, Z, P)
            shape = self.values[c.state_names[0]].shape
            for i, name in enumerate(c.alias_names):
                self.values[name] = out[:, i].reshape(shape)
        arrays = self.values.arrays() if isinstance(self.values, Columns) else self.values.values()
        for array in arrays:
            if array.flags.writeable:  # (a backend's views of one read-only block are already: 10^5 of them)
                array.flags.writeable = False
        self.t.flags.writeable = False

    # ---- access -------------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        """Every variable with values: states, algebraic variables, eliminated aliases."""
        c = self.compiled
        return (*c.state_names, *c.algebraic_names, *c.alias_names)

    @property
    def batch_size(self) -> int:
        return len(self.parameters)

    def __getitem__(self, name) -> np.ndarray:
        """Values of one variable, by its name or its symbol: shape (T,), or (B, T) for a batch.

        An array's name (``sol["u"]``, declared by ``m.states("u", 1000)``) gives all its elements,
        shape ``(*shape, T)`` (``(B, *shape, T)`` for a batch); an element's name (``sol["u[3]"]``,
        ``sol["T[3,4]"]``) or symbol gives one; an array of symbols (``sol[T[:, 0]]``) gives those.
        """
        if isinstance(name, np.ndarray):
            return self._gather(name)
        if isinstance(name, sp.Symbol):
            name = name.name
        if not isinstance(name, str):
            raise UnknownSymbolError(
                f"a solution is indexed by a variable's name or symbol (e.g. sol['x']); got {type(name).__name__}"
            )
        if name not in self.values:
            return self._array(name)
        values = self.values[name]
        return values if self.batched else values[0]

    def _array(self, name: str) -> np.ndarray:
        """``sol[name]`` for an array's name or an element's (``"T[3, 4]"`` with spaces too), else the
        error naming what is wrong: no such variable, an index out of range, a pruned element."""
        shapes = self.compiled.arrays
        if name in shapes:
            return self._gather(np.array(element_names(name, shapes[name]), dtype=object).reshape(shapes[name]))
        parts = split_element(name)
        if parts is not None and parts[0] in shapes:
            element = element_name(*parts, shapes[parts[0]], f"sol[{name!r}]")
            return self._gather(np.array(element, dtype=object))
        raise UnknownSymbolError(f"the solution has no variable {name!r}; it has [{compact_listing(self.names)}]")

    def _gather(self, names: np.ndarray) -> np.ndarray:
        """The values of an array of variables (names or symbols): shape ``(*names.shape, T)``, batch first."""
        flat = [n.name if isinstance(n, sp.Symbol) else n for n in names.flat]
        missing = [n for n in flat if not isinstance(n, str) or n not in self.values]
        if missing:
            pruned = [n for n in missing if isinstance(n, str) and n in self.compiled.dropped_names()]
            why = "pruned by compile(outputs=...): add them to outputs" if pruned == missing else "not variables of it"
            shown = ", ".join(repr(n) for n in missing[:5]) + (
                f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            )
            raise UnknownSymbolError(f"the solution has no values of {shown}: {why}")
        B, T = self.batch_size, len(self.t)
        out = np.empty((B, len(flat), T))
        for i, n in enumerate(flat):
            out[:, i] = self.values[n]
        out = out.reshape(B, *names.shape, T)
        out.flags.writeable = False
        return out if self.batched else out[0]

    def _flat(self):
        """States, algebraics, parameters and times flattened to (B*T, .) rows."""
        c = self.compiled
        B, T = self.batch_size, len(self.t)

        def stack(names):
            if not names:
                return np.zeros((B * T, 0))
            return np.stack([self.values[n].reshape(B * T) for n in names], axis=-1)

        P = np.repeat(self.parameters, T, axis=0)
        times = np.tile(self.t, B)
        return stack(c.state_names), stack(c.algebraic_names), P, times

    # ---- derivatives --------------------------------------------------------------------
    def sensitivity(self, output: str, name: str) -> np.ndarray:
        """``d output / d name`` at the output times, shaped like ``sol[output]``: the exact derivative
        of radau's discrete solution (:mod:`daemodel.sensitivities`).

        Parameters
        ----------
        output : str
            A state, algebraic variable or eliminated alias.
        name : str
            One of the parameters or states named in ``solve(..., sensitivities=[...])``.

        Raises
        ------
        SensitivityError
            When the solve computed none for ``name``.
        UnknownSymbolError
            For an output the solution does not have.
        """
        from daemodel.errors import SensitivityError

        if name not in self.sensitivities:
            asked = list(self.sensitivities)
            raise SensitivityError(
                f"the solution has no sensitivities with respect to {name!r}; "
                + (f"it has them for {asked}" if asked else "solve with sensitivities=[...] naming it")
            )
        if output not in self.values:
            raise UnknownSymbolError(f"the solution has no variable {output!r}; it has {list(self.names)}")
        c = self.compiled
        S = self.sensitivities[name]  # (B, T, n+m)
        kept = (*c.state_names, *c.algebraic_names)
        if output in kept:
            out = S[..., kept.index(output)]
        else:  # an alias: the chain rule through its expression
            from daemodel.sensitivities import alias_derivatives

            Y, Z, P, T = self._flat()
            B, K = self.batch_size, len(self.t)
            dw, dp = alias_derivatives(c, output, T, Y, Z, P)  # (B*K, n+m), (B*K, k)
            out = np.einsum("rd,rd->r", dw, S.reshape(B * K, -1)).reshape(B, K)
            if name in c.parameter_names:
                out = out + dp[:, c.parameter_names.index(name)].reshape(B, K)
        return out if self.batched else out[0]

    def gradient(self, objective, wrt) -> dict[str, float | np.ndarray]:
        """The gradient of a scalar objective of the outputs by the discrete adjoint of radau's steps:
        one backward pass whose cost does not grow with the number of names.

        Parameters
        ----------
        objective : dict or str or sympy expression
            A dict output name -> measured values shaped like ``sol[output]`` (NaN where missing):
            ``J = sum of (sol[output] - data)^2``; or an expression of the outputs (and ``t``),
            summed over the output times: ``J = sum_t phi(outputs(t))``.
        wrt : str or list of str
            Parameters and states (their initial values, moved consistently with the constraints).

        Returns
        -------
        dict name -> float, or ndarray (B,) for a batch (each sample's own J)

        Raises
        ------
        SensitivityError
            For a solution of another method or without step records, or names that are not free.
        ShapeError, UnknownSymbolError, ExpressionParseError
            For data of the wrong shape or an objective naming what the solution does not have.
        DataError
            For data that are not real numbers (strings, complex, bools), or a series NaN everywhere.
        """
        from daemodel.sensitivities import adjoint, objective_cotangent

        cotangent = objective_cotangent(self, objective)
        where, gradient = adjoint(self, cotangent, wrt)
        out = {name: gradient[:, q] for q, name in enumerate(where.names)}
        return out if self.batched else {name: float(v[0]) for name, v in out.items()}

    # ---- accuracy -----------------------------------------------------------------------
    def errors(self, reference, names=None) -> dict[str, dict[str, float]]:
        """Max and mean absolute error per variable against a reference, at the output times away from
        events and breakpoints (:meth:`error_report` measures those instants, and says how many times it
        left out).

        Parameters
        ----------
        reference : callable or Solution
            ``reference(t) -> dict name -> ndarray`` (shape (T,) or (B, T)), e.g.
            ``Problem.exact_solution()``, or a Solution: on the same times, or one with a dense
            output (:attr:`dense`) over a span that holds these times, evaluated at them
            (:meth:`at`); for another, re-solve it with ``t_eval=sol.t``.
        names : iterable of str, optional
            Variables to compare; default every variable both sides have.

        Returns
        -------
        dict name -> {"max": float, "mean": float}
            Over the output times, except those within the window of an event or breakpoint of
            either side (:mod:`daemodel.instants`): there one side may hold the value after
            a reset and the other the value before it; ``"max"`` takes in the errors at the instants
            too, each side's value just before (after) against the other's just before (after), so
            that an event located wrong shows here.
        """
        report = self.error_report(reference, names)
        out = {name: dict(values) for name, values in report.variables.items()}
        for instants in report.instants.values():
            for side in (instants.before, instants.after):
                for name, error in side.items():
                    if name in out and np.isfinite(error):
                        out[name]["max"] = max(out[name]["max"], float(error))
        return out

    def error_report(self, reference, names=None):
        """The errors against a reference on each side's own branch: the variables at the output times
        away from events and breakpoints, and the instants themselves (:mod:`daemodel.instants`).

        Parameters
        ----------
        reference, names
            As for :meth:`errors`.  A reference callable may state its events with an attribute
            ``events`` laid out as :attr:`events` (``Problem.exact_solution()`` does).

        Returns
        -------
        ErrorReport
            ``variables`` (what :meth:`errors` returns), ``instants`` (per event name and ``"time
            breakpoints"``: the counts on both sides, max ``|t_a - t_b|``, and each variable's max error
            just before and just after, each side at its own instant), ``excluded`` (output values left
            out of ``variables``) and ``window``.

        Raises
        ------
        ComparisonError
            As for :meth:`errors`; a reference callable whose ``events`` is not laid out as
            :attr:`events`.
        """
        from daemodel.instants import ErrorReport, measure, records_of

        wanted, ref_values = self._aligned_reference(reference, names)
        B = self.batch_size
        own = records_of(self, wanted, B, "solution")
        theirs = records_of(reference, wanted, B, "reference")
        keep, instants, window = measure(self.t, own, theirs, wanted, B)
        out = {}
        for name in wanted:
            ref = np.asarray(ref_values[name], dtype=float)
            diff = np.abs(self.values[name] - np.broadcast_to(ref, self.values[name].shape))[keep]
            out[name] = {
                "max": float(diff.max()) if diff.size else float("nan"),
                "mean": float(diff.mean()) if diff.size else float("nan"),
            }
        return ErrorReport(variables=out, instants=instants, excluded=int((~keep).sum()), window=window)

    def _aligned_reference(self, reference, names=None) -> tuple[list[str], dict]:
        """The variables to compare with ``reference`` and its values on this solution's times.

        Raises :class:`ComparisonError` for a Solution on other times without a dense output that
        covers them, anything that is neither
        a Solution nor a callable, or variables that one side lacks.
        """
        if isinstance(reference, Solution):
            span = max(abs(self.t[-1] - self.t[0]), 1.0)
            same = len(reference.t) == len(self.t) and np.max(np.abs(reference.t - self.t)) <= TIME_MATCH_RTOL * span
            inside = reference.t[0] <= self.t[0] and self.t[-1] <= reference.t[-1]
            if not same and reference.dense is not None and inside:  # (its own continuous solution at our times)
                ref_values = reference.at(self.t)
            elif not same:
                raise ComparisonError(
                    f"the reference ({reference.method}) has {len(reference.t)} times from {reference.t[0]:g} to "
                    f"{reference.t[-1]:g}, this solution ({self.method}) {len(self.t)} from {self.t[0]:g} to "
                    f"{self.t[-1]:g}"
                    + ("" if reference.dense is None else ", beyond the span of its dense output")
                    + "; solve the reference with t_eval=sol.t"
                )
            else:
                ref_values = {n: reference.values[n] for n in reference.names}
        elif callable(reference):
            ref_values = dict(reference(self.t))
        else:
            raise ComparisonError(
                f"errors() needs a Solution or a callable t -> dict of values; got {type(reference).__name__}"
            )
        wanted = list(names) if names is not None else [n for n in self.names if n in ref_values]
        missing = [n for n in wanted if n not in ref_values or n not in self.values]
        if missing or not wanted:
            raise ComparisonError(
                f"cannot compare {missing or 'anything'}: this solution has {list(self.names)}, "
                f"the reference has {sorted(ref_values)}"
            )
        return wanted, ref_values

    def drift(self) -> dict[str, float]:
        """Max ``|g|`` of each original constraint (and hidden position/velocity level) along the solution."""
        c = self.compiled
        Y, Z, P, T = self._flat()
        numeric = c.numeric
        values = numeric.batch_function([e for _, e in c.invariants])(T, Y, Z, P)
        return {name: float(np.max(np.abs(values[:, i]))) for i, name in enumerate(c.invariant_names)}

    # ---- between the output times ---------------------------------------------------------
    def _switch_records(self) -> list[dict]:
        """The breakpoint record and each event's: ``"t"`` (B, K) and the values before and after."""
        return ([self.breakpoints] if self.breakpoints else []) + list(self.events.values())

    def _check_memory_of_at(self, K: int) -> None:
        """Refuse ``at()`` at ``K`` times whose values and their evaluation would not fit (before allocating)."""
        from daemodel.errors import ResourceLimitError

        unknowns = len(self.compiled.states) + len(self.compiled.algebraics)
        stages = int(self.settings.get("stages", 3) or 3) if isinstance(self.settings, dict) else 3
        # (the values, and the dense output's work arrays: a polynomial's nodes per time)
        need = 8 * K * self.batch_size * unknowns * (stages + 3)
        limit = memory_limit()
        if need > limit:
            raise ResourceLimitError(
                f"at(): {K} times of {self.batch_size} sample(s) and {unknowns} unknowns would need about "
                f"{need / 2**30:.3g} GiB, beyond the {limit / 2**30:.3g} GiB allowance; ask for fewer times at once"
            )

    def at(self, times) -> dict[str, np.ndarray]:
        """Values at ``times`` inside the solution's span, by name: (len(times),) or (B, len(times)).

        Where the method keeps a dense output (:attr:`dense`: radau's collocation polynomials, the
        Radau-PINN's), it is evaluated: the values are those ``solve(..., t_eval=times)`` would give,
        at the method's own accuracy, across breakpoints and events too (a time on one takes the
        values after it); where it is marked ``resolves_algebraic`` (adaptive radau on a system of index
        2 or 3), its algebraic variables are solved from its states, as the method did at its outputs.
        Otherwise the states are interpolated by cubic Hermite polynomials through the two nearest
        points of the time's piece, with the derivatives ``f(t, y, z)`` there:
        the adjacent output times, or a breakpoint or event between them, with its values before it
        (on its left) or after it (on its right), so that no interpolant spans one (an error of O(dt^4)
        in the output spacing dt on top of the method's); the algebraic variables are solved from the
        constraints that determine them at the interpolated states (Newton from their linear
        interpolation).  At the output times every value is the solution's own.

        Raises
        ------
        InvalidValueError
            For times that are not real numbers (strings, bools, complex), outside the solution's span,
            or not finite.
        InitialisationError
            Without a dense output, or with one marked ``resolves_algebraic``: the algebraic variables
            cannot be solved at an interpolated state.
        """
        from daemodel.errors import InvalidValueError
        from daemodel.reals import real_array

        times = np.atleast_1d(real_array(times, "at(): times"))  # ("0.5" and True are no times)
        t = self.t
        if times.ndim != 1:
            raise InvalidValueError(f"at(): times must be a 1-d array; got shape {times.shape}")
        if not np.isfinite(times).all():
            raise InvalidValueError(f"at(): times must be finite; got {times[~np.isfinite(times)][0]}")
        self._check_memory_of_at(len(times))
        outside = (times < t[0]) | (times > t[-1])
        if outside.any():
            raise InvalidValueError(
                f"at(): t = {times[outside][0]:g} is outside the solution's span [{t[0]:g}, {t[-1]:g}]; solve "
                "over a span that contains it"
            )
        c = self.compiled
        B, n, m, K = self.batch_size, len(c.states), len(c.algebraics), len(times)
        if self.dense is not None:
            u = self.dense(times)
            y, z = u[..., :n], u[..., n:]
            if self.dense.resolves_algebraic and m:
                z = self._algebraic_from_states(times, y, z)
        else:
            y, z = self._hermite(times)
        out = {name: y[..., i] for i, name in enumerate(c.state_names)}
        out.update({name: z[..., j] for j, name in enumerate(c.algebraic_names)})
        if c.aliases:
            values = c.numeric.batch_function([e for _, e, _ in c.aliases])(
                np.tile(times, B), y.reshape(B * K, n), z.reshape(B * K, m), np.repeat(self.parameters, K, axis=0)
            )
            out.update({name: values[:, i].reshape(B, K) for i, name in enumerate(c.alias_names)})
        return out if self.batched else {name: v[0] for name, v in out.items()}

    def _algebraic_from_states(self, times: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The algebraic variables (B, K, m) solved from the dense output's states ``y`` (B, K, n) at ``times``,
        from its values ``z``, as the method solved them at its outputs (``dense.resolves_algebraic``)."""
        from daemodel.compiling.algebraic import algebraic_from_states
        from daemodel.errors import InitialisationError

        found = algebraic_from_states(self.compiled, times, y, z, self.parameters)
        finite = np.isfinite(y).all(axis=2)  # (NaN after a sample's terminal event: kept)
        failed = ~found.converged & finite
        if failed.any():
            sample, k = np.argwhere(failed)[0]
            raise InitialisationError(
                f"at(): the algebraic variables could not be solved at t = {times[k]:g} (sample {sample}) from the "
                "states of the dense output; ask for that time with solve(..., t_eval=...)"
            )
        return found.z

    def columns_at(self, times: np.ndarray, names) -> np.ndarray:
        """The states and algebraic variables ``names`` of the first sample at ``times`` inside the span,
        ``(len(times), len(names))``: read straight off :attr:`dense` where it holds them (no checks: the
        times are the caller's own, such as an event search's; where it is marked ``resolves_algebraic``,
        the algebraic variables solved from its states, as :meth:`at` gives them, or its own where that
        fails), else through :meth:`at`."""
        c = self.compiled
        position = {v: k for k, v in enumerate((*c.state_names, *c.algebraic_names))}
        if self.dense is not None and all(v in position for v in names):
            times = np.asarray(times, dtype=float)
            u = self.dense(times)[:1]
            n = len(c.states)
            if self.dense.resolves_algebraic and any(position[v] >= n for v in names):
                from daemodel.compiling.algebraic import algebraic_from_states

                u = u.copy()
                u[..., n:] = algebraic_from_states(c, times, u[..., :n], u[..., n:], self.parameters[:1]).z
            return u[0][:, [position[v] for v in names]]
        values = self.at(times)
        columns = [np.reshape(values[v], (self.batch_size, -1))[0] for v in names]
        return np.stack(columns, axis=-1) if columns else np.zeros((len(np.atleast_1d(times)), 0))

    def _hermite(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(y (B, K, n), z (B, K, m))`` at ``times`` from the outputs and the switches' values (see :meth:`at`)."""
        from daemodel.compiling.init import solve_algebraic
        from daemodel.errors import InitialisationError

        t, c = self.t, self.compiled
        numeric = c.numeric
        Y, Z, _, _ = self._flat()
        B, n, m, K = self.batch_size, len(c.states), len(c.algebraics), len(times)
        U = np.concatenate([Y.reshape(B, len(t), n), Z.reshape(B, len(t), m)], axis=2)
        k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)  # interval of each time
        # each time's piece: the outputs around it, or a switch between them (its values after it on the
        # left, before it on the right); a time on a switch is the piece after it
        left_t, right_t = np.tile(t[k], (B, 1)), np.tile(t[k + 1], (B, 1))  # (B, K)
        left, right = U[:, k], U[:, k + 1]  # (B, K, n+m), copies
        names = [*c.state_names, *c.algebraic_names]
        for record in self._switch_records():
            switch_times = np.asarray(record["t"], dtype=float)
            for j in range(switch_times.shape[1]):
                at = switch_times[:, j, None]  # (B, 1); NaN (a batch's padding) compares False
                before = np.stack([np.asarray(record["before"][v], dtype=float)[:, j] for v in names], axis=-1)
                after = np.stack([np.asarray(record["after"][v], dtype=float)[:, j] for v in names], axis=-1)
                on_left = (at > left_t) & (at <= times)
                on_right = (at <= right_t) & (at > times)
                left_t, right_t = np.where(on_left, at, left_t), np.where(on_right, at, right_t)
                left = np.where(on_left[..., None], after[:, None], left)
                right = np.where(on_right[..., None], before[:, None], right)
        rhs = numeric.batch_function(list(c.rhs))
        rows_p = np.repeat(self.parameters, K, axis=0)

        def slope(when, values):
            return rhs(
                when.reshape(B * K), values[..., :n].reshape(B * K, n), values[..., n:].reshape(B * K, m), rows_p
            )

        step = right_t - left_t
        s = np.divide(times - left_t, step, out=np.zeros_like(step), where=step > 0)[..., None]  # (B, K, 1)
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        dt = step[..., None]
        y = (
            h00 * left[..., :n]
            + h10 * dt * slope(left_t, left).reshape(B, K, n)
            + h01 * right[..., :n]
            + h11 * dt * slope(right_t, right).reshape(B, K, n)
        )
        z = (1 - s) * left[..., n:] + s * right[..., n:]
        if m:
            determining = [constraint.determining for constraint in c.constraints]
            H, Hz = numeric.batch_function(determining), numeric.newton_jacobian(determining, c.algebraics)
            rows_t, rows_y = np.tile(times, B), y.reshape(B * K, n)
            result = solve_algebraic(
                lambda x: H(rows_t, rows_y, x, rows_p), lambda x: Hz(rows_t, rows_y, x, rows_p), z.reshape(B * K, m)
            )
            if not result.converged.all():
                row = int(np.flatnonzero(~result.converged)[0])
                raise InitialisationError(
                    f"at(): the algebraic variables could not be solved at t = {times[row % K]:g} (sample {row // K}) "
                    "from the interpolated states; ask for that time with solve(..., t_eval=...)"
                )
            # at an output or switch time itself, the method's own algebraic values (its z may differ from
            # the constraints' root at its y by the method's algebraic error)
            z = np.where(s == 0, left[..., n:], np.where(s == 1, right[..., n:], result.x.reshape(B, K, m)))
        return y, z

    # ---- files --------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the solution to ``path`` (numpy's ``.npz``; no pickled objects): times, values,
        parameters, method, settings, clocks, stats (their arrays as arrays), status, breakpoints,
        events, the dense output where it is data (radau's and the Radau-PINN's collocation
        polynomials, in their pieces; a method's restarts are not: the loaded solution's :meth:`at`
        interpolates within each piece between breakpoints and events) and the model's fingerprints
        (equations, events, parameter values).  Read it back with :meth:`load` and the model."""
        from daemodel.solution_files import write

        return write(self, path)

    @classmethod
    def load(cls, path, model) -> Solution:
        """Read a solution written by :meth:`save` for ``model`` (a Model or a CompiledDAE with the
        same equations, names, events and parameter values; an index-3 model may be given for a
        solution of its reduction).

        Raises
        ------
        SolutionFileError
            No file, not a daemodel solution file, a damaged field (named), or a model whose
            equations, events or parameter values differ from the solved one's (each named).
        """
        from daemodel.solution_files import read

        path = readable_path(path, "Solution.load: path", SolutionFileError)
        if not path.exists():
            raise SolutionFileError(f"no solution file at {path}")
        with open_file(path, "path", SolutionFileError) as handle:
            return read(handle, path, model, cls)

    # ---- export -------------------------------------------------------------------------
    def to_pandas(self):
        """A DataFrame with a column ``t``, a column ``sample`` for a batch, and one per variable."""
        import pandas as pd

        B, T = self.batch_size, len(self.t)
        columns = {}
        if self.batched:
            columns["sample"] = np.repeat(np.arange(B), T)
        columns["t"] = np.tile(self.t, B)
        for name in self.names:
            columns[name] = self.values[name].reshape(B * T)
        return pd.DataFrame(columns)

    def plot(self, path=None, names=None, reference=None):
        """Plot each variable against t (one panel each); a batch shows up to 20 samples.

        Drawn from the dense output (:meth:`at`, the method's accuracy) on a fine grid, or the output
        points where there is none; broken at every event and breakpoint (each side's limit shown),
        whose times are marked on the time axis (:mod:`daemodel.plotting`).

        Parameters
        ----------
        path : str or Path, optional
            Write the figure there (PNG, PDF, ... by suffix).
        names : iterable of str, optional
            Variables to draw, all of them.  Default: the states, then the algebraic variables, at
            most :data:`~daemodel.plotting.PLOTTED_PANELS` (12) of them; where more were left out, the figure's title
            says how many and an :class:`~daemodel.errors.OmittedPanelsWarning` names them.
        reference : callable or Solution, optional
            Drawn dashed on top (first sample only for a batch), broken at the instants it states.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from daemodel.plotting import plot_solution

        return plot_solution(self, path, names, reference)

    def __repr__(self) -> str:
        batch = f", batch={self.batch_size}" if self.batched else ""
        return (
            f"Solution({self.compiled.name!r}, method={self.method!r}, t=[{self.t[0]:g}, {self.t[-1]:g}] "
            f"({len(self.t)} points){batch}, solve_time={self.solve_time:.3g} s, setup_time={self.setup_time:.3g} s, "
            f"status={self.status!r})"
        )
