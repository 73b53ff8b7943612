"""How many entries the LU factors of ``sigma M - J`` hold, found within the memory the solve may take.

The memory guard counts the fill of SuperLU's factors of the Jacobian's pattern (:func:`.fill.factor_entries`:
one factorisation at values drawn once).  That trial is as large as the factors it measures: on a random sparse
pattern of 10^4 unknowns (0.14 n^2 entries) it took 6-25 s, and at 10^5 it would need ~17 GB and hours, the guard
exhausting the machine before it could refuse.  So the trial runs only where a bound says it is affordable:

1. **A bound from the pattern** (:func:`fill_bound`).  Whatever rows partial pivoting picks, the LU factors of
   ``A Pc`` fit in the structure of the Cholesky factor of ``(A Pc)^T (A Pc)`` (George and Ng, 1987): L's and U's
   entries are each at most its entries.  Its column counts come from the column elimination tree without
   forming the factor or ``A^T A`` (Gilbert, Ng and Peyton, 1994; CSparse's ``cs_counts`` with ``ata``), here
   in numpy in O(nnz log n); the column order is SuperLU's own (COLAMD and its postorder, read from an
   incomplete factorisation that drops every entry: the same ``perm_c``, measured on every pattern of the
   tests).  0.02-0.1 s at 10^4 unknowns.
2. Where the trial's memory at the bound fits the limit (:data:`TRIAL_BYTES_PER_ENTRY`), **the trial** runs as
   before: the exact count, the same path and timing for every model that fits.
3. Else, where no row or column is dense (:func:`dense_lines`), the bound over :data:`BOUND_SLACK` is below
   the fill on every pattern measured (the bound is 1.0-1.9 times the fill of random, banded, block and 2-D
   grid patterns, up to 51 times with many rows of 16-64 entries); where even that does not fit, the model
   is **refused** at once.
4. Else (a dense row or column: a constraint summing every state, a multiplier in every equation; or a bound
   within :data:`BOUND_SLACK` of the limit) the bound says little (2,500 times the fill of an arrow at 10^4
   unknowns, 14 times that of one dense row), and **the trial runs in a child process** under ``RLIMIT_AS``
   (the memory limit) and :data:`TRIAL_SECONDS` (radau's ``fill_seconds``): its count, or a refusal when it
   runs out of either (without ``fork``, the bound decides).

Refusals are :class:`FillOverLimit`, which the guard turns into a :class:`~daemodel.errors.ResourceLimitError`
naming the size, the fill and the limit.
"""

from __future__ import annotations

import math
import os

import numpy as np
from daemodel.backends.radau.linalg import pattern_matrix, sorted_unique

from daemodel.errors import DaemodelError

# Bytes a SuperLU factorisation and the CSC copies of its L and U take at their peak, per entry of the
# factors: 8-21 measured on 2-D grids and random patterns, 75 on a dense row (its supernodes' work space);
# the trial runs in this process only where this many bytes per entry of the bound fit the limit.
TRIAL_BYTES_PER_ENTRY = 80
# The bound over the fill, at most, on patterns without dense rows or columns: 1.0 (block-diagonal), 1.7
# (banded), 1.8-1.9 (random, four entries a row; a 2-D grid) at 2,000 and 10^4 unknowns, but 26-51 on a chain
# of 10^4 states with 100-300 algebraic rows of 16-64 states each (rows that pivot last, where the bound lets
# any row pivot): above the largest measured.  A model refused on the bound has a fill at least this
# many times below it, and would still not fit.
BOUND_SLACK = 64.0
# Seconds the trial in a child process may take (case 4) unless radau's ``fill_seconds`` says: one
# factorisation of the solve would take as long, and a solve makes one at every Jacobian.
TRIAL_SECONDS = 30.0
# The fill ratio given to the incomplete factorisation that reads SuperLU's column order (scipy's default):
# at 1, SuperLU's ILU overran its work space on random patterns without a full diagonal (300 unknowns, 180
# of them differential, 900 entries: "double free or corruption", the process aborted, in 3 of 3 runs of
# 300 random patterns); at 10, none in 6,000 patterns of 2-400 unknowns (at 2, none in 3,000).
ORDER_FILL_FACTOR = 10
# The largest address-space limit setrlimit takes (a C rlim_t read as signed by Python): a child given more
# failed with an OverflowError, and the guard refused a model under a memory limit of 10^8 TiB.
MAX_RLIMIT = 2**63 - 1
# The longest wait for the child's answer (31 years): select's timeout must fit the platform's time_t, and
# fill_seconds = 1e300 raised an OverflowError out of the solve; a longer limit is no limit in practice.
MAX_WAIT_SECONDS = 1e9


