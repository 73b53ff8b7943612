"""radau's memory at scale (issue 44): what its factors hold (stats["factor_bytes"]) and the solve's own peak
against it, on reaction-diffusion (benchmarks/scaling_models.py; benchmarks/solve_memory.py measures 10^5)."""

import functools
import gc
import os
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau import engines
from daemodel.backends.radau.compiled import find_compiler
from daemodel.backends.radau.heap import TRIM_MIN_UNKNOWNS, hand_back_freed_memory, malloc_trim

import daemodel as dm

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models

needs_compiler = pytest.mark.skipif(find_compiler() is None, reason="no C compiler")
# The solve's peak over its factors' bytes that the test holds it to (10^4 unknowns, the first solve of a
# fresh model, which makes the model's own pieces too: its Jacobian's pattern, the band kernel, the
# engines' bound buffers): measured 3.67 (dense output) and 3.10 (without) on 7bc53eb (the Solution's values
# as views made when read, the shifted systems' layout in int32, the branch check's signs without a copy of
# the diagonals, the dense output's nodes joined before the values at t_eval are made; this file's module
# imports the engines before it measures, benchmarks/solve_memory.py's fresh processes do not: 4.15 and 3.55
# there, 4.51 and 3.82 on 6384f00), 4.02 and 3.38 on 88e28fa, 4.15 and 3.99 before Newton's increment, norm
# and stage values were kept in buffers, the band LUs shared their solve buffers, the residual was read in its
# output buffer and the dense output's formula read a step's nodes through a view (4.86 and 5.85 before
# t_eval's outputs were filled as the steps came, 7.3 and 8.5 before the factors were made in one
# factorisation's buffers); 3.51 and 2.87 on d22090c (the last step's nodes read and dropped without copies,
# Newton's stage values and the guess in the next step's nodes' array, the complex right-hand side in the
# increment's buffer); 3.29 and 2.69 on a00ce11 (the increment over the residual, the solves in their right-hand
# sides' places, the band kernel without buffers of its own, the stages' f in the residual's output; 3.57 and 2.97
# on 0e3fa22); 3.01 and 2.44 on 6b5c98a (the stencil's functions on the caller's arrays, no casadi first-step
# function, the Jacobian's values to gather made per call, the branch check without a transposed copy, g_z's sign
# from J's entries, the error's norm in place); 3.25: 8 % above the larger, the margin the bound had (a retry more or
# less moves the peak by a stage array, 0.12)
PEAK_OVER_FACTORS = 3.25
# Issue 44's target: the solve within 2x its factors (a cold solve's arrays: test_a_cold_solve_holds_its_arrays_...)
TARGET_OVER_FACTORS = 2.0


