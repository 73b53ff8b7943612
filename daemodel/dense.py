"""Dense output: a method's own continuous solution between its output times.

A :class:`~daemodel.solution.Solution` keeps one of these in ``Solution.dense`` where its method
has one, and :meth:`~daemodel.solution.Solution.at` evaluates it:

* :class:`CollocationPolynomials`: Radau IIA's (``method="radau"``, the Radau-PINN): on each
  step ``[t_n, t_n + h]`` the polynomial of degree s through the step's start ``u_n`` at
  ``theta = 0`` and its stage values ``U_i`` at ``theta = c_i``, for the states and the algebraic
  variables alike.  It is what collocation solves for: the states' polynomial meets the
  differential equations at the nodes, and its error between them is of the stage order, O(h^(s+1))
  for the states (O(h^s) for an index-2 algebraic variable, the order of its end values) where the
  step ends are O(h^(2s-1)); so it is as accurate as ``t_eval`` asking radau for the same times
  (it is the same evaluation).
* :class:`Segments`: the dense outputs of a solve cut at breakpoints or events, one after the
  other in time (a time shared by two is the later one's: values after the switch).
* :class:`Groups`: the dense outputs of groups of a batch's samples solved apart (samples whose
  parameters move the breakpoints, events), row by row.
* :class:`Held`: the values after a terminal event, at its time.
* :class:`Deferred`: one made on the first query (a trained surrogate's).
* :class:`Restarts`: for a method whose own interpolant is out of reach (the reference), the method
  started again from the output before each time.

Each evaluates ``(B, K, n+m)`` values at ``K`` ascending or unordered times inside its span, in the
order of the solved system's states then algebraic variables.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from daemodel.collocation import lagrange_matrix

# A time that a step's end misses by less than this, relative to the step, belongs to that step:
# step ends summed as t + h differ from the grid's t_{n+1} in the last bits.
END_MATCH_RTOL = 1e-13
# A step's nodes (B (s+1) (n+m) entries) from which the dense output reads each step's points apart
# (:func:`collocation_values`): below, the Python loop over steps costs more than the gathered copy it saves;
# above, the copy is the solve's peak (4.8 MB at 10^4 unknowns, s = 5, 10 steps: 1.5x the factors' bytes)
NODES_PER_STEP_LOOP = 10_000


def step_owners(starts: np.ndarray, lengths: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(step, theta)`` of each time: the step whose interval holds it (a step's end its own, not the
    next one's start) and where in it, ``theta = (t - t_n) / h`` in [0, 1]."""
    ends = starts + lengths * (1 + END_MATCH_RTOL)
    step = np.minimum(np.searchsorted(ends, times, side="left"), len(starts) - 1)
    return step, (times - starts[step]) / lengths[step]


def collocation_values(weights, owner: np.ndarray, nodes_of, xp, index, out=None):
    """The values at points owned by the steps ``owner`` (nondecreasing), shape (B, P, n+m): the Lagrange
    ``weights`` (P, s+1) of each point applied to its step's nodes, ``nodes_of(steps)`` (B, len(steps),
    s+1, n+m); ``index`` makes step indices the arrays' (a tensor for torch).  Where a step's nodes hold
    at least :data:`NODES_PER_STEP_LOOP` entries, each step's points take its nodes alone: the gathered
    (B, P, s+1, n+m) copy of all the points' nodes (48 MB a solve at 10^5 unknowns, 11 outputs) is not
    made; both ways are one ``einsum`` over the same subscripts.  ``out`` (numpy, (B, P, n+m)): each step's
    values written there, not gathered in parts and joined (two copies of the outputs, 17.6 MB at 10^5)."""
    changes = np.ones(len(owner), dtype=bool)  # (owner ascends: no np.unique, no search)
    changes[1:] = owner[1:] != owner[:-1]
    used = owner[changes]
    where = np.cumsum(changes) - 1
    first = nodes_of(used[:1])
    if first.shape[0] * first.shape[2] * first.shape[3] < NODES_PER_STEP_LOOP:
        values = xp.einsum("pj,bpjk->bpk", weights, nodes_of(used)[:, index(where)])
        if out is None:
            return values
        out[...] = values
        return out
    bounds = np.searchsorted(where, np.arange(len(used) + 1))
    parts = []
    for u, (a, b) in enumerate(itertools.pairwise(bounds)):
        nodes = first if u == 0 else nodes_of(used[u : u + 1])  # (B, 1, s+1, n+m): the step's own block
        first = None  # (not held through the loop)
        # (its nodes seen b - a times, a view: a gathered copy of them a point was the first solve's peak, 0.96 MB
        # for a step of two outputs at 10^4 unknowns, s = 5)
        seen = xp.broadcast_to(nodes, (nodes.shape[0], b - a, *nodes.shape[2:]))
        if out is None:
            parts.append(xp.einsum("pj,bpjk->bpk", weights[a:b], seen))
        else:
            np.einsum("pj,bpjk->bpk", weights[a:b], seen, out=out[:, a:b])
    return out if out is not None else xp.concatenate(parts, axis=1)


