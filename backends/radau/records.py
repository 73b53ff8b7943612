"""The accepted steps' outputs of a radau solve (:class:`Records`), the values at ``t_eval`` filled as the
steps come (:class:`OutputsAt`), and the bytes each step keeps."""

from __future__ import annotations

import numpy as np
from daemodel.backends.radau.error import numpy_copy
from daemodel.backends.radau.heap import hand_back_freed_memory

from daemodel.collocation import lagrange_matrix
from daemodel.dense import END_MATCH_RTOL, collocation_values


class Records:
    """The accepted steps' outputs, in blocks (one step, or a compiled run's steps): each step's end
    time and, with ``dense`` (the dense output kept for :meth:`Solution.at`), its start, length and
    nodes (start value and stages: its collocation polynomial), else its end value.  With ``outputs``
    (an :class:`OutputsAt`: t_eval without the dense output) each block's polynomials fill the values
    at the times they cover as the block comes, and its nodes are kept only until :meth:`release`
    (the block shown to a caller's stop), not to the end.  ``count``: the outputs kept, the start's
    included."""

    def __init__(self, t0: float, u0, dense: bool, outputs: OutputsAt | None = None):
        self.dense, self.outputs = dense, outputs
        self.nodal = dense or outputs is not None  # (blocks come with their nodes)
        self.times, self.values = [np.array([t0])], [u0[:, None]]  # (k,), (B, k, n+m)
        self.starts, self.lengths, self.nodes = [], [], []  # (k,), (k,), (B, k, s+1, n+m)
        self.count = 1

    def add(self, starts, lengths, times, arrays):
        """A block of steps: their ``starts``, ``lengths`` and end ``times``, and ``arrays`` = their nodes
        (B, k, s+1, n+m) where :attr:`nodal`, else their end values (B, k, n+m)."""
        self.times.append(times)
        if self.nodal:
            self.starts.append(starts)
            self.lengths.append(lengths)
            self.nodes.append(arrays)
            if self.outputs is not None:
                self.outputs.fill(starts, lengths, times, arrays)
        else:
            self.values.append(arrays[:, :, -1])
        self.count += len(times)

    def release(self, shown: int, newest: bool = True) -> None:
        """With ``outputs``: drop the nodes of the blocks before the ``shown``-th (0: the start value), whose
        outputs at t_eval were filled (the newest's stay, unless not ``newest``: the next step's start guess reads
        them, until the next block comes).  Otherwise the records keep all nodes (``dense``) or none."""
        if self.outputs is None:
            return
        for k in range(max(min(shown, len(self.times) - 1) - (1 if newest else 0), 0)):
            self.nodes[k] = None

    def ends(self, xp):
        """``(times (T,), values (B, T, n+m))`` at the steps' ends, the start first."""
        values = self.values if not self.nodal else self.values + [nodes[:, :, -1] for nodes in self.nodes]
        return np.concatenate(self.times), xp.concatenate(values, axis=1)

    def block(self, k: int):
        """``(times (j,), values (B, j, n+m))`` of the ``k``-th block of outputs (0: the start value)."""
        if k == 0 or not self.nodal:
            return self.times[k], self.values[k]
        return self.times[k], self.nodes[k - 1][:, :, -1]

    def block_polynomials(self, k: int, c):
        """The :class:`~daemodel.dense.CollocationPolynomials` of the ``k``-th block's steps (``k`` >= 1), or
        None where blocks come without nodes."""
        if not self.nodal:
            return None
        from daemodel.dense import CollocationPolynomials

        return CollocationPolynomials(
            c=np.asarray(c, dtype=float),
            starts=np.asarray(self.starts[k - 1], dtype=float),
            lengths=np.asarray(self.lengths[k - 1], dtype=float),
            nodes=numpy_copy(self.nodes[k - 1]),
        )

    def polynomials(self, c):
        """The steps' :class:`~daemodel.dense.CollocationPolynomials` (numpy), or None without ``dense``
        or steps: of the blocks :meth:`join` made one (their nodes are the records' own, not a copy)."""
        if not self.dense or not self.starts:
            return None
        self.join()
        return self.block_polynomials(1, c)

    def join(self) -> None:
        """With ``dense``, the blocks' nodes moved into one array, the records' only block from now on: each
        block is copied in and dropped at once, so that the solve's peak holds them once and a block, not
        twice (at 10^5 unknowns and s = 5, 4.8 MB a step).  Before :meth:`.step.Stepper.dense_output` makes
        the values at t_eval: the joined nodes and those values were not all held at once beside the blocks
        (0.88 MB of a first solve's peak at 10^4 unknowns, 11 outputs)."""
        if not self.dense or len(self.nodes) < 2:
            return
        B, _, stages, D = self.nodes[0].shape
        nodes, at = np.empty((B, sum(block.shape[1] for block in self.nodes), stages, D)), 0
        for k, block in enumerate(self.nodes):
            nodes[:, at : at + block.shape[1]] = numpy_copy(block)
            at += block.shape[1]
            self.nodes[k] = block = None
            hand_back_freed_memory(B * D)  # (its pages: else resident beside the joined nodes, 3.04 -> 2.76x at 10^5)
        self.nodes = [nodes]
        self.starts = [np.concatenate(self.starts).astype(float)]
        self.lengths = [np.concatenate(self.lengths).astype(float)]

    def nodes_of(self, steps: np.ndarray, xp, index):
        """The nodes of ``steps`` (ascending step numbers), ``(B, len(steps), s+1, n+m)``, gathered
        block by block (only the steps asked for are copied)."""
        if len(self.nodes) == 1:  # (one compiled run: the whole solve)
            return block_nodes(self.nodes[0], steps, index)
        offsets = np.cumsum([0] + [len(block) for block in self.starts])
        block = np.searchsorted(offsets, steps, side="right") - 1
        # the asked-for steps of each block are a contiguous run of ``steps`` (ascending): split there
        starts = np.flatnonzero(np.concatenate([[True], block[1:] != block[:-1]]))
        pieces = []
        for first, last in zip(starts, [*starts[1:], len(steps)], strict=True):
            b, local = block[first], steps[first:last] - offsets[block[first]]
            pieces.append(block_nodes(self.nodes[b], local, index))
        return pieces[0] if len(pieces) == 1 else xp.concatenate(pieces, axis=1)