class FillOverLimit(RuntimeError):
    """The factors would hold more than the entries allowed, or could not be counted within the limit:
    ``entries`` (an estimate, at least what the reason says; None where the count did not finish) and
    ``reason`` (how it is known, in words).  Internal: the memory guard turns it into a
    :class:`~daemodel.errors.ResourceLimitError`."""

    def __init__(self, entries: float | None, reason: str):
        super().__init__(reason)
        self.entries, self.reason = entries, reason


def dense_lines(rows: np.ndarray, cols: np.ndarray, D: int) -> bool:
    """Whether a row or a column of the ``D x D`` pattern ``(rows, cols)`` has more than COLAMD's dense
    threshold, ``max(16, 10 sqrt(D))`` entries (COLAMD sets such rows aside when it orders)."""
    threshold = max(16.0, 10.0 * math.sqrt(D))
    keys = sorted_unique(rows.astype(np.int64) * D + cols)
    counts = [np.bincount(keys // D, minlength=D), np.bincount(keys % D, minlength=D)]
    return bool(max(int(c.max(initial=0)) for c in counts) > threshold)


def superlu_column_order(matrix) -> np.ndarray | None:
    """The order SuperLU's ``splu`` takes the columns of the square CSC ``matrix`` in (COLAMD, then the
    postorder of its column elimination tree): ``order[k]`` is the k-th column.  Read from ``spilu`` with
    every entry dropped (the ordering is made from the pattern before any value is read: O(nnz)), the dropped
    entries added to the diagonal (``SMILU_1``: without it the algebraic columns of an index-2 or 3 model met
    zero pivots, the pendulum chains' and the sphere particles'), else not; None where both meet one."""
    import scipy.sparse.linalg as splinalg

    for modified in ("SMILU_1", "SILU"):
        try:
            ilu = splinalg.spilu(
                matrix,
                drop_tol=1e300,
                fill_factor=ORDER_FILL_FACTOR,
                diag_pivot_thresh=0.0,
                options={"ILU_MILU": modified},
            )
        except DaemodelError:  # (a time limit's signal, raised inside the call)
            raise
        except RuntimeError:  # ("Factor is exactly singular")
            continue
        return np.argsort(ilu.perm_c)
    return None


def fill_bound(matrix) -> int | None:
    """An upper bound of the entries of SuperLU's LU factors (L's and U's) of the square CSC ``matrix``,
    whatever rows partial pivoting picks: twice those of the Cholesky factor of ``A^T A``, ``A`` the matrix
    in SuperLU's column order (:func:`superlu_column_order`; None where it is not known)."""
    order = superlu_column_order(matrix)
    if order is None:
        return None
    return 2 * int(ata_column_counts(matrix[:, order]).sum())


def ata_column_counts(A) -> np.ndarray:
    """The entries of each column of the Cholesky factor of ``A^T A`` (the diagonal included), ``A`` sparse
    (m x D), ``A^T A`` never formed: Gilbert, Ng and Peyton's algorithm on the column elimination tree
    (casadi's ``etree(ata)``), with each row's leftmost column standing for the row's clique (CSparse's
    ``cs_counts`` with ``ata``), vectorised: the nodes relabelled in postorder, each row subtree's leaves
    found by comparing first descendants, their least common ancestors by binary lifting."""
    import casadi
    import scipy.sparse as sparse

    A = sparse.csc_matrix(A)
    A.sort_indices()
    m, D = A.shape
    if D == 0:
        return np.zeros(0, dtype=np.int64)
    parent = np.asarray(casadi.Sparsity(m, D, A.indptr.tolist(), A.indices.tolist()).etree(True), dtype=np.int64)
    post, size = _postorder(parent)
    label = np.empty(D, dtype=np.int64)  # (a column's position in the postorder)
    label[post] = np.arange(D)
    up = np.full(D + 1, D, dtype=np.int64)  # (the parent in postorder labels; roots under a sentinel D)
    up[label[parent >= 0]] = label[parent[parent >= 0]]
    first = np.arange(D) - size[post] + 1  # (the first descendant of each, its subtree [first, itself])
    # Each row's clique: the pairs (i, j) of its columns i after its leftmost (in postorder) j.
    entries = A.tocoo()
    column = label[entries.col]
    leftmost = np.full(m, D, dtype=np.int64)
    np.minimum.at(leftmost, entries.row, column)
    j = leftmost[entries.row]
    keep = column > j
    keys = sorted_unique(column[keep] * D + j[keep])  # (by i, then j: each row subtree's candidates in postorder)
    i, j = keys // D, keys % D
    head = np.full(min(i.size, 1), -1, dtype=np.int64)  # (what comes before the first pair: none)
    new = np.concatenate([head < 0, i[1:] != i[:-1]])
    # j is a leaf of row subtree i where it is no ancestor of the candidate before it
    leaf = new | (first[j] > np.concatenate([head, first[j][:-1]]))
    delta = np.zeros(D + 1, dtype=np.int64)
    delta[:D] = size[post] == 1
    np.subtract.at(delta, up[:D], 1)
    i, j = i[leaf], j[leaf]
    np.add.at(delta, j, 1)
    later = np.concatenate([head >= 0, i[1:] == i[:-1]])  # (a leaf after its row subtree's first)
    np.subtract.at(delta, _ancestor_reaching(up, np.concatenate([head, j[:-1]])[later], j[later]), 1)
    total = np.r_[0, np.cumsum(delta[:D])]
    counts_post = total[1:] - total[first]  # (the sum of delta over each subtree)
    return counts_post[label]


def _postorder(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(post, size)`` of the forest ``parent`` (-1: a root): a postorder (children in increasing order)
    and each node's subtree size, from scipy's depth-first orders: a postorder is the reverse of a preorder
    that takes the children in decreasing order, and a node precedes ``size - 1 - depth`` more nodes in the
    postorder than in the preorder of the same child order (its descendants move before it, its ancestors
    after)."""
    import scipy.sparse as sparse
    from scipy.sparse.csgraph import depth_first_order

    D = parent.size
    above = np.where(parent < 0, D, parent)  # (a sentinel root D over every root)
    children = np.arange(D)
    increasing = sparse.csr_matrix((np.ones(D), (above, children)), shape=(D + 1, D + 1))
    increasing.sort_indices()
    decreasing = sparse.csr_matrix(
        (
            np.ones(D),
            increasing.indices[np.lexsort((-increasing.indices, above[increasing.indices]))],
            increasing.indptr,
        ),
        shape=(D + 1, D + 1),
    )
    post = depth_first_order(decreasing, D, directed=True, return_predecessors=False)[::-1][:-1]
    pre = depth_first_order(increasing, D, directed=True, return_predecessors=False)[1:]
    depth, reach, hops = np.zeros(D + 1, dtype=np.int64), np.append(above, D), np.ones(D + 1, dtype=np.int64)
    hops[D] = 0
    while (reach[:D] != D).any():  # (pointer jumping: log2 of the height passes)
        hops = hops + np.where(reach != D, hops[reach], 0)
        reach = reach[reach]
    depth = hops[:D] - 1  # (proper ancestors)
    at_post, at_pre = np.empty(D, dtype=np.int64), np.empty(D, dtype=np.int64)
    at_post[post], at_pre[pre] = np.arange(D), np.arange(D)
    return post, at_post - at_pre + depth + 1


def _ancestor_reaching(up: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each pair, the lowest ancestor of ``a`` (postorder labels, ``a < b``, parents ``up``) whose label
    is at least ``b``: the least common ancestor of ``a`` and ``b`` where both lie in one subtree."""
    if a.size == 0:
        return a
    table = [up]
    while 2 ** (len(table) - 1) < up.size:
        table.append(table[-1][table[-1]])
    x = a.copy()
    for level in reversed(table):
        above = level[x]
        x = np.where(above < b, above, x)
    return np.where(x < b, up[x], x)


def measured_fill(
    rows: np.ndarray, cols: np.ndarray, n: int, D: int, max_entries: float, seconds: float = TRIAL_SECONDS
) -> int:
    """The entries of SuperLU's factors of ``sigma M - J`` (:func:`.fill.factor_entries`), measured only
    where it can be within the memory limit; :class:`FillOverLimit` where they would be more than
    ``max_entries`` (the largest fill the limit leaves the solve), as the module docstring's steps say.
    ``seconds``: the most the count in a child process may take (radau's ``fill_seconds``)."""
    from daemodel.files import memory_limit

    matrix = pattern_matrix(rows, cols, n, D)  # (made once: the bound, the order and the count read it)
    bound = fill_bound(matrix)
    trial_limit = memory_limit()
    if bound is not None and bound * TRIAL_BYTES_PER_ENTRY <= trial_limit:
        return matrix_entries(matrix)
    if bound is not None and not dense_lines(rows, cols, D) and bound / BOUND_SLACK > max_entries:
        raise FillOverLimit(
            bound / BOUND_SLACK,
            f"the bound {bound:.3g} from the Jacobian's pattern (George and Ng's: the Cholesky factor of A^T A in "
            f"SuperLU's column order) over {BOUND_SLACK:g}, more than it exceeded the fill on any pattern without "
            "dense rows measured; not factored",
        )
    outcome = capped_trial(matrix, trial_limit, seconds)  # (its count, over max_entries or not, decides)
    if isinstance(outcome, int):
        return outcome
    if outcome == "unavailable":
        estimate = bound if bound is not None else D * D
        if estimate <= max_entries:  # (no fork: the bound itself fits, the trial is within it)
            return matrix_entries(matrix)
        raise FillOverLimit(estimate, f"the bound {estimate:.3g} from the Jacobian's pattern; not factored")
    raise FillOverLimit(None, outcome)  # (how many entries is not known: the count did not finish)


def capped_trial(matrix, max_bytes: float, seconds: float) -> int | str:
    """SuperLU's fill of ``matrix`` (L's and U's entries) factored in a child process (``fork``) whose
    address space may grow by ``max_bytes`` and which may take ``seconds``: the count, or in words why
    there is none (out of memory, out of time, singular), or ``"unavailable"`` where this system cannot
    fork or no child can be made now (``fork``'s ``OSError``)."""
    import select
    import signal

    if not hasattr(os, "fork"):
        return "unavailable"
    try:
        read_end, write_end = os.pipe()
    except OSError:  # (no descriptors left: as without fork)
        return "unavailable"
    try:
        pid = os.fork()
    except OSError:  # (EAGAIN, ENOMEM: no process can be made now; the bound decides, as without fork)
        os.close(read_end)
        os.close(write_end)
        return "unavailable"
    if pid == 0:  # the child: factor, write the count or the reason, and leave without Python's exit handlers
        message = b"error"
        try:
            os.close(read_end)
            import resource

            import scipy.sparse.linalg as splinalg

            _, hard = resource.getrlimit(resource.RLIMIT_AS)
            size = os.sysconf("SC_PAGE_SIZE") * int(open("/proc/self/statm").read().split()[0])
            soft = size + int(max_bytes)
            if soft < MAX_RLIMIT:  # (a limit past what setrlimit takes, DAEMODEL_MEMORY_LIMIT = '10^8T': none)
                resource.setrlimit(
                    resource.RLIMIT_AS, (soft if hard == resource.RLIM_INFINITY else min(soft, hard), hard)
                )
            try:
                lu = splinalg.splu(matrix)
                message = str(int(lu.L.nnz + lu.U.nnz)).encode()
            except (MemoryError, SystemError):  # (SuperLU's failed expansion of its work space, "Can't expand
                message = b"memory"  # MemType", comes back as a SystemError where Python's own allocation failed)
            except RuntimeError:
                message = b"singular"
        except BaseException as error:  # (whatever else, named where memory is left to name it: no count)
            try:
                message = f"error {type(error).__name__}".encode()[:60]
            except BaseException:
                pass
        finally:
            try:
                os.write(write_end, message)
            finally:
                os._exit(0)
    os.close(write_end)
    answer = None
    try:
        ready, _, _ = select.select([read_end], [], [], min(seconds, MAX_WAIT_SECONDS))
        if ready:
            answer = os.read(read_end, 64).decode()
    finally:  # (out of time, or interrupted here, as by a time limit's signal: the child is stopped, not left)
        os.close(read_end)
        if answer is None:
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    if answer is None:
        return f"one factorisation of the pattern did not finish within {seconds:g} s"
    if answer.isdigit():
        return int(answer)
    if answer == "singular":
        return matrix.shape[0] ** 2  # (structurally singular at these values: at most dense, as factor_entries)
    if answer == "memory":
        return f"one factorisation of the pattern ran out of the {max_bytes / 2**30:.3g} GiB it was given"
    return (  # (at the memory it was given, the child may fail before it can say why)
        f"one factorisation of the pattern failed in a child process given {max_bytes / 2**30:.3g} GiB "
        f"({answer or 'no answer'})"
    )


def factor_entries(rows: np.ndarray, cols: np.ndarray, n: int, D: int) -> int:
    """The entries SuperLU's LU factors of ``sigma M - J`` hold (L's and U's), ``J`` of the pattern
    ``(rows, cols)``: one factorisation of that pattern with values drawn once (the fill of the
    engine's factors, which pivot on their own values, is of the same order)."""
    return matrix_entries(pattern_matrix(rows, cols, n, D))


def matrix_entries(matrix) -> int:
    """The entries of SuperLU's LU factors (L's and U's) of the square CSC ``matrix``
    (:func:`.linalg.pattern_matrix`'s), ``D^2`` where it is singular at its values."""
    import scipy.sparse.linalg as splinalg

    D = matrix.shape[0]
    try:
        lu = splinalg.splu(matrix)
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:  # (structurally singular at these values: at most dense)
        return D * D
    return int(lu.L.nnz + lu.U.nnz)