def outputs_before(outputs: np.ndarray, values: np.ndarray, times: np.ndarray) -> tuple:
    """``(before, at_outputs, inside)`` for ``times`` among ``outputs`` (T,): the index of the output at
    or before each time, the values (B, K, n+m) there, and which times lie strictly after it (a
    restart's to solve; the others are outputs, their own values)."""
    before = np.clip(np.searchsorted(outputs, times, side="right") - 1, 0, len(outputs) - 1)
    return before, values[:, before].copy(), times > outputs[before]


class AbstractDenseOutput(ABC):
    """A continuous solution over a solve's span: ``(B, K, n+m)`` values at any ``K`` times inside."""

    # whether reading it solves again (a method started again from an output): costly to read often
    solves_again = False
    # whether :meth:`Solution.at` solves the algebraic variables from its states, as the method did at its
    # outputs (adaptive radau on index 2: daemodel.compiling.algebraic), instead of reading them off it
    resolves_algebraic = False

    @abstractmethod
    def __call__(self, times: np.ndarray) -> np.ndarray: ...

    @property
    @abstractmethod
    def description(self) -> str:
        """What it evaluates, in words (``sol.dense.description``: what ``sol.at()`` answers with)."""


@dataclass(frozen=True, eq=False)
class CollocationPolynomials(AbstractDenseOutput):
    """Each step's collocation polynomial (see the module docstring).

    Attributes
    ----------
    c : ndarray, shape (s,)
        The tableau's nodes (Radau IIA: ``c_s = 1``, so ``theta = 1`` gives the step's end value).
    starts, lengths : ndarray, shape (S,)
        Each step's start time and length, ascending.
    nodes : ndarray, shape (B, S, s+1, n+m)
        Each step's start value, then its stage values.
    resolves_algebraic : bool
        The algebraic variables are to be solved from the states (see :class:`AbstractDenseOutput`):
        adaptive radau's on a system of index 2 or more, whose polynomials read them to order s only.
    """

    c: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray
    nodes: np.ndarray
    resolves_algebraic: bool = False

    @property
    def description(self) -> str:
        return f"each step's collocation polynomial (degree {len(self.c)})"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        step, theta = step_owners(self.starts, self.lengths, times)
        # the product form of the Lagrange weights: exact at the nodes (a weight of 1 and zeros)
        weights = lagrange_matrix(np.concatenate([[0.0], self.c]), theta)  # (K, s+1)
        return np.einsum("kj,bkjd->bkd", weights, self.nodes[:, step].astype(float, copy=False))

    @staticmethod
    def joined(blocks: list) -> CollocationPolynomials:
        """The polynomials of consecutive blocks of one solve's steps (one tableau), one after another."""
        if len(blocks) == 1:
            return blocks[0]
        if not all(np.array_equal(b.c, blocks[0].c) for b in blocks):
            raise ValueError("CollocationPolynomials.joined: blocks of one tableau only")  # (daemodel's own bug)
        return CollocationPolynomials(
            c=blocks[0].c,
            starts=np.concatenate([b.starts for b in blocks]),
            lengths=np.concatenate([b.lengths for b in blocks]),
            nodes=np.concatenate([b.nodes for b in blocks], axis=1),
            resolves_algebraic=blocks[0].resolves_algebraic,
        )