def block_nodes(nodes, steps: np.ndarray, index):
    """The nodes (B, len(steps), s+1, n+m) of a block's ``steps`` (ascending, local): the block itself where
    all are asked for, a view of it where they are a run (the dense output's values at t_eval, a step at a time:
    a copy each, 4.8 MB at 10^5 unknowns, s = 5), else a copy."""
    if len(steps) == nodes.shape[1]:
        return nodes
    if len(steps) and steps[-1] - steps[0] + 1 == len(steps) and (np.diff(steps) == 1).all():
        return nodes[:, int(steps[0]) : int(steps[-1]) + 1]
    return nodes[:, index(steps)]


class OutputsAt:
    """The values at the output times ``t_out`` (T,) (t_eval's, ascending), ``(B, T, n+m)`` on the engine's
    arrays, filled block by block as the accepted steps come (:meth:`fill`), each time from the
    collocation polynomial of the step that :func:`~daemodel.dense.step_owners` gives it over the whole
    solve, by the same formula as :meth:`.step.Stepper.dense_output` (Lagrange weights of the product
    form, :func:`~daemodel.dense.collocation_values`): the same values, bit for bit, without every step's
    nodes kept to the end (48 MB at 10^5 unknowns, s = 5, ten steps).  Times at or before ``t0`` take the
    start value ``u0`` (B, n+m).

    The numpy array is laid out variable by variable, ``(n+m, B, T)`` seen as ``(B, T, n+m)``: each
    variable's values are the contiguous block that :func:`~daemodel.backends.base.make_solution` keeps
    (no copy there)."""

    def __init__(self, t_out: np.ndarray, t0: float, u0, c, engine, index):
        self.t_out, self.engine, self.index = np.asarray(t_out, dtype=float), engine, index
        self.nodes_at = np.concatenate([[0.0], np.asarray(c, dtype=float)])  # (the polynomial's nodes in a step)
        B, D, T = u0.shape[0], u0.shape[1], len(self.t_out)
        if engine.xp is np:
            self.values = np.empty((D, B, T)).transpose(1, 2, 0)
        else:
            self.values = u0.new_empty((B, T, D))
        after = (self.t_out > t0).nonzero()[0]  # (a suffix: t_out ascends)
        first = int(after[0]) if len(after) else T
        self.values[:, :first] = u0[:, None]
        self.pending = after  # (the times no step has taken for good yet)

    def fill(self, starts: np.ndarray, lengths: np.ndarray, ends: np.ndarray, nodes) -> None:
        """The values at the pending times that the block of steps ``starts``, ``lengths`` (k,) covers, from
        its ``nodes`` (B, k, s+1, n+m).  A time past a step's end by less than :data:`END_MATCH_RTOL` of it is
        that step's; one past the last step's end (to rounding) but not past the block's last end time
        ``ends[-1]`` takes the last step's polynomial for now, as at the solve's end (the next step's start,
        where there is one, takes it then)."""
        pending = self.pending
        if not len(pending):
            return
        times = self.t_out[pending]
        owner = np.searchsorted(starts + lengths * (1 + END_MATCH_RTOL), times, side="left")
        inside = owner < len(starts)
        taken = inside | (times <= ends[-1])
        if taken.any():
            owner = np.minimum(owner[taken], len(starts) - 1)
            theta = (times[taken] - starts[owner]) / lengths[owner]
            weights = self.engine.asarray(lagrange_matrix(self.nodes_at, theta))  # (P, s+1)
            found = collocation_values(
                weights, owner, lambda k: block_nodes(nodes, k, self.index), self.engine.xp, self.index
            )
            self.values[:, pending[taken]] = found
        self.pending = pending[~inside]

    def result(self, reached: float) -> tuple:
        """``(times, values)``: the output times up to ``reached`` (the last step's end) and their values."""
        count = int(np.searchsorted(self.t_out, reached, side="right"))
        return self.t_out[:count], numpy_copy(self.values[:, :count])


def step_record_bytes(D: int, B: int, options) -> int:
    """Bytes an accepted step keeps until the end: its stages and start with the dense output, else with t_eval
    its start, length and end time (the outputs are filled as the steps come), else its end value."""
    itemsize = 4 if options.dtype == "float32" else 8
    if options.dense_output:
        return B * D * itemsize * (options.stages + 1)
    return 3 * 8 if options.t_eval is not None else B * D * itemsize
