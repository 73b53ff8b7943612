"""Radau IIA in torch: Newton on the compiled, batched stage residual.

Each step solves ``F = 0, G = 0`` of :func:`daemodel.collocation.stage_residual` (the
equations the Radau-PINN minimises) for the stage values of every sample at once, with a
simplified Newton method: one Jacobian ``[f_y f_z; g_y g_z]`` at the step's start (forward-mode
autograd through the generated code), one batched LU of the ``s(n+m)`` stage matrix, reused
across iterations and, while Newton contracts fast, across steps.

Fixed step (``h=...``) reproduces the Radau IIA collocation solution on the grid
``t0 + k h``.  Where the simplified iteration fails, full Newton (each stage's Jacobian) tries
the step again, and where that fails too, damped Newton (Deuflhard's natural monotonicity test,
:data:`DAMPED_NEWTON_FACTOR`): a fixed step has no smaller h to fall back on.  A step whose
extrapolated start guess leaves f's domain starts again from its start value.

Adaptive mode (``rtol``, ``atol``) estimates the local error with an embedded formula of order s
(Hairer & Wanner, Solving ODEs II, IV.8, generalised to s stages): with ``gamma0`` the real
eigenvalue of A (s odd) and ``bhat`` of order s including the start point,

    (M - h gamma0 J) err = [gamma0 h f(y_n) + h sum_i (bhat_i - b_i) f(Y_i) ; 0]

where ``M = diag(I, 0)``.  As in RADAU5, the error of an algebraic variable determined through
an index-k constraint is multiplied by ``h^(k-1)`` before the norm (its stage values are only
accurate to order s - k + 2).  A batch shares the step sequence (the worst sample decides).

Fixed step computes the same estimate after every step, with the Jacobian Newton already used,
in units of the solution's size ``1 + max |u|`` so far, reports its maximum as
``stats["max_local_error_estimate"]`` and refuses a step whose estimate exceeds
:data:`LOCAL_ERROR_BOUND` (:class:`~daemodel.errors.LocalErrorBoundError`): Newton converges on
a step across a singularity as readily as on a good one, and only the estimate tells them apart.

Adaptive mode stops Newton on the contraction rate of the last step, as RADAU5 does, but a step
declared converged after a single iteration is checked with one more increment (one LU solve):
trusting that rate alone accepted unconverged stages, 100 x rtol errors on the pendulum and finite
garbage on a switching f such as sign(x).

Every loop is bounded: ``max_steps`` bounds the fixed grid (checked before it is built) and, in
adaptive mode, every step attempt, accepted, rejected or failed in Newton
(:class:`~daemodel.errors.StepLimitError`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    LOCAL_ERROR_BOUND,
    SWEEP_FIRST_STEPS,
    AbstractBackend,
    ProgressWatch,
    check_dtype,
    check_number,
    check_stages,
    check_threads,
    check_tolerances,
    fixed_grid,
    fixed_step_sweep,
    grid_steps,
    make_solution,
    output_times,
    torch_device,
    torch_threads,
)
from daemodel.backends.radau_compiled import CONVERGED
from daemodel.backends.radau_engines import CasadiEngine, Residual, StageFactors, StageTransform, TorchEngine

from daemodel.collocation import extrapolation_polynomial, horner, lagrange_matrix
from daemodel.errors import (
    ConvergenceError,
    InvalidOptionError,
    LocalErrorBoundError,
    ResourceLimitError,
    StepLimitError,
)
from daemodel.files import check_memory, memory_limit
from daemodel.tableau import radau_iia

# Stages of a fixed step when none are given: the paper's v = 3 (order 5).
FIXED_STAGES = 3
# Stages of adaptive mode when none are given, by rtol: (smallest rtol, stages), loosest first.
# Measured at equal error on the pendulums, Robertson, the squeezer and the scaling families
# (benchmarks/adaptive_precision.py): s = 5 takes 3-5x fewer steps than s = 3 below rtol 1e-6
# for 1.3-2x the cost of a step, and s = 7 pays off only below 1e-10 (at looser tolerances
# its steps are rejected or fail Newton more often).
ADAPTIVE_STAGES = ((1e-6, 3), (1e-10, 5), (0.0, 7))
# Fixed step: Newton stops when the scaled increment is below this many eps of the dtype.
FIXED_NEWTON_TOL_EPS = 10
# Who evaluates and factors: "auto" picks casadi for one float64 CPU trajectory, torch otherwise.
ENGINES = ("auto", "torch", "casadi")
# Tolerances of adaptive mode when neither h nor rtol/atol is given.
DEFAULT_RTOL, DEFAULT_ATOL = 1e-6, 1e-8
# float32 carries ~7 digits: asking for more from it is an error, not a silent loss.
FLOAT32_MIN_RTOL = 1e-5
# Step-size controller (RADAU5's values): safety factor, and bounds on h_new / h.
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 8.0
# Keep h (and the LU) when the controller asks for a change within this band (RADAU5's QUOT1/2).
KEEP_H_BAND = (1.0, 1.2)
# Reuse the Jacobian for the next step when Newton contracted at least this fast (RADAU5's THET:
# 0.001 for small systems, "0.1, say" where Jacobians and factorisations are costly).  Above
# REUSE_LARGE_SIZE unknowns REUSE_THETA_LARGE applies.  Measured at equal error (rtol 1e-6, 1e-8):
# chains of 40 and 160 unknowns and 160 dense particles 1.2-1.9x faster, a 600-unknown grid 1.3-2x;
# the pendulum (5) at rtol 1e-10 and the squeezer (27) 1.3x slower (more iterations, cheap LUs).
REUSE_THETA, REUSE_THETA_LARGE, REUSE_LARGE_SIZE = 1e-3, 0.03, 32
# Above this contraction rate, Newton switches to per-stage Jacobians at the current iterate.
REFRESH_THETA = 0.05
# Fixed step: increments that stop shrinking (contraction above STAGNATION_THETA) while within
# STAGNATION_FACTOR of newton_tol have reached the rounding floor of the residual.
STAGNATION_THETA, STAGNATION_FACTOR = 0.5, 100.0
# After a step needed full Newton (per-stage Jacobians), this many steps start with it directly,
# then the transformed systems are tried again: where the Jacobian varies along the step (the
# pendulum at h = 0.05 contracts at ~0.1 with one Jacobian) the transformed start only costs.
STAGE_NEWTON_STEPS = 8
# Newton is declared diverging when an increment is not at least this much smaller than the last.
DIVERGENCE_THETA = 0.99
# A fixed step whose Newton iterations (simplified, then full) both fail gets a last attempt:
# damped Newton from the start guess with each stage's Jacobian at every iterate (Deuflhard's
# natural monotonicity test: a step lam dW is taken when the next simplified increment is at
# most (1 - lam / 2) times dW; lam halves down to DAMPING_MIN = 2^-DAMPING_HALVINGS), for at most
# DAMPED_NEWTON_FACTOR x max_newton_iterations iterations.  casadi's collocation (full Newton, no
# divergence test) converged on steps where the undamped iterations here failed: the transistor
# amplifier at h = 1e-3 (contraction 30 at step 1) and 2.5e-4 (10 iterations too few, step 52).
DAMPED_NEWTON_FACTOR, DAMPING_HALVINGS = 5, 10
DAMPING_MIN = 2.0**-DAMPING_HALVINGS
# Adaptive mode: default budget of step attempts (accepted, rejected, or failed in Newton).  An
# attempt costs 2-6 ms on one (shared) CPU core, so a runaway (a chattering switch, an endless
# t_span) fails within 10-30 s; the pendulum on [0, 10] takes ~370 attempts at rtol = 1e-6.
DEFAULT_MAX_ADAPTIVE_STEPS = 5_000
# Fixed step: default bound on the grid's step count, checked before the grid is built (the count
# is known up front, so no runaway is possible; daemodel.compare's finest sweep takes 20,480 steps).
DEFAULT_MAX_FIXED_STEPS = 100_000


@dataclass(frozen=True, kw_only=True)
class RadauOptions:
    """Options of ``method="radau"``.

    Attributes
    ----------
    stages : int, optional
        Radau IIA stages s (order 2s-1 for y; s for an index-2 algebraic variable).  Default: 3
        (RADAU5, the paper's v = 3) for a fixed step and for ``rtol >= 1e-6``; 5 (order 9) for
        ``1e-10 <= rtol < 1e-6`` and 7 (order 13) below, where the larger steps of the higher order
        pay for its larger systems (:data:`ADAPTIVE_STAGES`).
    h : float, optional
        Fixed step size.  Exclusive with ``rtol``/``atol``.
    rtol, atol : float, optional
        Adaptive mode's tolerances (default 1e-6, 1e-8 when ``h`` is not given).
    h0 : float, optional
        First step of adaptive mode (default: estimated from f at t0).
    t_eval : array, optional
        Output times (collocation-polynomial dense output); default: the step grid.
    newton_tol : float, optional
        Newton's tolerance on scaled increments; default ``10 * eps`` of the dtype for a fixed
        step (the collocation solution to rounding), ``max(10 eps / rtol, min(0.03, sqrt(rtol)))``
        relative to the error tolerance in adaptive mode (RADAU5's rule).
    max_newton_iterations : int
    max_steps : int, optional
        Fixed step: most steps of the grid, refused before it is built
        (:class:`~daemodel.errors.ResourceLimitError`); default 100,000.  Adaptive mode: most step
        attempts, accepted, rejected or failed in Newton alike
        (:class:`~daemodel.errors.StepLimitError`); default 5,000, a runaway's 10-30 s.
    reuse_jacobian : bool
        Keep the Jacobian (and the LU while h is unchanged) for the next step when Newton
        contracted fast; otherwise a fresh one every step.
    dtype : "float64" or "float32"
    device : str
        A torch device ("cpu", "cuda", "cuda:1", ...).
    threads : int, optional
        torch's intra-op threads for the torch engine (the caller's setting is restored after the
        solve).  Default: one thread for batches of under 20,000 unknowns in all (samples x
        (n + m)), where more threads only add synchronisation, and torch's own setting above
        (:data:`~daemodel.backends.base.SMALL_TORCH_WORK`).  The casadi engine runs on one thread.
    engine : "auto", "torch" or "casadi"
        Who evaluates the residuals and Jacobians and factors the matrices; the algorithm is the
        same, and so are the results to rounding.  "casadi": casadi-compiled functions, casadi's
        sparse Jacobian and scipy's dense or sparse LU, for one trajectory in float64 on the CPU
        (no torch code generation, no per-operation dispatch).  "torch": the compiler's batched
        torch functions, for batches, float32 and GPUs.  "auto" picks casadi where it can.
    start_guess : callable, optional
        Fixed step only: ``start_guess(t, y, z) -> W``, the stage values ``(B, s, n+m)`` Newton
        starts each step from (``y`` (B, n), ``z`` (B, m) the step's start values, arrays of
        the engine), instead of extrapolating the last step's collocation polynomial.  A trained
        Radau-PINN is such a guess (``Surrogate.solve(newton=True)``); the answer is still the
        collocation solution, Newton only starts closer to it.  From a guess, each step runs
        full Newton (each stage's Jacobian at the guess); where it fails, the step starts again
        from its start value, as it does after a failed extrapolation.
    """

    stages: int | None = None
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    h0: float | None = None
    t_eval: object = None
    newton_tol: float | None = None
    max_newton_iterations: int = 10
    max_steps: int | None = None
    reuse_jacobian: bool = True
    dtype: str = "float64"
    device: str = "cpu"
    threads: int | None = None
    engine: str = "auto"
    start_guess: object = None

    def __post_init__(self) -> None:
        for name in ("h", "rtol", "atol", "h0", "newton_tol"):
            check_number(name, getattr(self, name), allow_none=True)
        check_number("max_newton_iterations", self.max_newton_iterations, integer=True)
        object.__setattr__(self, "dtype", check_dtype(self.dtype))
        if self.h is not None and (self.rtol is not None or self.atol is not None or self.h0 is not None):
            raise InvalidOptionError("h fixes the step size; rtol/atol/h0 select adaptive steps: give one or the other")
        if self.max_steps is None:
            object.__setattr__(
                self, "max_steps", DEFAULT_MAX_ADAPTIVE_STEPS if self.adaptive else DEFAULT_MAX_FIXED_STEPS
            )
        check_number("max_steps", self.max_steps, integer=True)
        if self.adaptive:
            object.__setattr__(self, "rtol", DEFAULT_RTOL if self.rtol is None else self.rtol)
            object.__setattr__(self, "atol", DEFAULT_ATOL if self.atol is None else self.atol)
            if self.dtype == "float32" and self.rtol < FLOAT32_MIN_RTOL:
                raise InvalidOptionError(
                    f"rtol = {self.rtol:g} is below what float32 can deliver (>= {FLOAT32_MIN_RTOL:g}); "
                    "use dtype='float64'"
                )
            check_tolerances(self.rtol, self.atol)
        if self.stages is None:
            object.__setattr__(self, "stages", adaptive_stages(self.rtol) if self.adaptive else FIXED_STAGES)
        check_stages(self.stages)
        eps = float(np.finfo(self.dtype).eps)
        if self.newton_tol is not None and self.newton_tol < 10 * eps:
            raise InvalidOptionError(
                f"newton_tol = {self.newton_tol:g} is below 10 eps of {self.dtype} ({10 * eps:.1e}); "
                "Newton cannot reach it" + (": use dtype='float64'" if self.dtype == "float32" else "")
            )
        check_threads(self.threads)
        if not isinstance(self.reuse_jacobian, bool):
            raise InvalidOptionError(f"reuse_jacobian must be True or False; got {self.reuse_jacobian!r}")
        # InvalidOptionError for a device torch cannot use here ("cpu" needs no torch: the casadi
        # engine's solves then never import it, ~2.7 s on a first call)
        if self.device != "cpu":
            device = torch_device(self.device)
            if not isinstance(self.device, str):
                object.__setattr__(self, "device", str(device))
        device_type = "cpu" if self.device == "cpu" else torch_device(self.device).type
        if self.start_guess is not None and (not callable(self.start_guess) or self.adaptive):
            raise InvalidOptionError(
                "start_guess must be a function (t, y, z) -> stage values, for a fixed step (h=...); "
                f"got {type(self.start_guess).__name__}" + (" with adaptive steps" if self.adaptive else "")
            )
        if self.engine not in ENGINES:
            raise InvalidOptionError(f"engine must be one of {', '.join(map(repr, ENGINES))}; got {self.engine!r}")
        if self.engine == "casadi" and (self.dtype != "float64" or device_type != "cpu"):
            raise InvalidOptionError(
                f"engine='casadi' computes in float64 on the CPU; dtype={self.dtype!r}, device={self.device!r} "
                "need engine='torch'"
            )

    @property
    def adaptive(self) -> bool:
        return self.h is None


class RadauBackend(AbstractBackend):
    """``method="radau"``: batched Radau IIA with Newton, fixed or adaptive steps."""

    name = "radau"
    Options = RadauOptions
    # index 3 would need h^-2-conditioned Newton matrices; solve() reduces it to index 2
    max_index = 2

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return fixed_step_sweep(t_span, points, steps)

    def times_follow_samples(self, options: RadauOptions) -> bool:
        return options.adaptive and options.t_eval is None  # a batch steps together, on its own times

    def solve(self, compiled, t_span, start, options: RadauOptions):
        if make_engine_name(start, options) == "casadi":
            return self._solve(compiled, t_span, start, options)
        with torch_threads(options.threads, start.size * (len(compiled.states) + len(compiled.algebraics))):
            return self._solve(compiled, t_span, start, options)

    def _solve(self, compiled, t_span, start, options: RadauOptions):
        check_memory(
            f"radau on {start.size} sample(s) of {len(compiled.states) + len(compiled.algebraics)} unknowns",
            memory_parts(compiled, t_span, start.size, options),
        )
        began = time.perf_counter()
        engine = make_engine(compiled, start, options)
        stepper = _Stepper(compiled, start, options, engine)
        setup = time.perf_counter() - began
        began = time.perf_counter()
        times, values = stepper.integrate(t_span)
        if engine.name == "torch" and engine.device.type == "cuda":
            engine.torch.cuda.synchronize(engine.device)
        wall = time.perf_counter() - began
        if engine.name == "torch":
            stepper.stats["torch_threads"] = engine.torch.get_num_threads()
        return make_solution(self, compiled, start, options, times, values, wall, stepper.stats, setup_time=setup)


def adaptive_stages(rtol: float) -> int:
    """The stages adaptive mode uses at ``rtol`` when none are given (:data:`ADAPTIVE_STAGES`)."""
    return next(stages for smallest, stages in ADAPTIVE_STAGES if rtol >= smallest)


def memory_parts(compiled, t_span, B: int, options: RadauOptions) -> dict:
    """What a solve of ``B`` samples holds, in bytes, as far as it is known before it starts: the
    Newton matrices (a stage Jacobian and the factored transformed systems, about (2s + 1) D^2 a
    sample), and the outputs (a fixed grid's points, or t_eval's; with t_eval, also each step's
    stages for the dense output).  Adaptive steps add per step what :func:`step_record_bytes` says."""
    D = len(compiled.states) + len(compiled.algebraics)
    parts = {"Newton matrices": B * (2 * options.stages + 1) * D * D * _itemsize(options)}
    steps = None if options.adaptive else grid_steps(t_span, options.h, max_steps=options.max_steps)
    if options.t_eval is not None:
        parts["outputs"] = B * len(output_times(options.t_eval, t_span, ())) * D * 8  # validated first
    if steps is not None:
        parts["step records" if options.t_eval is not None else "outputs"] = steps * step_record_bytes(D, B, options)
    return parts


def step_record_bytes(D: int, B: int, options: RadauOptions) -> int:
    """Bytes an accepted step keeps until the end: its end values, or with t_eval its stages and start."""
    return B * D * _itemsize(options) * (options.stages + 1 if options.t_eval is not None else 1)


def _itemsize(options: RadauOptions) -> int:
    return 4 if options.dtype == "float32" else 8


def make_engine_name(start, options: RadauOptions) -> str:
    """The engine ``options.engine`` picks for ``start`` ("auto": see :func:`make_engine`)."""
    if options.engine != "auto":
        return options.engine
    on_cpu = options.device == "cpu" or torch_device(options.device).type == "cpu"
    return "casadi" if start.size == 1 and options.dtype == "float64" and on_cpu else "torch"


def make_engine(compiled, start, options: RadauOptions):
    """The engine ``options.engine`` names; ``"auto"``: casadi for one trajectory in float64 on the CPU
    (compiled functions, no per-operation dispatch), torch for batches, float32 and GPUs."""
    tableau = radau_iia(options.stages)
    transform = StageTransform.of(tableau.A, embedded_weights(tableau)[0])
    name = make_engine_name(start, options)
    if name == "casadi":
        if start.size != 1:
            raise InvalidOptionError(
                f"engine='casadi' solves one trajectory; this batch has {start.size} samples: use engine='torch' "
                "(or 'auto')"
            )
        return CasadiEngine(compiled, start, tableau, transform)
    import torch

    return TorchEngine(compiled, start, tableau, transform, getattr(torch, options.dtype), torch_device(options.device))


def embedded_weights(tableau) -> tuple[float, np.ndarray]:
    """``(gamma0, bhat - b)`` of the order-s error estimate.

    ``gamma0`` is A's real eigenvalue (s odd, as in RADAU5 and Hairer-Wanner's RADAU); for even
    s, A has no real eigenvalue and ``det(A)^(1/s)`` (the geometric mean of their moduli) is used.
    ``bhat`` solves ``gamma0 * 0^(k-1) + sum_i bhat_i c_i^(k-1) = 1/k`` for k = 1..s.
    """
    s, c = tableau.stages, tableau.c
    eig = np.linalg.eigvals(tableau.A)
    real = eig[np.abs(eig.imag) < 1e-12].real
    gamma0 = float(real.max()) if real.size else float(abs(np.linalg.det(tableau.A)) ** (1 / s))
    V = np.vander(c, s, increasing=True).T  # V[k, i] = c_i^k
    rhs = 1.0 / np.arange(1, s + 1)
    rhs[0] -= gamma0
    return gamma0, np.linalg.solve(V, rhs) - tableau.b


class _Stepper:
    """State of one integration on an engine: the step, the controller, counters.

    Arrays belong to the engine's ``xp`` (numpy or torch): ``y (B, n)``, ``z (B, m)`` and the
    stage values ``W (B, s, n+m)``, stage by stage ``[Y_i, Z_i]``.
    """

    def __init__(self, compiled, start, options: RadauOptions, engine):
        self.engine, self.xp = engine, engine.xp
        self.y, self.z = engine.asarray(start.y0), engine.asarray(start.z0)
        self.compiled, self.options = compiled, options
        self.tableau = engine.tableau
        self.gamma0 = engine.transform.gamma0
        self.e = engine.asarray(embedded_weights(self.tableau)[1])
        self.s, self.n, self.m, self.B = engine.s, engine.n, engine.m, engine.B
        # each algebraic variable's index (RADAU5's count, coupling included): its error weight is h^(k-1)
        self.z_index = np.array(compiled.algebraic_index, dtype=float)
        self._det_sign, self._det_time = None, compiled.t0  # the last fresh Jacobian's sign of det
        eps = float(np.finfo(options.dtype).eps)
        if options.adaptive:
            self.rtol, self.atol = options.rtol, options.atol
            self.newton_tol = options.newton_tol or max(10 * eps / self.rtol, min(0.03, self.rtol**0.5))
        else:
            # fixed step: converge to rounding, increments measured against 1 + |w|
            self.rtol, self.atol = 1.0, 1.0
            self.newton_tol = options.newton_tol or FIXED_NEWTON_TOL_EPS * eps
        self.stats = {
            "mode": "adaptive" if options.adaptive else "fixed",
            "engine": engine.name,
            "stages": self.s,
            "order": self.tableau.order,
            "dtype": options.dtype,
            "device": options.device,
            "batch": self.B,
            "steps": 0,
            "attempts": 0,
            "rejected_steps": 0,
            "newton_iterations": 0,
            "max_newton_iterations": 0,
            "newton_failures": 0,
            "newton_refreshes": 0,
            "jacobian_evaluations": 0,
            "lu_decompositions": 0,
            "residual_evaluations": 0,
            "h_min": math.inf,
            "h_max": 0.0,
        }
        if not options.adaptive:
            # worst step, sample and variable, in units of 1 + max|u| (see check_local_error)
            self.stats["max_local_error_estimate"] = 0.0
            self.stats["damped_newton_attempts"] = (
                0  # runs of the last resort (DAMPED_NEWTON_FACTOR); a step may need 2
            )
        self._jac = None  # (J, t) at the last refresh
        self._lu = None  # the Factors of the transformed systems of J and the current h
        self._index_weights = None  # (h, h^(k-1) per component (D,)) for the last h
        self._f_start = None  # f at the start of the next step (the last stage's f of this one)
        self._scale = None  # fixed step: 1 + max |u| over the steps' start values so far, (B, n+m)
        self._outputs = None  # ([t], [u (B, n+m)], [(t, h, u_start, W)]) of the accepted steps
        self._eta = engine.asarray(np.ones(self.B))  # Newton's contraction estimate
        self._previous = None  # (h, u_start, W) of the last accepted step, for the start guess
        self._stage_steps = 0  # steps left that start with full Newton (see attempt)
        self._extrapolation = None  # (h / h_old, Lagrange matrix) of the last start guess
        self._extrapolation_polynomial = extrapolation_polynomial(self.tableau.c)  # the matrix by Horner's rule
        # adaptive steps on dense systems of one trajectory: each attempt in one compiled call
        self._compiled = (
            options.adaptive
            and options.start_guess is None
            and engine.make_compiled_step(options.max_newton_iterations, embedded_weights(self.tableau)[1])
        )
        if self._compiled:
            self.stats["compiled_retries"] = 0  # compiled attempts that failed and ran again on the general path

    # ---- pieces -------------------------------------------------------------------------
    def state(self):
        return self.xp.concatenate([self.y, self.z], axis=-1)

    def rms(self, x):
        """Root mean square over all but the batch axis, shape (B,)."""
        x = x.reshape(self.B, -1)
        return self.xp.sqrt((x * x).sum(axis=-1) / x.shape[-1])

    def jacobian(self, t, y, z):
        self.stats["jacobian_evaluations"] += 1
        return self.engine.jacobian(t, y, z)

    def factor(self, J, t, h, error_only=False):
        factors = self.engine.factor(J, h, error_only)
        self.stats["lu_decompositions"] += len(factors.shifts) if factors.complete else 1
        self.check_singular(factors.singular, t, h, "Newton matrix", J)
        return factors

    def index_weights(self, h):
        """``h^(k-1)`` for each component (1 for the states), kept while h is unchanged."""
        if self._index_weights is None or self._index_weights[0] != h:
            weights = np.concatenate([np.ones(self.n), h ** (self.z_index - 1)])
            self._index_weights = (h, self.engine.asarray(weights))
        return self._index_weights[1]

    def weights(self, h, u_ref):
        """Error scale of each of the n + m components, shape (B, n+m)."""
        return (self.atol + self.rtol * u_ref) / self.index_weights(h)

    def residual(self, t, h, W):
        self.stats["residual_evaluations"] += 1
        return self.engine.residual(t, h, self.y, W)

    def constant_guess(self):
        """Every stage value equal to the step's start value."""
        u = self.state()
        return np.repeat(u[:, None, :], self.s, axis=1) if self.xp is np else u[:, None, :].expand(self.B, self.s, -1)

    def start_guess(self, h, t=None):
        """Stage values from ``options.start_guess`` where given, else extrapolated from the last
        step's collocation polynomial (or constant at the first step)."""
        xp = self.xp
        if self.options.start_guess is not None:
            W = self.options.start_guess(t, self.y, self.z)
            if xp is np:
                W = np.asarray(W.detach().cpu().numpy() if hasattr(W, "detach") else W, dtype=float)
            else:
                W = xp.as_tensor(W, dtype=self.y.dtype, device=self.y.device)
            if tuple(W.shape) != (self.B, self.s, self.n + self.m):
                raise InvalidOptionError(
                    f"start_guess returned stage values of shape {tuple(W.shape)}; expected "
                    f"{(self.B, self.s, self.n + self.m)} (samples, stages, n + m)"
                )
            return W
        if self._previous is None:
            return self.constant_guess()
        h_old, u_old, W_old = self._previous
        L = self.extrapolation(h / h_old)
        return xp.einsum("ij,bjk->bik", L, xp.concatenate([u_old[:, None, :], W_old], axis=1))

    def extrapolation(self, ratio):
        """The start guess's extrapolation matrix (s, s+1) for ``ratio`` = h / h_old, kept while it is unchanged."""
        if self._extrapolation is None or self._extrapolation[0] != ratio:
            self._extrapolation = (ratio, self.engine.asarray(horner(self._extrapolation_polynomial, ratio)))
        return self._extrapolation[1]

    # ---- one step -----------------------------------------------------------------------
    def newton(self, t, h, factors, W):
        """Solve the stage equations from the guess ``W``; ``(W, stage residual, theta)`` or None."""
        xp, engine = self.xp, self.engine
        scale = self.weights(h, xp.abs(self.state()))[:, None, :]
        if self.options.adaptive:
            # RADAU5: trust the last step's contraction rate, so one iteration may suffice
            eta = xp.clip(self._eta, float(np.finfo(self.options.dtype).eps), None) ** 0.8
        else:
            # the fixed-step solution must be the collocation solution: no early trust
            eta = xp.ones_like(self._eta)
        previous = None
        theta = xp.zeros_like(self._eta)
        active = xp.ones_like(self._eta) > 0  # samples still iterating
        for k in range(1, self.options.max_newton_iterations + 1):
            self.stats["residual_evaluations"] += 1
            r, dW = engine.newton_step(factors, t, h, self.y, W)
            if self.B > 1:
                dW = dW * active[:, None, None]  # samples that converged keep their stage values
            W = W + dW
            norm = self.rms(dW / scale)
            finite = xp.isfinite(norm)  # a NaN or inf anywhere in R or dW ends up here
            if not bool(finite.all()):
                sample = engine.first(~finite)
                return None, k, f"non-finite values: {self.non_finite(r, dW, sample, t, h)}", sample
            if previous is not None:
                theta = xp.where(active, norm / xp.clip(previous, 1e-300, None), theta)
                diverging = active & (theta >= DIVERGENCE_THETA)
                if not self.options.adaptive:  # increments at the rounding floor wander: that is not divergence
                    diverging = diverging & (norm > STAGNATION_FACTOR * self.newton_tol)
                if bool(diverging.any()):
                    worst = engine.first(diverging)
                    return None, k, f"diverging (contraction {float(theta[worst]):.2f})", worst
                eta = xp.where(active, theta / (1 - theta), eta)
            if self.options.adaptive:
                done = eta * norm <= self.newton_tol
            else:
                # the last increment itself is below tol, or rounding stops the iteration near it
                done = (norm <= self.newton_tol) | (
                    (theta >= STAGNATION_THETA) & (norm <= STAGNATION_FACTOR * self.newton_tol)
                )
            active = active & ~done
            left = self.options.max_newton_iterations - k
            if previous is not None and left > 0 and bool(active.any()):
                result = self.slow_contraction(t, h, W, factors, theta, eta * norm * theta**left, active)
                if isinstance(result, str):
                    worst = engine.first(active & (theta >= float((theta * active).max())))
                    return None, k, result, worst
                factors = result
            previous = norm
            if not bool(active.any()) and self.options.adaptive:
                # the error estimate needs f at the final stage values
                if k == 1 and k < self.options.max_newton_iterations:
                    # converged on the last step's contraction alone: check that the next increment is
                    # small too (a non-smooth f, e.g. sign(x), can make one iteration look converged)
                    self.stats["residual_evaluations"] += 1
                    r, after = engine.newton_step(factors, t, h, self.y, W)
                    active = self.rms(after / scale) > self.newton_tol
                else:
                    r = self.residual(t, h, W)
            if not bool(active.any()):
                self._eta = eta
                self.stats["newton_iterations"] += k
                self.stats["max_newton_iterations"] = max(self.stats["max_newton_iterations"], k)
                return (W, r, float(theta.max())), k, None, None
        return None, k, f"not converged in {k} iterations", self.engine.first(active)

    def slow_contraction(self, t, h, W, factors, theta, predicted, active):
        """What Newton does when it contracts too slowly: the factors to go on with, or why it stops.

        ``predicted`` is the size of the increment after the iterations left (RADAU5's test).  With
        the transformed systems, a slow contraction that will not reach the tolerance ends the
        attempt in adaptive mode (the controller shrinks h, as RADAU5 does) and switches a fixed
        step to full Newton with each stage's Jacobian at the current iterate, which stays
        quadratic; under full Newton the stage Jacobians are refreshed while it contracts slower
        than REFRESH_THETA.
        """
        worst = float((theta * active).max())
        if isinstance(factors, StageFactors):
            refresh = worst > REFRESH_THETA
        else:
            refresh = bool((active & (predicted > self.newton_tol)).any())
            if refresh and self.options.adaptive:
                return f"converging too slowly (contraction {worst:.2f})"
        if not refresh:
            return factors
        stage_J = self.engine.stage_jacobians(t, h, W)
        self.stats["jacobian_evaluations"] += 1
        self._jac = None  # the next step starts from a fresh Jacobian too
        return self.factor_stages(stage_J, t, h)

    def non_finite(self, r, dW, sample, t, h) -> str:
        """Where a sample's first non-finite value arose: ``f`` or ``g`` at a stage, else an increment of a variable."""
        xp, compiled, n = self.xp, self.compiled, self.n
        for values, names, what in (
            (r.stage_f, compiled.state_names, "the right-hand side of {}'"),
            (r.G, compiled.constraint_names, "constraint '{}'"),
            (dW[..., :n], compiled.state_names, "the Newton increment of '{}'"),
            (dW[..., n:], compiled.algebraic_names, "the Newton increment of '{}'"),
        ):
            bad = np.argwhere(~_host(xp.isfinite(values[sample])))
            if len(bad):
                stage, k = (int(i) for i in bad[0])
                when = t + float(self.tableau.c[stage]) * h
                return f"{what.format(names[k])} at stage {stage + 1} (t = {when:.6g})"
        return "the Newton increment"

    def local_error(self, h, factors, f0, stage_f):
        """The embedded local error estimate of the step (see the module docstring), shape (B, n+m).

        ``factors`` hold ``(1 / (h gamma0)) M - J``, ``f0`` (B, n) is ``f`` at the step's start,
        ``stage_f`` (B, s, n) at its stages.  Returns the estimate and what :meth:`refiltered` needs.
        """
        xp = self.xp
        quadrature = xp.einsum("i,bin->bn", self.e, stage_f)  # sum_i (bhat_i - b_i) f(Y_i), (B, n)
        # (M - h gamma0 J) err = [h (quadrature + gamma0 f0); 0] divided row-wise by diag(h gamma0, -1).
        # The constraint rows carry no local error: each step's Newton enforces g at its stages,
        # and its leftover |g(y_n)| (Newton's tolerance) must not block ever smaller steps.
        zeros = xp.zeros_like(self.z)
        rhs = xp.concatenate([quadrature / self.gamma0 + f0, zeros], axis=-1)
        return self.engine.error_solve(factors, rhs), (factors, quadrature, zeros)

    def refiltered(self, t, err, matrices):
        """The estimate with the stiff filter applied once more (Hairer-Wanner's first or rejected step)."""
        factors, quadrature, zeros = matrices
        n = self.n
        f1 = self.engine.f(t, self.y + err[:, :n], self.z + err[:, n:])
        rhs = self.xp.concatenate([quadrature / self.gamma0 + f1, zeros], axis=-1)
        return self.engine.error_solve(factors, rhs)

    def start_f(self, t):
        """``f`` at the step's start: the last accepted step's final stage (Radau IIA is stiffly accurate)."""
        if self._f_start is None:
            self._f_start = self.engine.f(t, self.y, self.z)
        return self._f_start

    def error_norm(self, t, h, r, W, first):
        """RADAU5-style scaled local error of the step, worst sample (adaptive mode)."""
        xp = self.xp
        err, matrices = self.local_error(h, self._lu, self.start_f(t), r.stage_f)
        u_new = W[:, -1]
        w = self.weights(h, xp.maximum(xp.abs(self.state()), xp.abs(u_new)))
        norm = self.rms(err / w)
        if first and bool((norm >= 1).any()):
            err = self.refiltered(t, err, matrices)
            norm = self.rms(err / w)
        if not bool(xp.isfinite(norm).all()):
            return math.inf
        return float(norm.max())

    def check_local_error(self, step, t, h, r):
        """Fixed step: the step's local error estimate in units of the solution's size; raise beyond the bound.

        The unit is ``1 + max |u|`` over the steps' start values so far (an algebraic variable of
        index k: that over ``h^(k-1)``), so a step across a singularity cannot excuse its error by
        its own huge result, nor an oscillation be judged where it crosses zero.  It reuses the
        factored Newton matrix of the step's Jacobian and takes ``f`` at the step's start from the
        last step's final stage (Radau IIA is stiffly accurate: ``c_s = 1``).
        """
        xp = self.xp
        u = xp.abs(self.state()) + 1.0
        self._scale = u if self._scale is None else xp.maximum(self._scale, u)
        err, matrices = self.local_error(h, self._lu, self.start_f(t), r.stage_f)
        index_weight = self.index_weights(h)
        ratio = xp.abs(err) * index_weight / self._scale
        worst = float(ratio.max())
        if worst > LOCAL_ERROR_BOUND:  # the stiff filter once more before judging (Hairer-Wanner)
            ratio = xp.abs(self.refiltered(t, err, matrices)) * index_weight / self._scale
            worst = float(ratio.max())
        if worst <= LOCAL_ERROR_BOUND:  # the usual case: False for NaN too
            self.stats["max_local_error_estimate"] = max(self.stats["max_local_error_estimate"], worst)
            return
        self.stats["max_local_error_estimate"] = math.inf if math.isnan(worst) else worst
        ratio = np.nan_to_num(np.asarray(_numpy(ratio)), nan=math.inf)
        sample, k = divmod(int(np.argmax(ratio.reshape(-1))), self.n + self.m)
        name = (*self.compiled.state_names, *self.compiled.algebraic_names)[k]
        index = int(self.z_index[k - self.n]) if k >= self.n else 1
        size = f"1 + max|{name}|" if index == 1 else f"(1 + max|{name}|) / h^{index - 1}"
        value = float(ratio.reshape(-1)[sample * (self.n + self.m) + k])
        raise LocalErrorBoundError(
            f"radau: step {step} from t = {t:.6g} with h = {h:.3g}: the local error estimate of '{name}' "
            f"(sample {sample}) is {value:.3g} times the solution's size {size} so far, beyond "
            f"LOCAL_ERROR_BOUND = {LOCAL_ERROR_BOUND:g}: the step has no correct digit (the solution may be "
            "singular, switch or change too fast there); take a smaller h, or the adaptive mode (rtol=...)"
        )

    def check_singular(self, singular, t, h, what, J):
        """Raise :class:`ConvergenceError` where a factorisation reports a singular matrix, with the
        likely cause: a Jacobian ``J`` that is not finite (the state left f's domain), algebraic
        variables the constraints stop determining, or else the step size itself."""
        if not bool(singular.any()):
            return
        sample = self.engine.first(singular)
        head = f"radau: the {what} is singular for sample {sample} at t = {t:.6g} with h = {h:.3g}"
        matrices = J if isinstance(J, list) else [J]
        if not all(bool(self.xp.isfinite(m).all()) for m in matrices):
            raise ConvergenceError(
                f"{head}: the Jacobian of f and g is not finite there (f or g is not differentiable at this "
                "state, e.g. sqrt(x) at x = 0, or the state left their domain, e.g. sqrt or log of a negative "
                "value, which a step this long can cause); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
            )
        signs = self.engine.z_matrix_sign(J)
        if self.m and bool((signs == 0).any()):
            raise ConvergenceError(
                f"{head}; the constraints do not determine the algebraic variables there (their iteration matrix, "
                "g_z or g_y f_z, is singular)"
            )
        determined = ", though the constraints determine the algebraic variables" if self.m else ""
        raise ConvergenceError(
            f"{head}{determined}: an eigenvalue of the Jacobian times h meets one of the method's shifts (a stiff "
            "mode at this h); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
        )

    # ---- the loop -----------------------------------------------------------------------
    def integrate(self, t_span):
        """Values at the output times: ``(times (T,), values (B, T, n+m))``."""
        options = self.options
        t0 = t_span[0]
        grid = None if options.adaptive else fixed_grid(t_span, options.h, max_steps=options.max_steps)
        t_out = output_times(options.t_eval, t_span, grid)
        u0 = self.state()
        self._outputs = ([t0], [u0], [])
        # adaptive steps keep a record each: how many fit in the memory the solve may take (a fixed
        # grid's records were counted before the solve)
        self._record_budget = math.inf
        if options.adaptive:
            known = sum(memory_parts(self.compiled, t_span, self.B, options).values())
            self._record_budget = (memory_limit() - known) // step_record_bytes(self.n + self.m, self.B, options)
        if options.adaptive:
            self.adaptive_steps(t_span)
        else:
            self.fixed_steps(grid)
        out_t, out_u, steps = self._outputs
        if options.t_eval is not None:
            return self.dense_output(t_out, u0, t0, steps)
        values = self.xp.stack(out_u, axis=1)  # (B, T, n+m)
        return np.asarray(out_t, dtype=float), _numpy(values)

    def fixed_steps(self, grid):
        """Step along ``grid``, checking each step's local error estimate."""
        for step in range(1, len(grid)):
            t, h = float(grid[step - 1]), float(grid[step] - grid[step - 1])
            if abs(h - self.options.h) <= 1e-12 * self.options.h:
                h = self.options.h  # not its rounded copy: the LU and the estimate's weights are kept per h
            self.stats["attempts"] += 1
            result, _, why, sample = self.attempt(t, h)
            if result is None:
                self.stats["newton_failures"] += 1
                raise ConvergenceError(
                    f"radau: Newton failed in step {step} from t = {t:.6g} with h = {h:.3g} ({why}, "
                    f"sample {sample}); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
                )
            self.check_local_error(step, t, h, result[1])
            self.accept(t, h, result, float(grid[step]))

    def adaptive_steps(self, t_span):
        """RADAU5's step-size controller; every attempt counts against ``max_steps``."""
        options = self.options
        t0, t1 = t_span
        t = t0
        h = options.h0 or self.initial_step(t_span)
        first, rejected_last = True, False
        half = (t0, 0)  # (t, accepted steps) when half the budget was spent: the recent rate of progress
        watch = ProgressWatch(t0, h, extra=0)  # extra: the accepted steps when the window began
        while t < t1 and not math.isclose(t, t1, rel_tol=1e-13, abs_tol=1e-13 * abs(t1 - t0)):
            attempts = self.stats["attempts"]
            if attempts >= options.max_steps:
                raise self.budget_error(t, h, t1, half, options.max_steps - options.max_steps // 2)
            if attempts == options.max_steps // 2:
                half = (t, self.stats["steps"])
            needed = watch.hopeless(attempts, t, h, t1, options.max_steps, extra=self.stats["steps"])
            if needed is not None:
                t_w, count_w, _, accepted_w = watch.start
                raise self.budget_error(t, h, t1, (t_w, accepted_w), attempts - count_w, projected=needed)
            self.stats["attempts"] += 1
            if h < 1e-14 * max(1.0, abs(t)):
                h = self._shrink(h, t, "the error estimate kept shrinking the step", None, 1.0)
            h = min(h, t1 - t)
            if (t1 - t) - h < 1e-10 * h:
                h = t1 - t
            fast = self.compiled_attempt(t, h, first or rejected_last) if self._compiled else None
            if fast is not None:
                result, iterations, err = fast
            else:
                result, iterations, why, sample = self.attempt(t, h)
                if result is None:
                    self.stats["newton_failures"] += 1
                    self._lu = None
                    h = self._shrink(h, t, why, sample, 0.5)
                    first = True
                    continue
                W, r, _ = result
                err = self.error_norm(t, h, r, W, first or rejected_last)
            factor = min(
                SAFETY,
                SAFETY * (2 * options.max_newton_iterations + 1) / (2 * options.max_newton_iterations + iterations),
            )
            quot = factor * max(err, 1e-10) ** (-1.0 / (self.s + 1))
            if err > 1:
                self.stats["rejected_steps"] += 1
                h = self._shrink(h, t, f"error estimate {err:.2g} > 1", None, max(MIN_FACTOR, min(quot, 0.9)))
                rejected_last = True
                self._lu = None
                continue
            t_next = t1 if math.isclose(t + h, t1, rel_tol=1e-13) else t + h
            self.accept(t, h, result, t_next)
            t = t_next
            new_h = h * min(MAX_FACTOR, max(MIN_FACTOR, quot)) if not rejected_last else h * min(1.0, quot)
            if KEEP_H_BAND[0] <= new_h / h <= KEEP_H_BAND[1]:
                new_h = h
            h = new_h
            first = rejected_last = False

    def attempt(self, t, h):
        """Newton on the step from ``t`` with ``h``.

        First with the step-start Jacobian through the transformed systems (reused while it serves,
        refreshed once if a reused one fails); if that fails, full Newton with each stage's Jacobian
        at the starting guess, which also checks that z stays determined at the stages.  After a
        step needed full Newton, the next STAGE_NEWTON_STEPS steps start with it directly.
        """
        W0 = self.start_guess(h, t)
        J = self.current_jacobian(t, h)
        if self.options.start_guess is not None:
            # a guess close to the collocation solution: full Newton from it converges quadratically
            # (the pendulum at h = 0.05 from a Radau-PINN's stages: 2 iterations a step, against 6 of
            # simplified Newton with the step-start Jacobian, which contracts at ~0.1 there)
            self._stage_steps = max(self._stage_steps, 1)
        if self._stage_steps > 0:
            self._stage_steps -= 1
            self.current_lu(J, t, h, error_only=True)  # the error estimate's system
            guessed = self._previous is not None or self.options.start_guess is not None
            if guessed and not self.finite_at(t, h, W0):
                # the guess left f's domain (Akzo Nobel: y2 < 0 under a sqrt): start from the start value
                W0, guessed = self.constant_guess(), False
            found = self.stage_newton(t, h, W0)
            if found[0] is None and guessed:
                return self.stage_newton(t, h, self.constant_guess())
            return found
        factors = self.current_lu(J, t, h)
        result, iterations, why, sample = self.newton(t, h, factors, W0)
        if result is None and (self._previous is not None or self.options.start_guess is not None):
            # the extrapolated guess can be far off (a fast transient, a degree-2s-1 polynomial taken past
            # its step): start from the step's start value before anything costlier
            W0 = self.constant_guess()
            result, iterations, why, sample = self.newton(t, h, factors, W0)
        if result is None and self._jac is not None and self._jac[1] != t:
            # the reused Jacobian is stale: refresh it and try again
            self._jac = self._lu = None
            factors = self.current_lu(self.current_jacobian(t, h), t, h)
            result, iterations, why, sample = self.newton(t, h, factors, W0)
        if result is None and not self.options.adaptive:
            return self.stage_newton(t, h, W0)
        if result is None:  # the controller shrinks h; first check that z stays determined over the step
            stage_J = self.engine.stage_jacobians(t, h, W0)
            self.stats["jacobian_evaluations"] += 1
            self.check_determined(stage_J, t, h, keep=False)
        return result, iterations, why, sample

    def compiled_attempt(self, t, h, first):
        """The attempt of :meth:`attempt` and the error norm of :meth:`error_norm` in one compiled call
        (:mod:`daemodel.backends.radau_compiled`), where Newton runs on the transformed systems:
        ``(result, iterations, error norm)``, or None where the step must run on the general path (full
        Newton pending, or the compiled Newton did not converge: the general path retries and words why)."""
        if self._stage_steps > 0:
            return None
        factors = self.current_lu(self.current_jacobian(t, h), t, h)
        if factors.inverse is None:
            return None
        s, n, D = self.s, self.n, self.n + self.m
        if self._previous is None:
            # every node at the start value: a constant guess (at the ratio 0, the start value's weight is 1)
            previous, ratio = np.tile(self.state()[0], s + 1), 0.0
        else:
            h_old, u_old, W_old = self._previous
            previous, ratio = np.concatenate([u_old[0], W_old.ravel()]), h / h_old
        scalars = (t, h, ratio, float(self._eta[0]), self.newton_tol, float(first), self.rtol, self.atol)
        out = self.engine.compiled_step(factors, scalars, previous, self.start_f(t)[0])
        outcome, k, evaluations, theta, eta, err = out[:6]
        self.stats["residual_evaluations"] += int(evaluations)
        if outcome != CONVERGED:
            self.stats["compiled_retries"] += 1
            return None
        k = int(k)
        self.stats["newton_iterations"] += k
        self.stats["max_newton_iterations"] = max(self.stats["max_newton_iterations"], k)
        self._eta = np.array([eta])
        W = out[6 : 6 + s * D].reshape(1, s, D)
        r = Residual(R=None, stage_f=out[6 + s * D :].reshape(1, s, n), G=None)
        return (W, r, float(theta)), k, (float(err) if math.isfinite(err) else math.inf)

    def finite_at(self, t, h, W) -> bool:
        """Whether the stage residual (f and g) is finite at the stage values ``W``."""
        return bool(self.xp.isfinite(self.residual(t, h, W).R).all())

    def stage_newton(self, t, h, W0):
        """Full Newton from ``W0`` with each stage's Jacobian at ``W0`` (and at later iterates while
        it contracts slowly); for a fixed step, damped Newton if that fails."""
        stage_J = self.engine.stage_jacobians(t, h, W0)
        self.stats["jacobian_evaluations"] += 1
        self.check_determined(stage_J, t, h)
        result, iterations, why, sample = self.newton(t, h, self.factor_stages(stage_J, t, h), W0)
        if result is not None or self.options.adaptive:
            return result, iterations, why, sample
        damped, more, why_damped, sample = self.damped_newton(t, h, W0)
        if damped is not None:
            return damped, iterations + more, None, None
        return None, iterations + more, f"{why}; damped Newton: {why_damped}", sample

    def damped_newton(self, t, h, W):
        """A fixed step's last attempt: Newton from ``W`` with each stage's Jacobian at every iterate,
        damped by the natural monotonicity test (see :data:`DAMPED_NEWTON_FACTOR`).

        Returns ``(W, residual, 1.0)`` or None, the iterations, why it failed and the sample, as
        :meth:`newton` does; the contraction 1.0 makes the next step evaluate a fresh Jacobian.
        """
        xp, engine = self.xp, self.engine
        self.stats["damped_newton_attempts"] += 1
        scale = self.weights(h, xp.abs(self.state()))[:, None, :]
        lam = xp.ones_like(self._eta)
        active = lam > 0
        previous = xp.full_like(lam, math.inf)
        limit = DAMPED_NEWTON_FACTOR * self.options.max_newton_iterations
        for k in range(1, limit + 1):
            stage_J = engine.stage_jacobians(t, h, W)
            self.stats["jacobian_evaluations"] += 1
            factors = engine.factor_stages(stage_J, h)
            self.stats["lu_decompositions"] += 1
            self.stats["newton_refreshes"] += 1
            self._stage_steps = STAGE_NEWTON_STEPS
            if bool(factors.singular.any()):  # an iterate left f's domain, or a stiff mode meets a shift
                finite = all(bool(xp.isfinite(J).all()) for J in stage_J)
                cause = "" if finite else " (the Jacobian of f and g is not finite there)"
                return None, k, f"the Newton matrix at iterate {k} is singular{cause}", engine.first(factors.singular)
            self.stats["residual_evaluations"] += 1
            r, dW = engine.newton_step(factors, t, h, self.y, W)
            norm = self.rms(dW / scale)
            finite = xp.isfinite(norm)
            if not bool(finite.all()):
                sample = engine.first(~finite)
                return None, k, f"non-finite values: {self.non_finite(r, dW, sample, t, h)}", sample
            # converged: the increment is below tol, or it stopped shrinking at the rounding floor near it
            stagnant = (norm >= STAGNATION_THETA * previous) & (norm <= STAGNATION_FACTOR * self.newton_tol)
            active = active & (norm > self.newton_tol) & ~stagnant
            previous = norm
            if not bool(active.any()):
                W = W + dW  # every sample's increment is below the tolerance: take it whole
                self.stats["newton_iterations"] += k
                self.stats["max_newton_iterations"] = max(self.stats["max_newton_iterations"], k)
                return (W, self.residual(t, h, W), 1.0), k, None, None
            lam = xp.clip(2 * lam, None, 1.0)
            while True:  # lam halves each pass, down to DAMPING_MIN: at most DAMPING_HALVINGS + 1 passes
                trial = W + (lam * active)[:, None, None] * dW
                self.stats["residual_evaluations"] += 1
                _, simplified = engine.newton_step(factors, t, h, self.y, trial)
                after = self.rms(simplified / scale)
                fine = ~active | (xp.isfinite(after) & (after <= (1 - lam / 2) * norm))
                if bool(fine.all()):
                    break
                if bool((~fine & (lam <= DAMPING_MIN)).any()):
                    sample = engine.first(~fine & (lam <= DAMPING_MIN))
                    return (
                        None,
                        k,
                        f"no damped step down to {DAMPING_MIN:.2g} of the increment decreases it (increment "
                        f"{float(norm[sample]):.2g}, tolerance {self.newton_tol:.2g})",
                        sample,
                    )
                lam = xp.where(fine, lam, lam / 2)
            W = trial
        return None, limit, f"not converged in {limit} iterations", engine.first(active)

    def factor_stages(self, stage_J, t, h):
        factors = self.engine.factor_stages(stage_J, h)
        self.stats["lu_decompositions"] += 1
        self.stats["newton_refreshes"] += 1
        self.check_singular(factors.singular, t, h, "Newton matrix", stage_J)
        self._stage_steps = STAGE_NEWTON_STEPS
        return factors

    def accept(self, t, h, result, t_next):
        """Take the step: record its output, move the state to ``t_next``, decide on the Jacobian's reuse."""
        W, r, theta = result
        out_t, out_u, steps = self._outputs
        if len(out_t) + len(steps) > self._record_budget:
            raise ResourceLimitError(
                f"radau: at t = {t:.6g}, the {len(out_t) + len(steps)} steps' outputs of {self.B} sample(s) reach "
                f"the memory allowed ({memory_limit() / 2**30:.3g} GiB, DAEMODEL_MEMORY_LIMIT): solve fewer samples "
                "at a time, loosen rtol, or give t_eval (with a fixed h, a grid's size is checked before the solve)"
            )
        u_start = self.state()
        if self.options.t_eval is not None:
            steps.append((t, h, u_start, W))
        else:
            out_t.append(t_next)
            out_u.append(W[:, -1])
        self._previous = (h, u_start, W)
        self.y, self.z = W[:, -1, : self.n], W[:, -1, self.n :]
        self._f_start = r.stage_f[:, -1]
        self.stats["steps"] += 1
        self.stats["h_min"] = min(self.stats["h_min"], h)
        self.stats["h_max"] = max(self.stats["h_max"], h)
        reuse_theta = REUSE_THETA_LARGE if self.n + self.m > REUSE_LARGE_SIZE else REUSE_THETA
        if not self.options.reuse_jacobian or theta > reuse_theta:
            self._jac = None  # slow contraction (or no reuse asked for): a fresh Jacobian next step

    def budget_error(self, t, h, t1, half, recent, projected=None) -> StepLimitError:
        """max_steps ran out (or, ``projected``, cannot suffice): say where, and why it likely did
        (chattering, or a span too long); ``half`` is (t, accepted steps) ``recent`` attempts ago."""
        budget, accepted = self.options.max_steps, self.stats["steps"]
        failed = self.stats["rejected_steps"] + self.stats["newton_failures"]
        recent_accepted = accepted - half[1]
        progress = t - half[0]
        if recent_accepted < recent / 2:
            reason = (
                f"{recent - recent_accepted} of the last {recent} attempts were rejected or failed in Newton, "
                f"and they advanced t by {progress:.3g} of the {t1 - half[0]:.3g} left: the right-hand side is "
                "likely discontinuous near "
                f"t = {t:.6g} (sign(x), abs(x), min/max or a Piecewise that switches), and steps across the "
                "switch need h -> 0 (chattering); stop the integration at the switch and restart from there, "
                "or smooth the switch"
            )
        else:
            rate = progress / max(recent, 1)
            if projected is not None:
                more = f"about {projected:.3g} more"
            else:
                more = f"about {(t1 - t) / rate:.3g} more" if rate > 0 else "endlessly many"
            reason = (
                f"the steps are accepted, but at the last {recent} attempts' rate ({rate:.3g} per attempt) the "
                f"rest of t_span needs {more} attempts: t_span is too long for max_steps at this tolerance; "
                "raise max_steps, loosen rtol/atol or shorten t_span"
            )
        if projected is None:
            head = f"radau: max_steps = {budget} reached at t = {t:.6g}"
        else:
            head = (
                f"radau: max_steps = {budget} cannot suffice (about {projected:.3g} more attempts projected, "
                f"{budget - self.stats['attempts']} left), stopped early at t = {t:.6g}"
            )
        return StepLimitError(
            f"{head} (h = {h:.3g}) before t1 = {t1:g}, after {accepted} accepted steps and {failed} rejected or "
            f"failed attempts: {reason}"
        )

    def current_jacobian(self, t, h):
        """The Jacobian at the step's start (kept while Newton contracts fast), as RADAU5."""
        if self._jac is None:
            self.stats["jacobian_evaluations"] += 1
            J, factors, signs = self.engine.refresh(t, self.y, self.z, h)
            self._jac, self._lu = (J, t), factors
            if factors is not None:  # factored along with J (see the engine's refresh)
                self.stats["lu_decompositions"] += len(factors.shifts)
            self.check_determined(J, t, h, signs=signs)
        return self._jac[0]

    def check_determined(self, J, t, h, keep=True, signs=None):
        """Refuse a step across a point where the constraints stop determining z.

        The iteration matrix of the algebraic variables (row by row ``g_z`` for an index-1 and
        ``g_y f_z`` for an index-2 constraint, as at compile time) must stay nonsingular; its
        determinant changing sign between two fresh Jacobians means it passed through zero, where
        z is undetermined and may blow up (``q' = (0.7 - t) z, 0 = q - sin t``).  Index-2 z is
        measured against ``(atol + rtol |z|) / h``, so the error estimate alone would step over it.
        ``signs``: the engine's ``z_matrix_sign(J)`` where it came with J.
        """
        if not self.m:
            return
        if signs is None:  # (B,), or (B, s) for the stages of one step
            signs = self.engine.z_matrix_sign(J)
        signs = signs[:, None] if signs.ndim == 1 else signs
        if self._det_sign is not None:
            signs = self.xp.concatenate([self._det_sign[:, None], signs], axis=1)
        flips = (signs[:, 1:] * signs[:, :-1] < 0).any(axis=1)
        if bool(flips.any()):
            sample = self.engine.first(flips)
            names = ", ".join(f"'{c.name}'" for c in self.compiled.constraints)
            raise ConvergenceError(
                f"radau: the constraints ({names}) stop determining the algebraic variables between t = "
                f"{self._det_time:.6g} and {t + h:.6g} (sample {sample}): the determinant of their iteration "
                "matrix (g_z, or g_y f_z at index 2) changes sign, so it passes through zero, where z is not "
                "determined and may blow up; end t_span before that time or reformulate the constraints"
            )
        if keep:  # (not for the stages of a failed attempt: the step is retried shorter)
            self._det_sign, self._det_time = signs[:, -1], t

    def current_lu(self, J, t, h, error_only=False):
        """The factored transformed systems of ``J`` for step ``h`` (kept while both are unchanged), or
        (``error_only``) the error estimate's system alone."""
        if self._lu is None or self._lu.h != h or not (self._lu.complete or error_only):
            self._lu = self.factor(J, t, h, error_only)
        return self._lu

    def _shrink(self, h, t, why, sample, factor):
        new = h * factor
        if new < 1e-14 * max(1.0, abs(t)):
            who = f", sample {sample}" if sample is not None else ""
            raise ConvergenceError(
                f"radau: step size underflow at t = {t:.6g} (h = {new:.3g}; last failure: {why}{who}); the "
                "solution may blow up or leave the domain of f there"
            )
        return new

    def initial_step(self, t_span) -> float:
        """``0.01 |u0| / |f(u0)|`` in the error norm, capped by the interval (Hairer-Wanner's first guess)."""
        xp = self.xp
        t0, t1 = t_span
        f0 = self.start_f(t0)
        sc = self.atol + self.rtol * xp.abs(self.y)
        d0 = float(self.rms(self.y / sc).max()) if self.n else 0.0
        d1 = float(self.rms(f0 / sc).max()) if self.n else 0.0
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        return min(h0, t1 - t0)

    def dense_output(self, t_out, u0, t0, steps):
        """Values at ``t_out`` from each step's collocation polynomial through (t_n, u_n), (t_n + c_i h, W_i)."""
        xp = self.xp
        nodes = np.concatenate([[0.0], self.tableau.c])
        rows = []
        k = 0
        for time_point in t_out:
            if time_point <= t0:
                rows.append(u0)
                continue
            while k < len(steps) - 1 and time_point > steps[k][0] + steps[k][1] * (1 + 1e-13):
                k += 1
            t_n, h, u_start, W = steps[k]
            L = self.engine.asarray(lagrange_matrix(nodes, np.array([(time_point - t_n) / h]))[0])
            rows.append(xp.einsum("j,bjk->bk", L, xp.concatenate([u_start[:, None, :], W], axis=1)))
        return np.asarray(t_out, dtype=float), _numpy(xp.stack(rows, axis=1))


def _host(values) -> np.ndarray:
    """A numpy view or copy of an engine's array, of its own dtype."""
    return values if isinstance(values, np.ndarray) else values.detach().cpu().numpy()


def _numpy(values) -> np.ndarray:
    """A float64 numpy copy of an engine's array."""
    if isinstance(values, np.ndarray):
        return values.astype(float, copy=False)
    return values.detach().cpu().double().numpy()