@functools.cache  # (one measurement per case)
def first_solve_peak(unknowns: int, dense_output: bool) -> tuple:
    """``(traced peak - the outputs' bytes, the Solution)`` of a fresh model's first solve (11 outputs)."""
    compiled = scaling_models.DECLARATIONS["stencils"](unknowns // 2).compile()
    gc.collect()
    return traced_solve(compiled, dense_output)


def traced_solve(compiled, dense_output: bool) -> tuple:
    """``(traced peak - the outputs' bytes, the Solution)`` of a solve of ``compiled`` over (0, 1), 11 outputs."""
    times = np.linspace(0.0, 1.0, 11)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        sol = dm.solve(compiled, (0.0, 1.0), method="radau", t_eval=times, dense_output=dense_output)
        peak = tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()
    names = [*compiled.state_names, *compiled.algebraic_names]
    outputs = sum(np.asarray(sol[name]).nbytes for name in names)
    outputs += sol.dense.nodes.nbytes if sol.dense is not None else 0
    return peak - outputs, sol


def test_factor_bytes_counts_each_array_once():
    """A view of an array counts as its owner, once; a SuperLU object by its entries (value and row index)."""
    import scipy.sparse as sparse
    import scipy.sparse.linalg as splinalg

    packed = np.zeros(100)
    lu = {1.0: ("static", False, packed[:40]), 2.0 + 1.0j: ("static", True, packed[40:])}
    factors = engines.Factors(h=0.1, shifts=(1.0, 2.0 + 1.0j), lu=lu, singular=None, error_shift=1.0, inverse=packed)
    assert engines.factors_bytes(factors) == packed.nbytes
    matrix = sparse.csc_matrix(np.array([[4.0, 1.0], [1.0, 3.0]]))
    superlu = splinalg.splu(matrix)
    factors = engines.Factors(h=0.1, shifts=(1.0,), lu={1.0: ("sparse", superlu)}, singular=None, error_shift=1.0)
    assert engines.factors_bytes(factors) == superlu.nnz * 12 + 3 * 4 * 2
    factors.release()
    assert engines.factors_bytes(factors) == 0 and factors.lu == {}


@pytest.mark.parametrize("size", [20, 300])
@pytest.mark.parametrize("jit", ["auto", False])
@pytest.mark.parametrize("engine", ["casadi", "torch"])
def test_factor_bytes_in_the_stats(size, jit, engine):
    """Every adaptive radau solve says what its largest factorisation holds: the band kernel's buffers (one
    real and two complex systems at s = 5), SuperLU's (jit=False), the compiled run's packed factors (40
    unknowns), the torch engine's LU: at least 8 bytes an unknown for the real system's entries and 16 for
    each complex one's."""
    if engine == "torch" and (jit is False or size > 20):
        pytest.skip("the torch engine compiles nothing; one size is enough")
    compiled = scaling_models.reaction_diffusion(size).compile()
    sol = dm.solve(compiled, scaling_models.T_SPAN["reaction_diffusion"], method="radau", jit=jit, engine=engine)
    assert sol.status == "success"
    assert sol.stats["factor_bytes"] >= 2 * size * (8 + 2 * 16)


def resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(malloc_trim() is None or not os.path.exists("/proc/self/statm"), reason="not glibc on Linux")
def test_a_large_solve_hands_the_freed_pages_back():
    """From TRIM_MIN_UNKNOWNS unknowns, the pages the C heap freed under a block still held go back to the system
    (the resident set falls by most of them); below, they stay (a small solve pays no heap walk)."""
    blocks = [np.ones(8192) for _ in range(400)]  # (64 KB each, 26 MB: the C heap's, under its mmap threshold)
    del blocks[:-1]  # (the last one held: the freed pages lie under it, not at the heap's top)
    before = resident_bytes()
    hand_back_freed_memory(TRIM_MIN_UNKNOWNS - 1)
    kept = resident_bytes()
    hand_back_freed_memory(TRIM_MIN_UNKNOWNS)
    assert before - kept < 4e6 and kept - resident_bytes() > 20e6, (before, kept, resident_bytes())


@needs_compiler
def test_the_dense_output_hands_each_joined_step_s_pages_back(monkeypatch):
    """From TRIM_MIN_UNKNOWNS unknowns the dense output's join hands the heap's free pages back as it drops each
    step's nodes (else resident beside the joined array); the same solution as without."""
    from daemodel.backends.radau import records

    compiled = scaling_models.DECLARATIONS["stencils"](TRIM_MIN_UNKNOWNS // 2).compile()
    options = {"method": "radau", "t_eval": np.linspace(0.0, 1.0, 5), "dense_output": True}
    plain = dm.solve(compiled, (0.0, 1.0), **options)
    calls = []
    monkeypatch.setattr(records, "hand_back_freed_memory", lambda unknowns: calls.append(unknowns))
    sol = dm.solve(compiled, (0.0, 1.0), **options)
    assert calls == [TRIM_MIN_UNKNOWNS] * sol.stats["steps"] and sol.stats["steps"] >= 5
    np.testing.assert_array_equal(sol.dense.nodes, plain.dense.nodes)
    np.testing.assert_array_equal(sol["c[7]"], plain["c[7]"])


@pytest.mark.parametrize(
    "library",
    [
        "no symbol",  # (a C library without malloc_trim: musl, macOS)
        "not loaded",  # (dlopen failed)
        "no main program",  # (Windows: CDLL(None) tests '/' in None, a TypeError)
    ],
)
def test_a_large_solve_withoutmalloc_trim_goes_on(monkeypatch, library):
    """Where ctypes finds no malloc_trim, a solve of TRIM_MIN_UNKNOWNS unknowns or more trims nothing and goes on
    (no error): malloc_trim is None."""
    from daemodel.backends.radau import heap

    def cdll(name):
        if library == "not loaded":
            raise OSError("cannot load")
        if library == "no main program":  # (ctypes.CDLL.__init__ on Windows reads '/' in name)
            return "/" in name
        return object()

    monkeypatch.setattr(heap.ctypes, "CDLL", cdll)
    malloc_trim.cache_clear()
    try:
        assert malloc_trim() is None
        assert hand_back_freed_memory(TRIM_MIN_UNKNOWNS) is None
    finally:
        malloc_trim.cache_clear()


@needs_compiler
@pytest.mark.slow  # (tracemalloc on a first solve of 10^4 unknowns: 20-110 s on 2 shared cores)
@pytest.mark.parametrize("dense_output", [True, False])
def test_the_solve_peak_stays_within_a_bound_of_its_factors(dense_output):
    """At 10^4 unknowns (tracemalloc sees numpy's allocations) the first solve's peak, the outputs the user
    asked for aside (values at t_eval, the dense output's nodes), is within PEAK_OVER_FACTORS of the
    factors' bytes (stats["factor_bytes"]): one factorisation's band buffers are reserved, not two, and the
    dense output is not held twice."""
    peak, sol = first_solve_peak(10_000, dense_output)
    assert sol.status == "success" and sol.stats["band_lu"].startswith("machine code")
    assert sol.stats["factor_bytes"] > 3e6  # (one real and two complex systems of 10^4 unknowns, LDAB 7)
    assert peak <= PEAK_OVER_FACTORS * sol.stats["factor_bytes"], peak / sol.stats["factor_bytes"]


@needs_compiler
@pytest.mark.slow  # (tracemalloc on two solves of 10^4 unknowns)
def test_a_cold_solve_holds_its_arrays_within_two_factors():
    """Issue 44's target, the solve within 2x its factors' bytes, counted strictly: a solve after every buffer a solve
    hands on to the next is dropped (benchmarks/solve_memory.py's drop_reused_buffers: the casadi functions' bound
    buffers, the band kernel's spare factors and solvers), so every array it works in is made in it; the model's
    one-off pieces (its Jacobian's pattern, layouts, compiled functions) are not.  tracemalloc's peak of its arrays,
    the outputs aside: 1.88x at 10^4 and 1.86x at 10^5 on 8cdfa4c (benchmarks/solve_memory.json, key
    item5_in_place), where the factors, two steps' nodes, the residual's output, Newton's right-hand sides and J are
    1.66x.  The process's resident set grows more (2.1-2.3x): glibc keeps the pages of blocks freed in the solve.
    A first solve makes the model's pieces too: 2.44x at 10^4 (bounded by PEAK_OVER_FACTORS above)."""
    import solve_memory

    compiled = scaling_models.DECLARATIONS["stencils"](5_000).compile()
    dm.solve(compiled, (0.0, 1.0), method="radau", t_eval=np.linspace(0.0, 1.0, 11), dense_output=False)
    solve_memory.drop_reused_buffers(compiled)
    held, sol = traced_solve(compiled, False)
    assert sol.status == "success" and sol.stats["band_lu"].startswith("machine code")
    ratio = held / sol.stats["factor_bytes"]
    assert ratio <= TARGET_OVER_FACTORS, ratio
