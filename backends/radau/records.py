"""The accepted steps' outputs of a radau solve (:class:`Records`) and the bytes each keeps."""

from __future__ import annotations

import numpy as np
from daemodel.backends.radau.error import numpy_copy


class Records:
    """The accepted steps' outputs, in blocks (one step, or a compiled run's steps): each step's end
    time and, with ``dense`` (t_eval, or the dense output kept for :meth:`Solution.at`), its start,
    length and nodes (start value and stages: its collocation polynomial), else its end value.
    ``count``: the outputs kept, the start's included."""

    def __init__(self, t0: float, u0, dense: bool):
        self.dense = dense
        self.times, self.values = [np.array([t0])], [u0[:, None]]  # (k,), (B, k, n+m)
        self.starts, self.lengths, self.nodes = [], [], []  # (k,), (k,), (B, k, s+1, n+m)
        self.count = 1

    def add(self, starts, lengths, times, arrays):
        """A block of steps: their ``starts``, ``lengths`` and end ``times``, and ``arrays`` = their nodes
        (B, k, s+1, n+m); without ``dense`` only the end values (the last node) are kept."""
        self.times.append(times)
        if self.dense:
            self.starts.append(starts)
            self.lengths.append(lengths)
            self.nodes.append(arrays)
        else:
            self.values.append(arrays[:, :, -1])
        self.count += len(times)

    def ends(self, xp):
        """``(times (T,), values (B, T, n+m))`` at the steps' ends, the start first."""
        values = self.values if not self.dense else self.values + [nodes[:, :, -1] for nodes in self.nodes]
        return np.concatenate(self.times), xp.concatenate(values, axis=1)

    def block(self, k: int):
        """``(times (j,), values (B, j, n+m))`` of the ``k``-th block of outputs (0: the start value)."""
        if k == 0 or not self.dense:
            return self.times[k], self.values[k]
        return self.times[k], self.nodes[k - 1][:, :, -1]

    def block_polynomials(self, k: int, c):
        """The :class:`~daemodel.dense.CollocationPolynomials` of the ``k``-th block's steps (``k`` >= 1), or
        None without ``dense``."""
        if not self.dense:
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
        or steps.  The blocks' nodes move into it: each is copied into the joined array and dropped from
        the records at once, so that the solve's peak holds them once and a block, not twice (at 10^5
        unknowns and s = 5, 4.8 MB a step); the records keep no nodes after it (the solve's last use)."""
        if not self.dense or not self.starts:
            return None
        from daemodel.dense import CollocationPolynomials

        if len(self.nodes) == 1:
            return self.block_polynomials(1, c)
        B, _, stages, D = self.nodes[0].shape
        nodes, at = np.empty((B, sum(block.shape[1] for block in self.nodes), stages, D)), 0
        for k, block in enumerate(self.nodes):
            nodes[:, at : at + block.shape[1]] = numpy_copy(block)
            at += block.shape[1]
            self.nodes[k] = None
        self.nodes = []
        starts, lengths = np.concatenate(self.starts).astype(float), np.concatenate(self.lengths).astype(float)
        return CollocationPolynomials(c=np.asarray(c, dtype=float), starts=starts, lengths=lengths, nodes=nodes)

    def nodes_of(self, steps: np.ndarray, xp, index):
        """The nodes of ``steps`` (ascending step numbers), ``(B, len(steps), s+1, n+m)``, gathered
        block by block (only the steps asked for are copied)."""
        if len(self.nodes) == 1:  # (one compiled run: the whole solve)
            nodes = self.nodes[0]
            return nodes if len(steps) == nodes.shape[1] else nodes[:, index(steps)]
        offsets = np.cumsum([0] + [len(block) for block in self.starts])
        block = np.searchsorted(offsets, steps, side="right") - 1
        # the asked-for steps of each block are a contiguous run of ``steps`` (ascending): split there
        starts = np.flatnonzero(np.concatenate([[True], block[1:] != block[:-1]]))
        pieces = []
        for first, last in zip(starts, [*starts[1:], len(steps)], strict=True):
            b, local = block[first], steps[first:last] - offsets[block[first]]
            nodes = self.nodes[b]
            pieces.append(nodes if len(local) == nodes.shape[1] else nodes[:, index(local)])
        return pieces[0] if len(pieces) == 1 else xp.concatenate(pieces, axis=1)


def step_record_bytes(D: int, B: int, options) -> int:
    """Bytes an accepted step keeps until the end: its end values, or with t_eval or the dense output its
    stages and start."""
    dense = options.t_eval is not None or options.dense_output
    return B * D * (4 if options.dtype == "float32" else 8) * (options.stages + 1 if dense else 1)