@dataclass(frozen=True, eq=False)
class Segments(AbstractDenseOutput):
    """Dense outputs of consecutive intervals ``[edges[k], edges[k+1]]``: a time on an inner edge is
    the later segment's (the values after a breakpoint or event)."""

    edges: np.ndarray
    pieces: tuple

    @property
    def description(self) -> str:
        return f"{self.pieces[0].description}, in {len(self.pieces)} segments"

    @property
    def solves_again(self) -> bool:
        return any(piece.solves_again for piece in self.pieces)

    @property
    def resolves_algebraic(self) -> bool:
        return any(piece.resolves_algebraic for piece in self.pieces)

    def __call__(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        segment = np.clip(np.searchsorted(self.edges, times, side="right") - 1, 0, len(self.pieces) - 1)
        out = None
        for k in np.unique(segment):
            where = np.flatnonzero(segment == k)
            values = self.pieces[k](times[where])
            if out is None:
                out = np.empty((values.shape[0], len(times), values.shape[2]))
            out[:, where] = values
        return out


@dataclass(frozen=True, eq=False)
class Groups(AbstractDenseOutput):
    """Dense outputs of groups of samples, ``(sample indices, dense output)``, solved apart over the
    same span: their rows in sample order."""

    groups: tuple
    samples: int
    # each group's last time where it ended early (a terminal event), else None: NaN after it
    ends: tuple | None = None

    @property
    def description(self) -> str:
        return self.groups[0][1].description

    @property
    def solves_again(self) -> bool:
        return any(dense.solves_again for _, dense in self.groups)

    @property
    def resolves_algebraic(self) -> bool:
        return any(dense.resolves_algebraic for _, dense in self.groups)

    def __call__(self, times: np.ndarray) -> np.ndarray:
        out = None
        for k, (index, dense) in enumerate(self.groups):
            end = None if self.ends is None else self.ends[k]
            values = dense(np.minimum(times, end) if end is not None else times)
            if out is None:
                out = np.empty((self.samples, values.shape[1], values.shape[2]))
            if end is not None:
                values[:, times > end] = np.nan  # (the samples ended there)
            out[index] = values
        return out


@dataclass(frozen=True, eq=False)
class Held(AbstractDenseOutput):
    """The values ``(B, n+m)`` at one time: where a solve ends at a terminal event, those after it."""

    t: float
    values: np.ndarray

    @property
    def description(self) -> str:
        return "the values after a terminal event"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        return np.repeat(self.values[:, None], len(np.atleast_1d(times)), axis=1)


@dataclass(frozen=True, eq=False)
class Restarts(AbstractDenseOutput):
    """A method started again from the output before each time asked for, with the solve's options, to
    that time: for methods whose own interpolant is out of reach (the reference's integrators step
    past the outputs and keep no polynomial of their steps).  One solve per interval of outputs that
    holds times (past the last output, on from it); an output time itself is the solve's own value.
    ``times`` must start at the solve's t0 (the backend puts each sample's start there).

    Attributes
    ----------
    backend, compiled, options
        The method, the system it solved and its options (``t_eval`` is replaced per interval).
    times : ndarray, shape (T,)
    values : ndarray, shape (B, T, n+m)
    parameters : ndarray, shape (B, k)
    """

    backend: object
    compiled: object
    options: object
    times: np.ndarray
    values: np.ndarray
    parameters: np.ndarray
    solves_again = True

    @property
    def description(self) -> str:
        return f"{self.backend.name} started again from the output before each time"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        import dataclasses

        from daemodel.compiling.initial_states import InitialStates

        times = np.asarray(times, dtype=float)
        n = len(self.compiled.states)
        before, out, inside = outputs_before(self.times, self.values, times)
        for k in np.unique(before[inside]):
            where = np.flatnonzero(inside & (before == k))
            # (past the last output, a piece that ends at an event: on from it to the latest time asked for)
            a = float(self.times[k])
            b = float(self.times[k + 1]) if k + 1 < len(self.times) else float(times[where].max())
            start = InitialStates(
                y0=self.values[:, k, :n].copy(), z0=self.values[:, k, n:].copy(), p=self.parameters, batched=True
            )
            model = dataclasses.replace(self.compiled, t0=a)
            options = dataclasses.replace(self.options, t_eval=np.unique(times[where]))
            sol = self.backend.solve(model, (a, b), start, options)
            names = (*self.compiled.state_names, *self.compiled.algebraic_names)
            found = np.stack([np.reshape(sol.values[name], (len(start.y0), -1)) for name in names], axis=-1)
            out[:, where] = found[:, np.searchsorted(sol.t, times[where])]
        return out


@dataclass(frozen=True, eq=False)
class Deferred(AbstractDenseOutput):
    """A dense output made on the first query, by ``make()``, and kept: what a solve would otherwise
    pay for on every call whether or not anyone asks between its outputs (a trained surrogate's stage
    values, one more pass of its networks)."""

    make: object
    what: str
    _made: list = field(default_factory=list)

    @property
    def description(self) -> str:
        return self.what

    def __call__(self, times: np.ndarray) -> np.ndarray:
        if not self._made:
            self._made.append(self.make())
        return self._made[0](times)


def joined_in_time(edges, pieces) -> AbstractDenseOutput | None:
    """The :class:`Segments` of ``pieces`` (None where a piece has no dense output)."""
    if any(piece is None for piece in pieces):
        return None
    return pieces[0] if len(pieces) == 1 else Segments(np.asarray(edges, dtype=float), tuple(pieces))


def joined_by_samples(groups, samples: int, ends=None) -> AbstractDenseOutput | None:
    """The :class:`Groups` of ``(index, dense)`` pairs (None where a group has no dense output); ``ends``:
    each group's end where it ended before the others, else None."""
    if any(dense is None for _, dense in groups):
        return None
    return Groups(tuple(groups), samples, None if ends is None else tuple(ends))


# ---- in files ------------------------------------------------------------------------------------
def stored_dense(dense: AbstractDenseOutput | None):
    """``dense`` as plain data with arrays (``{"kind": ..., ...}``), for :meth:`Solution.save`; None
    where it is no data but a method run again (:class:`Restarts`, casadi's), which a file cannot hold.
    A :class:`Deferred` one is made first."""
    if isinstance(dense, Deferred):
        if not dense._made:
            dense._made.append(dense.make())
        dense = dense._made[0]
    if isinstance(dense, CollocationPolynomials):
        return {
            "kind": "collocation",
            "c": dense.c,
            "starts": dense.starts,
            "lengths": dense.lengths,
            "nodes": dense.nodes,
            "resolves_algebraic": bool(dense.resolves_algebraic),
        }
    if isinstance(dense, Held):
        return {"kind": "held", "t": float(dense.t), "values": np.asarray(dense.values)}
    if isinstance(dense, Segments):
        pieces = [stored_dense(piece) for piece in dense.pieces]
        return None if None in pieces else {"kind": "segments", "edges": dense.edges, "pieces": pieces}
    if isinstance(dense, Groups):
        pieces = [stored_dense(piece) for _, piece in dense.groups]
        if None in pieces:
            return None
        return {
            "kind": "groups",
            "samples": int(dense.samples),
            "indices": [np.asarray(index, dtype=np.int64).reshape(-1) for index, _ in dense.groups],
            "pieces": pieces,
            "ends": None if dense.ends is None else [None if end is None else float(end) for end in dense.ends],
        }
    return None


def dense_from_stored(data, samples: int, width: int) -> AbstractDenseOutput:
    """The dense output :func:`stored_dense` wrote, for ``samples`` rows of ``width`` unknowns, every
    array checked before use; a ValueError saying what is wrong otherwise."""

    def array(value, ndim: int, what: str, kind: str = "f") -> np.ndarray:
        if not isinstance(value, np.ndarray) or value.ndim != ndim or value.dtype.kind not in kind:
            raise ValueError(f"{what} is not an array of {ndim} axes")
        return value

    def number(value, what: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise ValueError(f"{what} is not a finite number")
        return float(value)

    def build(data, rows: int, where: str) -> AbstractDenseOutput:
        kind = data.get("kind") if isinstance(data, dict) else None
        if kind == "collocation":
            c, starts = array(data.get("c"), 1, f"{where}.c"), array(data.get("starts"), 1, f"{where}.starts")
            lengths, nodes = (
                array(data.get("lengths"), 1, f"{where}.lengths"),
                array(data.get("nodes"), 4, f"{where}.nodes"),
            )
            S = len(starts)
            if not S or len(lengths) != S or nodes.shape != (rows, S, len(c) + 1, width):
                raise ValueError(
                    f"{where}.nodes has shape {nodes.shape}; {rows} samples, {S} steps, {len(c)} stages and {width} "
                    f"unknowns make {(rows, S, len(c) + 1, width)}"
                )
            if not (np.isfinite(starts).all() and np.isfinite(lengths).all() and (lengths > 0).all()):
                raise ValueError(f"{where}: its steps are not finite, positive intervals")
            resolves = data.get("resolves_algebraic", False)  # (absent from files written before it)
            if not isinstance(resolves, bool):
                raise ValueError(f"{where}.resolves_algebraic is not True or False")
            return CollocationPolynomials(c, starts, lengths, nodes, resolves)
        if kind == "held":
            values = array(data.get("values"), 2, f"{where}.values")
            if values.shape != (rows, width):
                raise ValueError(f"{where}.values has shape {values.shape}, not {(rows, width)}")
            return Held(number(data.get("t"), f"{where}.t"), values)
        if kind == "segments":
            edges, pieces = array(data.get("edges"), 1, f"{where}.edges"), data.get("pieces")
            if not isinstance(pieces, list) or not pieces or len(edges) != len(pieces) + 1:
                raise ValueError(f"{where} does not hold one more edge than pieces")
            if not np.isfinite(edges).all() or (np.diff(edges) < 0).any():
                raise ValueError(f"{where}.edges is not a finite, ascending sequence")
            built = tuple(build(piece, rows, f"{where}.pieces[{k}]") for k, piece in enumerate(pieces))
            return Segments(edges, built)
        if kind == "groups":
            indices, pieces, ends = data.get("indices"), data.get("pieces"), data.get("ends")
            if data.get("samples") != rows or not isinstance(indices, list) or not isinstance(pieces, list):
                raise ValueError(f"{where} is not {rows} samples in groups")
            if len(indices) != len(pieces) or (
                ends is not None and (not isinstance(ends, list) or len(ends) != len(pieces))
            ):
                raise ValueError(f"{where} has as many groups of samples as pieces")
            groups, seen = [], []
            for k, (index, piece) in enumerate(zip(indices, pieces, strict=True)):
                index = array(index, 1, f"{where}.indices[{k}]", "iu")
                if not len(index) or index.min() < 0 or index.max() >= rows:
                    raise ValueError(f"{where}.indices[{k}] holds no samples, or samples outside 0 to {rows - 1}")
                groups.append((index, build(piece, len(index), f"{where}.pieces[{k}]")))
                seen.append(index)
            if not np.array_equal(np.sort(np.concatenate(seen)), np.arange(rows)):
                raise ValueError(f"{where}: its groups do not hold each of the {rows} samples once")
            if ends is not None:
                ends = tuple(None if end is None else number(end, f"{where}.ends[{k}]") for k, end in enumerate(ends))
            return Groups(tuple(groups), rows, ends)
        raise ValueError(f"{where} is no dense output daemodel writes (kind {kind!r})")

    return build(data, samples, "dense")
