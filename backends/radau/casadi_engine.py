"""The casadi engine of ``method="radau"``: one trajectory in float64 on the CPU, compiled.

casadi-compiled residual, right-hand side and sparse Jacobian (casadi's AD); on dense systems the
inverses of the transformed systems (LAPACK's LU inside casadi), a Newton iteration as one casadi
call, an adaptive attempt as one casadi call (:mod:`.compiled`), and up to 24 unknowns many attempts
with the controller in one (:mod:`.loop`), so that Python runs once per run of attempts.  Sparse
patterns of 25-200 unknowns (any size with ``jit``, a loop in C: :mod:`.kernel`) get LU factors with a
fixed pivot order (:mod:`.sparse`), and then the many attempts in one call too; SuperLU for other
large sparse systems.  No torch code generation and no per-operation dispatch.
"""

from __future__ import annotations

import numpy as np
from daemodel.backends.progress import captured_output
from daemodel.backends.radau.band import BandLU
from daemodel.backends.radau.compiled import (
    STEP_SCALARS,
    Buffered,
    find_compiler,
    inverse_function,
    lend,
    machine_code,
    machine_library,
    newton_step_function,
    refresh_function,
    step_function,
    step_layouts,
)
from daemodel.backends.radau.engines import AbstractEngine, Factors, Residual, StageFactors
from daemodel.backends.radau.increments import PackedInverses, StaticFactors, inverse_size, static_factor_function
from daemodel.backends.radau.kernel import factor_call, kernel_source, sign_call
from daemodel.backends.radau.linalg import (
    DENSE_MAX_SIZE,
    OrderedLU,
    block_sign_det,
    dense_inverse,
    dense_lu,
    dense_sign_det,
    dense_systems,
    small_sign_det,
    sparse_lu,
    sparse_sign_det,
    z_block,
)
from daemodel.backends.radau.loop import MACHINE_ATTEMPT, CompiledRun, attempt_function, run_function, run_loop_source
from daemodel.backends.radau.pivots import MATCHED_MAX_COST, PivotOrders, first_order, holds
from daemodel.backends.radau.sparse import (
    MAX_GROWTH,
    PIVOTING,
    StaticLU,
    factor_shifts,
    shifted_layout,
    sorted_unique,
    unique_entries,
)
from daemodel.backends.radau.start import Start
from daemodel.backends.radau.stencil import engine_functions
from daemodel.backends.radau.transform import IncrementBuffers

from daemodel.errors import DaemodelError

# Dense systems up to this size are inverted in one casadi call (the complex blocks as real systems of
# twice the size, casadi computing in real numbers); above it scipy's complex LAPACK is cheaper
# (measured per factorisation: 0.12 against 0.09 ms at 40 unknowns, 0.85 against 0.51 ms at 100).
COMPILED_FACTOR_MAX_SIZE = 24
# LU factors with a fixed pivot order (.sparse) where the elimination takes at most this many
# multiply-adds and the factors hold at most this many entries (the triangular solves are straight-line
# code in the compiled step; the chain of 40 pendulums, 200 unknowns: 3,100 and ~1,900); larger systems
# keep LAPACK or SuperLU.  With jit (the factors a loop in C, .kernel) at any size and fill: car axis
# (10 unknowns, dense) refactors in ~1 us where casadi's LAPACK call took 8-13.
STATIC_MAX_FLOPS, STATIC_MAX_ENTRIES = 100_000, 5_000
# Without jit (straight-line SX on casadi's virtual machine, ~3 ns an operation) only above
# COMPILED_FACTOR_MAX_SIZE, for factors within this share of D^2 entries (the squeezer: 25 %) and an
# elimination of at most this many multiply-adds: the chain of 40 pendulums (3,100) at s = 5 was 1.15x
# slower than SuperLU, the chain of 20 (1,500) 1.8x faster, reaction-diffusion (100-600) 2.4-5x; up to 200
# unknowns (above, 0.45-2 s of setup per process for solves within 20 % of SuperLU's at 300-1,000 unknowns).
STATIC_MAX_FILL, STATIC_MAX_FLOPS_VM, STATIC_MAX_SIZE_VM = 0.2, 2_000, 200
# Attempts in one call of the compiled run in machine code (.loop.run_loop_source: it stops where the run does;
# virtual machine: loop.RUN_ATTEMPTS); a run ends at the progress watch's window (100 attempts) anyway.
MACHINE_RUN_ATTEMPTS = 100
# The compiled run is machine code up to this many unknowns, jit="auto"'s most (.backend.JIT_AUTO_MAX_SIZE;
# above, on casadi's virtual machine around the step's machine code).  Its C (the Jacobian at the step's
# start and at the stages, the controller) adds to the compile: with casadi's mapaccum the chain of 20
# pendulums compiled 3.5x longer; with the loop in C (.loop.run_loop_source) the chains of 20 and 40 take
# 1.07 -> 1.71 and 2.83 -> 4.22 s of compiler CPU (once per machine: the disk cache) for solves 11 and 8 %
# shorter (4.60 -> 4.09, 9.71 -> 8.98 ms at rtol 1e-6, benchmarks/compile_cost.py).
MACHINE_RUN_MAX_SIZE = 200

# What the disk cache did (daemodel.cache), the most telling first: a refused folder, a library not
# stored, compiled and stored, loaded from disk, built earlier in this process.
CACHE_OUTCOMES = ("refused:", "not", "miss", "hit", "memory")


class CasadiEngine(AbstractEngine):
    """One trajectory in float64 on casadi-compiled functions and scipy's LU (see the module docstring)."""

    name = "casadi"

    def __init__(self, compiled, start, tableau, transform, jit: bool = False, band: bool = False):
        super().__init__(compiled, start, tableau, transform)
        self.xp, self.B, self.p = np, 1, np.asarray(start.p, dtype=float)[0]
        self.increment = IncrementBuffers(transform, self.n, self.D)  # (Newton's increment on the general path)
        self.jit, self.band, self.band_outcomes = jit, band, []  # (band: narrow band orders' LU in C, .band)
        self.cache_outcomes = []  # (jit: what the disk cache did for each library compiled: _machine_code)
        self._kernel = None  # (jit with static factors: the C functions static_factors and sign_det, .kernel)
        # (stencil: a repeated stencil's f, g and residual in C above 200 unknowns, without jit: .stencil)
        functions, lent, stage_f, self.stencil = engine_functions(compiled, tableau, band and not jit)
        # (jit leaves these on casadi's virtual machine: compiled, the residual of 200 unknowns took 8 s to
        # build and saved 6 % of the solve; the steps below are where Python waited on casadi)
        self._f, self._residual, self._jac, self._stage_jac = (*(lend(self, fn) for fn in lent), None)
        self.rows, self.cols = functions[4:]
        self._functions = functions
        # (the stages' f on the residual's packed input, a stencil's on the caller's arrays (.stencil.Sliced), and
        # f at the stages' part of its output: 4.4 and 2 MB at 10^5 unknowns)
        out, kind = self._residual._outputs[self.s * self.D :], getattr(stage_f, "buffered", Buffered)
        self._stage_f = None if stage_f is None else kind(stage_f, 1, self._residual, out)
        D = self.D
        # sparse: the full Newton matrix's CSC layout (factor_stages, on first use), the band order (_sparse_layout)
        self._stage_layout = self._order = None
        self.dense = dense_systems(D, len(self.rows))
        self._step = None  # dense: the fused Newton step (see newton_step), and the factors it is bound to
        self._identity = None  # dense: real and complex identities, the right-hand sides of the inverses
        if self.dense:
            self._identity = (np.eye(D), np.eye(D, dtype=complex))
            if not jit:  # (with jit it is compiled with the compiled step, or alone: make_newton_step)
                self._step = [lend(self, self._newton_step_function(), inputs=2), None]
        else:
            self._sparse_layout()
        self._compiled = None  # dense: the compiled adaptive step and the factors bound to it (make_compiled_step)
        self._inverses = None  # dense: the compiled inverses of the shifted systems (_compiled_factor)
        self._refresh = None  # dense: Jacobian, inverses and iteration matrix in one call (refresh)
        # above COMPILED_FACTOR_MAX_SIZE, where the pattern is sparse: LU factors with a fixed pivot order as
        # compiled functions (.sparse), the pivots SuperLU picks at the first solve's start (per model and s)
        self.static = None  # (StaticFactors where the compiled step reads them: see make_compiled_step)
        self._static = {}  # (on bound buffers, made on first use: the factor function, the real and complex solves)
        self._static_active = False  # the compiled step reads the static factors: factor() makes them
        self._machine_run = None  # (jit on static factors: the compiled run in machine code, _library)
        self._version = 0  # (the .pivots order the static factors are built for)
        self.pivot_failures = 0  # static factorisations that did not hold, factored by LAPACK or SuperLU
        self._start = start

    def _machine_code(self, build, key):
        """What ``build()`` compiles (a :class:`.compiled.MachineCode` or a :class:`daemodel.cache.Library`:
        built once per model and ``key``, through the disk cache); what the cache did is added to
        :attr:`cache_outcomes` ("memory" where this process built it before)."""
        built = []

        def once():
            built.append(build())
            return built[-1]

        code = self.compiled.cached((*key, "machine code"), once)
        self.cache_outcomes.append(code.outcome if built else "memory")
        return code

    def _newton_step_function(self):
        """The casadi function of the fused Newton step (:func:`.compiled.newton_step_function`), built
        once per model and stages."""
        build = lambda: newton_step_function(self._functions[1], self)  # noqa: E731
        return self.compiled.cached(("casadi-radau-step", self.s), build)

    def make_newton_step(self) -> None:
        """With ``jit``, on dense systems whose compiled step did not bring it (none made, or one on
        static factors, whose general path solves with them), the fused Newton step in machine code:
        called once in the setup (:class:`.step.Stepper`), so that no compiling runs in the solve."""
        if not self.dense or self._step is not None or self._static_active:
            return
        key = ("casadi-radau-step", self.s)
        code = self._machine_code(lambda: machine_code(self._newton_step_function(), find_compiler()), key)
        self._step = [lend(self, code.function, inputs=2), None]

    def cache_outcome(self) -> str | None:
        """What the disk cache of compiled libraries did for this engine's machine code, in one word
        (:data:`CACHE_OUTCOMES`' most telling of :attr:`cache_outcomes`), or None without ``jit``."""
        if not self.cache_outcomes:
            return None
        return min(self.cache_outcomes, key=lambda outcome: CACHE_OUTCOMES.index(outcome.split(" ")[0]))

    def make_compiled_step(self, iterations: int, e: np.ndarray, jit: bool = False) -> bool:
        """Build (or fetch, cached per model, s and ``iterations``) the compiled adaptive step (``e``:
        the error estimate's ``bhat - b``), in machine code with ``jit`` (the system's C compiler, one
        library with the rest of the solve's machine code, :meth:`_library`: 0.5-3 s once per machine,
        the disk cache keeps it); False where the systems are sparse beyond the fixed-pivot factors' reach
        (:data:`STATIC_MAX_FLOPS`, :data:`STATIC_MAX_SIZE_VM`) and the step runs on the general path."""
        D, self.first_step = self.D, Start.of(self)  # (the first step's function, in the setup: .start)
        orders = self._pivot_orders() if jit or COMPILED_FACTOR_MAX_SIZE < D <= STATIC_MAX_SIZE_VM else None
        lu, version = None, 0
        if orders is not None:  # (re-derived where it stopped holding in an earlier solve of this model: .pivots)
            start = self._start
            key = b"".join(
                np.asarray(v, dtype=float).tobytes() for v in ([self.compiled.t0], start.y0, start.z0, start.p)
            )
            shifts = [lam for _, lam in self.transform.blocks]
            lu, version = orders.for_start(key, shifts, STATIC_MAX_FLOPS, STATIC_MAX_ENTRIES)
        if lu is not None and not jit and (lu.flops > STATIC_MAX_FLOPS_VM or lu.entries > STATIC_MAX_FILL * D * D):
            lu = None  # (on casadi's virtual machine its factors cost more than LAPACK's or SuperLU's)
        if not self.dense and lu is None:
            return False
        # (with jit the step's triangular solves call the loops of .kernel: the same bits, a third of the code)
        key = ("casadi-radau-static", self.s, jit, version)
        solver = self.static = (
            None if lu is None else self.compiled.cached(key, lambda: StaticFactors(lu, self.transform, jit))
        )
        compiled, functions = self.compiled, self._functions
        self._static_active = solver is not None
        self._version = version
        weights = np.array(compiled.algebraic_index, dtype=float)
        key = ("casadi-radau-compiled-step", self.s, iterations, solver is not None, jit, version)
        build = lambda: step_function(functions[0], functions[1], self, iterations, e, weights, solver)  # noqa: E731
        step = compiled.cached(key, build)
        if jit:
            step = self._library(step, key)
        self._compiled = [lend(self, step, inputs=2), None]
        self.step_input, self.step_output = step_layouts(self.s, self.n, self.D, self.p.size)
        if solver is not None and "factor" not in self._static:
            # made now, in the setup: its code generation (0.4 s for a chain of 16 pendulums) ran inside the
            # first solve's integration, at its first factorisation
            self._static["factor"] = lend(self, self._static_factor_function())
        return True

    def _library(self, step, key):
        """The machine code of the compiled ``step`` in one library with all a solve runs in machine code
        besides: on static factors :mod:`.kernel`'s C (factors, a determinant's sign, the general path's
        solves) and the compiled run (:mod:`.loop`), else on dense systems the fused Newton step (the
        stage residual compiled once for both).  One compiler run per model, stages and iterations."""
        static, m = self.static, self.m
        functions = {"radau_step_machine_code": step}
        if static is None and self.dense:
            functions["newton_step_machine_code"] = self._newton_step_function()
        names, run = (), None
        if static is not None:
            names = ("static_factors", "static_solve", "static_solve_complex", *(("sign_det",) if m else ()))
            if self.D <= MACHINE_RUN_MAX_SIZE:
                functions[MACHINE_ATTEMPT] = run = self._machine_attempt_function(step, key[2])
                names += ("radau_run_machine_code",)
        what = f"radau's machine code: compiling the step of {step.name()!r}"

        def build():
            # (the kernel's source only where the library is built: writing it took 8 ms, paid by every piece
            # between events when it stood outside, 563 times for the wheelset at rtol 1e-6)
            kernel = "" if static is None else kernel_source(static.lu, self.transform, static, m)
            after = "" if run is None else run_loop_source(self, run, MACHINE_RUN_ATTEMPTS)
            return machine_library(functions, find_compiler(), kernel, names, what, after)

        code = self._machine_code(build, key).functions
        if "newton_step_machine_code" in code:
            self._step = [lend(self, code["newton_step_machine_code"], inputs=2), None]
        if static is not None:
            self._kernel = (code["static_factors"], code.get("sign_det"))
            self._static[False] = lend(self, code["static_solve"], inputs=2)
            self._static[True] = lend(self, code["static_solve_complex"], inputs=2)
            self._machine_run = code.get("radau_run_machine_code")
        return code["radau_step_machine_code"]

    def _machine_attempt_function(self, step, iterations: int):
        """One attempt of the compiled run (:func:`.loop.attempt_function`) around the casadi ``step``, for
        machine code in one library with it, the kernel and the loop in C that calls it (:meth:`_library`,
        :func:`.loop.run_loop_source`): the static factors and the determinant's sign are calls into the
        kernel's C (:func:`.kernel.factor_call`, :func:`.kernel.sign_call`), so that nothing of the run is
        left to casadi's virtual machine (car axis, 10 unknowns: ~10 of its ~17 us an attempt)."""
        static, m = self.static, self.m

        def build():  # (its pieces only where it is built: they cost ~40 us of casadi per solve that needs it)
            factor = factor_call(static.lu, static)
            sign = sign_call(m) if m > 3 else None  # (up to m = 3 the run's own formula: sign_det_function)
            refresh = refresh_function(self._functions[2], factor, self.rows, self.cols, self, sparse=True)
            functions = (refresh, factor, self._functions[3](), sign, static)
            return attempt_function(self, step, *functions, iterations, machine=True)

        key = ("casadi-radau-machine-attempt", self.s, iterations, self._version)  # (._version: .pivots)
        return self.compiled.cached(key, build)

    def _sparse_layout(self):
        """``sigma M - J``'s CSC layout, in the band order (``band``: LU in C) where any (.sparse.shifted_layout)."""
        layout = shifted_layout(self.compiled, self.rows, self.cols, self.n, self.band_outcomes if self.band else None)
        self._order, self._csc, self._pos_J, self._pos_M = layout

    def asarray(self, values):
        return np.array(values, dtype=float)

    def factor(self, J, h: float, error_only: bool = False) -> Factors:
        if self._static_active:
            factors = self._static_factor(J, h)
            # (else SuperLU or LAPACK, whose factors the compiled step does not read: the general path)
            return factors if factors is not None else super().factor(J, h, error_only)
        if self.dense and not error_only and self.D <= COMPILED_FACTOR_MAX_SIZE:
            factors = self._compiled_factor(J, h)
            if factors is not None:
                return factors
        factors = super().factor(J, h, error_only)
        if self.dense and factors.complete and not factors.singular.any():
            # the blocks' inverses, column-major as casadi reads them, complex ones as (Re, Im)
            packed = []
            for _, lam in self.transform.blocks:
                inverse = factors.lu[lam / h][1]
                packed += [inverse.real.ravel("F")] + ([inverse.imag.ravel("F")] if lam.imag else [])
            packed.append(factors.lu[factors.error_shift][1].real.ravel("F"))  # the error estimate's (compiled step)
            factors.inverse = np.concatenate(packed)
        return factors

    def _inverse_function(self):
        """The casadi function of the shifted systems' inverses (:func:`.compiled.inverse_function`),
        built once per model and stages."""
        build = lambda: inverse_function(self.rows, self.cols, self)  # noqa: E731
        return self.compiled.cached(("casadi-radau-inverses", self.s), build)

    def _compiled_factor(self, J, h: float) -> Factors | None:
        """The inverses of every shift in one casadi call, or None where one is singular or not finite
        (scipy's LAPACK then factors, and names it)."""
        if self._inverses is None:
            self._inverses = lend(self, self._inverse_function())
        try:
            with captured_output():
                packed = self._inverses(np.concatenate([[h], J]))
        except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
            raise
        except RuntimeError:
            return None
        return self._packed_factors(packed, h)

    def _packed_factors(self, packed: np.ndarray, h: float) -> Factors | None:
        """:class:`Factors` of the packed inverses of the compiled factorisation (static factors where the
        compiled step reads them); None where one is not finite."""
        if self._static_active:
            return self._static_packed(packed, h)
        if not np.isfinite(packed.sum()):
            return None
        shifts = self.transform.shifts(h)
        error = self.transform.error_shift(shifts)
        lu = PackedInverses(packed, self.transform, shifts, self.D)
        return Factors(h=h, shifts=shifts, lu=lu, singular=_NOT_SINGULAR, error_shift=error, inverse=packed)

    def _static_pattern(self):
        """The :class:`.sparse.StaticLU` of this model's Jacobian pattern in the pivot order in use (see
        :meth:`_pivot_orders`), or None where its elimination exceeds :data:`STATIC_MAX_FLOPS`, its factors
        :data:`STATIC_MAX_ENTRIES`, or J is not finite there."""
        return self._pivot_orders().lu

    def _pivot_orders(self):
        """The :class:`.pivots.PivotOrders` of this model (cached per model): first the pivots SuperLU
        picks for ``sigma M - J`` at the start of the model's first adaptive solve (sigma 1000 times J's
        largest entry, a short step), re-derived in a later solve's setup where they stopped holding."""
        return self.compiled.cached(("casadi-radau-pivot-orders",), lambda: PivotOrders(self._static_lu(self._start)))

    def _static_lu(self, start):
        """See :meth:`_static_pattern`."""
        D = self.D
        # the factors hold at least sigma M - J's entries and D pivots (fill only adds): where that is beyond
        # STATIC_MAX_ENTRIES already, no elimination is traced (it took 2.2 s in Python at 50,000 unknowns)
        if D > STATIC_MAX_ENTRIES or unique_entries(self.rows, self.cols, self.n, D) > STATIC_MAX_ENTRIES:
            return None
        J = self.jacobian(
            self.compiled.t0, np.asarray(start.y0, dtype=float)[:1], np.asarray(start.z0, dtype=float)[:1]
        )
        if not np.isfinite(J).all():
            return None
        scale = 1e3 * max(1.0, float(np.abs(J).max(initial=0.0)))
        orders = []  # (static pivoting's and SuperLU's, where they hold here: .pivots.first_order chooses)
        # SuperLU's first: static pivoting's elimination is stopped beyond what first_order could take of it
        # (MATCHED_MAX_COST x SuperLU's where that holds), not traced to its end (seconds at 1,000 unknowns)
        for pivoting in sorted(PIVOTING, key=lambda kind: kind != "partial"):
            budget = STATIC_MAX_FLOPS
            if pivoting == "matched" and orders:
                budget = min(budget, MATCHED_MAX_COST * orders[0].flops)
            try:
                lu = StaticLU(self.rows, self.cols, self.n, self.D, J, 1.0 / scale, 1.0, pivoting, budget)
            except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
                raise
            except RuntimeError:  # (SuperLU: "Factor is exactly singular", or over its budget: no order from it)
                continue
            if lu.entries <= STATIC_MAX_ENTRIES and holds(lu, J, 1.0 / scale, [1.0]):
                orders.append(lu)
        return first_order(orders)

    def _static_factor(self, J, h: float) -> Factors | None:
        """:class:`Factors` of every shift with the fixed-pivot sparse LU, or None where their growth
        passes :data:`.sparse.MAX_GROWTH`, a pivot is 0 or a value is not finite (a singular system
        among them, or one the fixed order does not suit).  (Its function is made with the compiled
        step, :meth:`make_compiled_step`, which alone makes the static factors active.)"""
        factors = self._static_packed(self._static["factor"](np.concatenate([[h], J])), h)
        if factors is None:  # (LAPACK or SuperLU factors it instead; a later solve may take another order)
            self.pivot_failures += 1
            self._pivot_orders().record(J, h)
        return factors

    def _static_solve(self, complex_: bool):
        """The real or complex triangular solve of the static factors, on bound buffers (made on first
        use: the compiled step solves inside, Python only on the general path)."""
        if complex_ not in self._static:
            self._static[complex_] = lend(self, self.static.solves[complex_], inputs=2)
        return self._static[complex_]

    def _static_packed(self, packed: np.ndarray, h: float) -> Factors | None:
        """:class:`Factors` of the packed static factors (see :meth:`_static_factor`), or None."""
        growth, pivot = packed[-2:]
        with np.errstate(invalid="ignore", over="ignore"):  # (inf - inf in the sum: not finite, and said below)
            finite = np.isfinite(packed.sum())
        if not finite or growth > MAX_GROWTH or pivot == 0:
            return None
        shifts = self.transform.shifts(h)
        error = self.transform.error_shift(shifts)
        lu, static = {}, self.static
        for (_, lam), shift, offset in zip(self.transform.blocks, shifts, static.offsets, strict=False):
            complex_ = bool(lam.imag)
            lu[shift] = ("static", complex_, packed[offset : offset + static.lu.size(complex_)])
        if error not in lu:
            lu[error] = ("static", False, packed[static.error_offset : static.checks_offset])
        return Factors(h=h, shifts=shifts, lu=lu, singular=_NOT_SINGULAR, error_shift=error, inverse=packed)

    def _static_factor_function(self):
        """The casadi function of the packed static factors from ``[h, J's nonzeros]`` (cached per model
        and s): with ``jit`` the loop of :mod:`.kernel` in C, else straight-line SX
        (:func:`.increments.static_factor_function`); the same factors bit for bit."""
        if self.jit:
            return self._static_kernel()[0]
        build = lambda: static_factor_function(self.static.lu, self.transform)  # noqa: E731
        return self.compiled.cached(("casadi-radau-static-factor", self.s, self._version), build)

    def _static_kernel(self):
        """:mod:`.kernel`'s C static factors and sign of det (None where m = 0), in the step's library (_library)."""
        return self._kernel

    def _refresh_function(self):
        """The casadi function of a fresh Jacobian with its factored systems (:func:`.compiled.refresh_function`),
        built once per model and stages."""
        inverses = self._inverse_function()
        build = lambda: refresh_function(self._functions[2], inverses, self.rows, self.cols, self)  # noqa: E731
        return self.compiled.cached(("casadi-radau-refresh", self.s), build)

    def make_compiled_run(self, iterations: int):
        """RADAU5's controller over many attempts in one call (:mod:`.loop`), on the compiled step of
        :meth:`make_compiled_step` (its machine code with ``jit``); None where there is no compiled step,
        or above :data:`COMPILED_FACTOR_MAX_SIZE` unknowns unless the step reads static factors and
        ``jit`` makes them in C (:mod:`.kernel`, with the determinant's sign; on casadi's virtual
        machine their factorisation would cost more than the run saves)."""
        static = self._static_active and self.jit
        if self._compiled is None or (self.D > COMPILED_FACTOR_MAX_SIZE and not static):
            return None
        if static and self._machine_run is not None:  # (in machine code with the step: _library)
            return CompiledRun(self._machine_run, self)
        step = self._compiled[0].function
        key = ("casadi-radau-run", self.s, iterations, self.jit, static, self._version if static else 0)

        def build():
            # (the functions only where the run is built: the sparse refresh, 1-3 ms, was made again by every
            # piece between events)
            if static:  # (the factors and the determinant's sign in C: .kernel)
                factor, sign = self._static_kernel()
                refresh = refresh_function(self._functions[2], factor, self.rows, self.cols, self, sparse=True)
                functions = (refresh, factor, self._functions[3](), sign, self.static)
            else:
                functions = (self._refresh_function(), self._inverse_function(), self._functions[3](), None, None)
            return run_function(self, step, *functions, iterations)

        return CompiledRun(self.compiled.cached(key, build), self)

    def packed_size(self) -> int:
        """Entries of the packed factors the compiled step reads (static factors, or dense inverses)."""
        return self.static.size if self._static_active else inverse_size(self.transform, self.D)

    def refresh(self, t: float, y, z, h: float):
        """A fresh Jacobian, step ``h``'s systems factored and z's iteration matrix's sign in one call on dense systems
        (:func:`.compiled.refresh_function`); else J in its function's output buffer, not a copy (2.4 MB at 10^5)."""
        if not self.dense or self.D > COMPILED_FACTOR_MAX_SIZE or self._static_active:  # (J: the stepper's, the one
            return self._jac.packed(t, y[0], z[0], self.p, copy=False), None, None  # caller, until its next refresh)
        if self._refresh is None:
            self._refresh = lend(self, self._refresh_function())
        try:
            with captured_output():
                out = self._refresh(np.concatenate([[t], y[0], z[0], self.p, [h]]))
        except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
            raise
        except RuntimeError:  # a singular system: the general path factors it and names it
            return super().refresh(t, y, z, h)
        nnz, m = len(self.rows), self.m
        J = out[:nnz]
        sign = np.array([small_sign_det(out[nnz : nnz + m * m], m)])
        return J, self._packed_factors(out[nnz + m * m :], h), sign

    def compiled_step(self, factors: Factors, scalars: dict, previous: np.ndarray, f0: np.ndarray) -> np.ndarray:
        """One adaptive attempt in one call (:mod:`.compiled`): ``scalars`` by the names of its
        ``STEP_SCALARS``, ``previous`` ((s+1) D) the last step's start value and stages, ``f0`` (n) f at
        the step's start; returns its packed output (:attr:`step_output`)."""
        step, bound = self._compiled
        if bound is not factors:
            step.inputs[1][:] = factors.inverse
            self._compiled[1] = factors
        x, layout = step.inputs[0], self.step_input
        x[: len(STEP_SCALARS)] = [scalars[name] for name in STEP_SCALARS]
        x[layout["nodes"]], x[layout["f0"]], x[layout["p"]] = previous, f0, self.p
        return step.evaluate()

    def _factor_shifts(self, values, shifts):
        """Dense systems: each ``sigma M - J``'s inverse (LAPACK: the fused Newton step's products)."""
        if not self.dense:  # (sparse ones: SuperLU's or the band kernel's factors, -J placed once for all)
            return factor_shifts(values, shifts, self._csc, self._pos_J, self._pos_M, self._order)
        minus_J = -self._dense(values)
        diagonal = slice(0, self.n * (self.D + 1), self.D + 1)  # M's diagonal in the flattened matrix
        lu, singular = {}, False
        for sigma in shifts:
            matrix = minus_J.copy() if sigma.imag == 0 else minus_J.astype(complex)
            matrix.ravel()[diagonal] += sigma.real if sigma.imag == 0 else sigma
            lu[sigma] = dense_inverse(matrix, self._identity[sigma.imag != 0])
            singular = singular or lu[sigma][0] == "singular"
        return lu, np.array([singular])

    def newton_step(self, factors, t, h, y, W):
        """One casadi call for the residual and the transformed systems' increment (by their inverses)
        on dense systems; the residual and LU solves apart otherwise (full Newton, sparse systems)."""
        if not isinstance(factors, Factors) or factors.inverse is None or self._static_active:
            return super().newton_step(factors, t, h, y, W)
        if self._step is None:  # (an engine made outside a solve; a solve makes it in its setup)
            self.make_newton_step()
        step, bound = self._step
        if bound is not factors:
            step.inputs[1][:] = factors.inverse
            self._step[1] = factors
        s, n, D = self.s, self.n, self.D
        out = step(np.concatenate([[t, h], y[0], W.ravel(), self.p]))
        R = out[: s * D].reshape(1, s, D)
        stage_f = out[s * D : s * D + s * n].reshape(1, s, n)
        return Residual(R=R, stage_f=stage_f, G=R[..., n:]), out[s * D + s * n :].reshape(1, s, D)

    def f(self, t, y, z):
        return self._f.packed(t, y[0], z[0], self.p)[None]

    def residual(self, t, h, y, W):
        """The stage residual in the function's output buffer, overwritten by the next call (no 0.6 MB copy at
        10^4 unknowns, s = 5): a caller copies what it keeps (:meth:`.step.Stepper.accept`: f at the last stage)."""
        out = self._residual.packed(t, h, y[0], W, self.p, copy=False)
        R = out[: self.s * self.D].reshape(1, self.s, self.D)
        return Residual(R=R, stage_f=out[self.s * self.D :].reshape(1, self.s, self.n), G=R[..., self.n :])

    def stage_values(self, t, h, y, W):
        """f at the stages, in the function's output buffer (as :meth:`residual`'s)."""
        if self._stage_f is None:  # (up to INLINED_RESIDUAL_MAX_SIZE unknowns: the residual inlines f)
            return super().stage_values(t, h, y, W)
        f = self._stage_f.packed(t, h, y[0], W, self.p, copy=False)
        return Residual(R=None, stage_f=f.reshape(1, self.s, self.n), G=None)

    def jacobian(self, t, y, z):
        return self._jac.packed(t, y[0], z[0], self.p)

    def stage_jacobians(self, t, h, W):
        self._stage_jac = self._stage_jac or lend(self, self._functions[3]())  # (s J's: lent at first use)
        return list(self._stage_jac.packed(t, h, W, self.p).reshape(self.s, -1))

    def _dense(self, values) -> np.ndarray:
        (J := np.zeros((self.D, self.D)))[self.rows, self.cols] = values
        return J

    def _csr(self, values):
        import scipy.sparse as sparse

        return sparse.csr_matrix((values, (self.rows, self.cols)), shape=(self.D, self.D))

    def z_matrix_sign(self, values):
        if isinstance(values, list):  # the stages' Jacobians: (1, s)
            return np.array([[self.z_matrix_sign(v)[0] for v in values]])
        n = self.n
        if self.dense:
            J = self._dense(values)
            rows = J[n:, n:].copy()
            if self.index2_rows.any():
                rows[self.index2_rows] = (J[n:, :n] @ J[:n, n:])[self.index2_rows]
            return np.array([dense_sign_det(rows)])
        if self.m <= DENSE_MAX_SIZE:  # a small z block of a large system: dense blocks of J suffice
            g_rows = self.rows >= n
            G = np.zeros((self.m, self.D))
            G[self.rows[g_rows] - n, self.cols[g_rows]] = values[g_rows]
            rows = G[:, n:].copy()
            if self.index2_rows.any():
                f_z = (self.rows < n) & (self.cols >= n)
                F = np.zeros((n, self.m))
                F[self.rows[f_z], self.cols[f_z] - n] = values[f_z]
                rows[self.index2_rows] = (G[:, :n] @ F)[self.index2_rows]
            return np.array([dense_sign_det(rows)])
        if not self.index2_rows.any():  # (g_z's entries picked from J's: no sparse J, 4 MB at 10^5 unknowns)
            block = lambda: z_block(self.rows, self.cols, n)  # noqa: E731  (kept with the model, for this pattern)
            at, rows, cols = self.compiled.cached("radau-z-block", block, on=(self.rows, self.cols))
            return np.array([block_sign_det(values[at], rows, cols, self.m)])
        import scipy.sparse as sparse

        J = self._csr(values)
        pick = sparse.diags(self.index2_rows.astype(float))
        rows = J[n:, n:] - pick @ J[n:, n:] + pick @ (J[n:, :n] @ J[:n, n:])
        return np.array([sparse_sign_det(rows.tocsc())])

    def _factor_shift(self, values, sigma):
        """SuperLU's factors of ``sigma M - J`` (dense systems: see :meth:`_factor_shifts`)."""
        lu, singular = factor_shifts(values, (sigma,), self._csc, self._pos_J, self._pos_M, self._order)
        return lu[sigma], singular

    def solve(self, lu, rhs, out=None):
        if out is not None and not (len(lu) == 2 and isinstance(lu[1], (BandLU, OrderedLU))):  # (out may be rhs)
            out[...] = self.solve(lu, rhs)
            return out
        kind = lu[0]
        if kind == "inverse":
            return (lu[1] @ rhs[0])[None]
        if kind == "dense":
            LU, piv, getrs = lu[1:]
            if not np.iscomplexobj(LU) and np.iscomplexobj(rhs):
                return (getrs(LU, piv, rhs[0].real)[0] + 1j * getrs(LU, piv, rhs[0].imag)[0])[None]
            return getrs(LU, piv, rhs[0])[0][None]
        if kind == "singular":
            return np.full_like(rhs, np.nan)
        if kind == "static":
            _, complex_, packed = lu
            solve = self._static_solve(complex_)
            solve.inputs[0][:] = packed
            if complex_:
                solve.inputs[1][:] = np.concatenate([rhs[0].real, rhs[0].imag])
                x = solve.evaluate()
                return (x[: self.D] + 1j * x[self.D :])[None]
            solve.inputs[1][:] = rhs[0].real if np.iscomplexobj(rhs) else rhs[0]
            return solve.evaluate()[None]
        return lu[1].solve(rhs[0], **({} if out is None else {"out": out[0]}))[None]  # (SuperLU's own takes no out)

    def factor_stages(self, stage_J, h):
        s, n, D = self.s, self.n, self.D
        A = self.tableau.A
        if self.dense:
            # rows [F_i; G_i] and unknowns [Y_j; Z_j] stage by stage (see TorchEngine.factor_stages)
            Js = np.stack([self._dense(v) for v in stage_J])  # (s, D, D)
            N = np.zeros((s, D, s, D))
            N[:, :n] = (-h * A[:, None, :, None]) * Js[None, :, :n, :].transpose(0, 2, 1, 3)
            for i in range(s):
                N[i, n:, i, :] = Js[i, n:, :]
                N[i, :n, i, :n] += np.eye(n)
            lu, singular = dense_lu(N.reshape(s * D, s * D))
            return StageFactors(lu=lu, singular=singular)
        import scipy.sparse as sparse

        if self._stage_layout is None:
            self._stage_layout = self._full_newton_layout()
        top, bottom, positions, (indices, indptr, nnz) = self._stage_layout
        V = np.stack(stage_J)  # (s, nnz of J)
        values = np.concatenate(
            [((-h) * A[:, :, None] * V[None, :, top]).ravel(), V[:, bottom].ravel(), np.ones(s * n)]
        )
        data = np.bincount(positions, weights=values, minlength=nnz)  # sums the identity into J's diagonal
        lu, singular = sparse_lu(sparse.csc_matrix((data, indices, indptr), shape=(s * D, s * D)))
        return StageFactors(lu=lu, singular=singular)

    def _full_newton_layout(self):
        """Where each entry of the full Newton matrix goes in its CSC data, computed once.

        Entries, in the order :meth:`factor_stages` lays out their values: ``-h a_ij J_j`` on the F rows
        of every block (i, j), ``J_i`` on the G rows of the diagonal blocks, the identity of the F rows.
        """
        s, n, D = self.s, self.n, self.D
        top, bottom = np.flatnonzero(self.rows < n), np.flatnonzero(self.rows >= n)
        i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
        rows = [
            (i[:, :, None] * D + self.rows[None, None, top]).ravel(),
            (np.arange(s)[:, None] * D + self.rows[None, bottom]).ravel(),
            (np.arange(s)[:, None] * D + np.arange(n)[None, :]).ravel(),
        ]
        cols = [
            (j[:, :, None] * D + self.cols[None, None, top]).ravel(),
            (np.arange(s)[:, None] * D + self.cols[None, bottom]).ravel(),
            rows[2],
        ]
        keys_all = np.concatenate(cols) * (s * D) + np.concatenate(rows)  # CSC order: column, then row
        keys = sorted_unique(keys_all)
        indptr = np.searchsorted(keys // (s * D), np.arange(s * D + 1))
        return top, bottom, np.searchsorted(keys, keys_all), (keys % (s * D), indptr, len(keys))

    def solve_stages(self, factors, R):
        s, D = self.s, self.D
        return self.solve(factors.lu, -R.reshape(1, s * D)).reshape(1, s, D)

    def first(self, mask):
        return int(np.flatnonzero(mask)[0])


_NOT_SINGULAR = np.array([False])  # (shared: never written)
