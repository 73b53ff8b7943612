"""Options of ``method="radau"``: one frozen dataclass, validated where it is made."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import DEFAULT_ESTIMATE_BOUND
from daemodel.backends.checks import check_dtype, check_stages, check_threads, set_number, set_tolerances
from daemodel.backends.radau.compiled import COMPILERS, find_compiler
from daemodel.backends.radau.fill import TRIAL_SECONDS
from daemodel.backends.torch_setup import torch_device

from daemodel.errors import InvalidOptionError
from daemodel.messages import clip

# Newton's most iterations per attempt unless max_newton_iterations is given (a failure with fewer
# names it).
DEFAULT_NEWTON_ITERATIONS = 10

# Stages of a fixed step when none are given: the paper's v = 3 (order 5).
FIXED_STAGES = 3
# Stages of adaptive mode when none are given, by rtol: (smallest rtol, stages), loosest first.
# Measured at equal error on the pendulums, Robertson, the squeezer and the scaling families
# (benchmarks/adaptive_precision.py): s = 5 takes 3-5x fewer steps than s = 3 below rtol 1e-6
# for 1.3-2x the cost of a step, and s = 7 pays off from 1e-9 down (at looser tolerances
# its steps are rejected or fail Newton more often).  At 1e-10 the ring modulator takes 42,595 steps
# with 7 stages against 125,478 with 5 (over the default max_steps), 1.1 s against 2.1 s of solve at
# the same 9.6 digits.  At 1e-9 (warm solves, min of 3): the ring 36,937 steps and 1.01 s against
# 95,740 and 1.44 s (with 6,441 rejections: over the default max_steps, a StepLimitError in the
# bench), car axis 6.1 against 10.8 ms, the transistor amplifier 31 against 41 ms, Fekete 395
# against 470 ms, Akzo Nobel equal; the squeezer 17.7 against 12.8 ms and HIRES and pollution
# 0.2 ms slower, at the same digits.  Each entry holds for rtol >= its smallest rtol, loosest first.
# On systems of index 0 and 1, s = 5 from below 1e-5: with s = 3 the ring modulator took 125,656
# attempts at rtol = atol = 1e-6 (over the default max_steps: a StepLimitError at the default settings
# and at 2e-6; RADAU5 at the same internal tolerance takes 120,834 steps), with s = 5 36,073 (0.55
# against 1.2 s) and 24,428 at 9e-6, its end values 100x closer to the Test Set's reference; at 1e-6
# and 3e-6 (min of 5 passes) s = 5 was as fast or faster on the transistor amplifier (1.7x), Akzo
# Nobel, Robertson and reaction-diffusion, and its first compile up to 1.5x dearer (reaction-diffusion
# K = 50: 1.65 -> 2.5 s on a loaded machine).
ADAPTIVE_STAGES = ((1e-5, 3), (math.nextafter(1e-9, 1.0), 5), (0.0, 7))
# On systems of index 2 (and 3, solved as their index-2 reduction) the same, since s = 5 guesses the
# algebraic variables blind to their stages' defect pattern (.formulas.HIGH_INDEX_GUESS_MIN_STAGES):
# before, s = 5 at rtol 1e-6 (atol 1e-8) failed Newton on the pendulum over [0, 1000] at ever shorter
# steps (down to 2.5e-8; at 1e-5 a StepLimitError), and s = 3 was kept down to 1e-6.  At rtol = atol =
# 1e-6 (the radau_idas problems, min of 7 interleaved passes, one thread) s = 5 against s = 3: car axis
# 2.7 against 6.0 ms (state error 1.2e-6 against 1.1e-5), the squeezer 5.6 against 6.1 (9e-7, 1.2e-6),
# chains of 20 and 40 pendulums 3.3 against 4.2 and 6.7 against 12.1 (1.0e-6 and 8.7e-7 against 1.8e-6
# and 2.4e-6), the pendulum 0.42 against 0.41 (1.9e-7, 4.6e-7); over [0, 1000], 12,884 attempts
# against 27,589.  At 1e-5 s = 3 stays: s = 5 was slower on the squeezer (4.7 against 3.9 ms), the
# 40-chain (9.0 against 5.5) and the pendulum.
ADAPTIVE_STAGES_INDEX2 = ((1e-5, 3), (math.nextafter(1e-9, 1.0), 5), (0.0, 7))
# Fewest stages of adaptive mode.  One stage is implicit Euler: its local error is O(h^2), so steps
# that keep each local error at rtol number ~rtol^(-1/2) and add up to ~rtol^(1/2), 20-200 x rtol on
# a stiff linear pair at rtol 1e-4 and 1e-6 (tests/backends/test_radau_control.py), up to 4,000 x on
# random stiff systems; two stages (order 3) stayed within 0.1-100 x on the same systems.
MIN_ADAPTIVE_STAGES = 2
# Fewest stages of adaptive mode on a system of index 2 (an index-3 one is solved as its index-2
# reduction).  Two stages are order 3 over an order-2 estimate: steps that hold the estimate at rtol
# leave a global error that is a fixed multiple of rtol, whatever rtol, and at index 2, where the
# algebraic variables' estimates are weighted by h, that multiple grew large: the squeezer's
# velocities ended 1,000-1,600 x rtol off (its accelerations 1,700-2,600 x) at rtol 1e-3 to 1e-9,
# the car axis's 43-62 x, and both said success; three stages: 3-36 x and 0.2-5.5 x
# (tests/backends/test_radau_options.py).  The squeezer's error is a lag of the whole mechanism
# (4.5e-7 s at rtol 1e-5; 1.3e-8 s with three stages), read at t = 0.03 where its bodies' accelerations
# are 1e4-6e5 times their velocities.  No Radau code adapts steps with two stages (RADAU5 and
# Hairer's RADAU take 3, 5 or 7).
MIN_ADAPTIVE_STAGES_INDEX2 = 3
# Who evaluates and factors: "auto" picks casadi for one float64 CPU trajectory, torch otherwise.
ENGINES = ("auto", "torch", "casadi")
# Tolerances of adaptive mode when neither h nor rtol/atol is given.
DEFAULT_RTOL, DEFAULT_ATOL = 1e-6, 1e-8
# float32 carries ~7 digits: asking for more from it is an error, not a silent loss.
FLOAT32_MIN_RTOL = 1e-5
# Adaptive mode: default budget of step attempts (accepted, rejected, or failed in Newton).  It bounds the loop,
# and is set for a long span to run rather than to be refused: the pendulum on [0, 1000] at rtol = 1e-6 takes
# 27,000 attempts with three stages (2.8-12 s on one shared core with the casadi engine, 0.1-0.4 ms an attempt;
# 12,900 with the default's five), the old default of 5,000 stopped it at t = 106.  A span that cannot finish
# within it does not spend it: the progress watch (progress.ProgressWatch) stops after two windows of 100
# attempts that project past it, naming max_steps.  What spends it all is chattering at a switch (rejected
# attempts with h collapsing): 10-40 s with the casadi engine, minutes with the torch engine (2-6 ms an
# attempt); give a smaller max_steps where a quick failure matters more than a long span.
DEFAULT_MAX_ADAPTIVE_STEPS = 100_000
# Fixed step: default bound on the grid's step count, checked before the grid is built (the count
# is known up front, so no runaway is possible; daemodel.compare's finest sweep takes 20,480 steps).
DEFAULT_MAX_FIXED_STEPS = 100_000


@dataclass(frozen=True, kw_only=True)
class RadauOptions:
    """Options of ``method="radau"``.

    Attributes
    ----------
    stages : int, optional
        Radau IIA stages s (order 2s-1 for y; s for an index-2 algebraic variable).  Adaptive steps
        take at least 2, and at least 3 on a system of index 2 or 3
        (:data:`MIN_ADAPTIVE_STAGES_INDEX2`: two stages' global error there reached 1,000-2,600 x
        rtol and said success).  Default: 3
        (RADAU5, the paper's v = 3) for a fixed step and for ``rtol >= 1e-5``; 5 (order 9) below that
        down to ``1e-9 < rtol``, and 7 (order 13)
        from 1e-9 down, where the larger steps of the higher order pay for its larger systems
        (:data:`ADAPTIVE_STAGES`, :data:`ADAPTIVE_STAGES_INDEX2`).
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
        step (the collocation solution to rounding); relative to the error tolerance in adaptive
        mode, RADAU5's ``max(10 eps / rtol, min(0.03, sqrt(rtol)))`` up to three stages, and
        ``max(10 eps / rtol, min(1e-3, rtol^((s - 1) / (s + 1))))`` for more, as Hairer's RADAU
        (radau.f) sets it per stage count, but not below ten floors ``100 eps / rtol`` where
        three stages' rule is not (rtol below ~1.6e-8: Newton stalls on rounding at the floor)
        (:func:`~.control.adaptive_newton_tol`).  A value given
        is taken as it is, above that cap too; one looser than the stages' default may leave stage
        errors that do not shrink with h (seven stages at rtol 1e-4 on the pendulum: 0.03 collapses
        h), and the budget's and the underflow's errors then say so; a solve that finishes is
        flagged (:class:`~daemodel.errors.LocalErrorWarning`): its estimate does not see those errors.
    max_newton_iterations : int
    max_steps : int, optional
        Fixed step: most steps of the grid, refused before it is built
        (:class:`~daemodel.errors.ResourceLimitError`); default 100,000.  Adaptive mode: most step
        attempts, accepted, rejected or failed in Newton alike
        (:class:`~daemodel.errors.StepLimitError`); default 100,000
        (:data:`DEFAULT_MAX_ADAPTIVE_STEPS`), enough for long spans (the pendulum on [0, 1000] at
        rtol = 1e-6 takes 12,900, 27,600 with three stages).  A span that cannot finish within the
        budget is stopped early, after a few hundred attempts project past it, with the number it
        would need (where h has fallen far below its earlier steps, mostly accepted, a stiff layer,
        after up to a quarter of max_steps: raising max_steps lets a longer layer through).
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
        (:data:`~daemodel.backends.torch_setup.SMALL_TORCH_WORK`).  The casadi engine runs on one thread.
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
    jit : "auto", True or False
        The casadi engine: compile its steps (the adaptive attempt: start guess, Newton, error
        estimate; and the fused Newton iteration of fixed steps) to machine code with the system's
        C compiler (:data:`~.compiled.COMPILERS`, the first on PATH; ``CC`` is not read; a compiler
        run is stopped after ``DAEMODEL_COMPILE_TIMEOUT`` seconds where set; 0.3-1 s once per model and
        stages for systems of ten unknowns, seconds for a hundred, in the setup; kept in the disk
        cache :mod:`daemodel.cache`, so a later process loads it in ~0.02 s) instead of running
        them on casadi's virtual machine, and, in adaptive mode, factor the transformed systems by
        LU with a fixed pivot order in a C loop (:mod:`~daemodel.backends.radau.kernel`, wherever
        the elimination is small, dense or sparse), with up to 32 attempts in one call at any size.
        Fixed steps give the same results bit for bit; adaptive ones the same steps and values to
        rounding (the factors differ from LAPACK's in the last bits), 1.1-4x faster on the Test Set
        problems.  The C sources are compiled in a private temporary directory that is removed
        once the library is stored and loaded.

        ``"auto"`` (the default): machine code wherever the casadi engine runs a model of at most
        :data:`~.backend.JIT_AUTO_MAX_SIZE` (200) unknowns and a C compiler is found, else casadi's
        virtual machine (larger models' first compile takes minutes for little saved per solve);
        ``stats["jit"]`` says which and why, once per solve
        (no warning).  Where the compiler fails, ``"auto"`` goes on on the virtual machine and says
        so there, with the compiler's message, and does not try that model again in this process
        (nor its pieces between events and breakpoints).  ``True`` insists: an
        :class:`~daemodel.errors.InvalidOptionError` without a compiler or on the torch engine, a
        :class:`~daemodel.errors.CompileError` where the compiler fails.  ``False``: the virtual
        machine, nothing compiled.
    estimate_bound : float, optional
        Fixed step only: a run whose largest local error estimate, in units of the solution's
        size ``1 + max |u|``, exceeds this is flagged (status ``"flagged: ..."`` naming the step,
        and a :class:`~daemodel.errors.LocalErrorWarning`) instead of "success".  Default
        :data:`~daemodel.backends.base.DEFAULT_ESTIMATE_BOUND`; every step's estimate is in
        ``stats["local_error_estimates"]``.  Beyond
        :data:`~daemodel.backends.base.LOCAL_ERROR_BOUND` a step has no correct digit and the
        solve raises :class:`~daemodel.errors.LocalErrorBoundError`.
    dense_output : bool
        Keep each step's collocation polynomial (its start value and stages) in
        :attr:`Solution.dense`, for :meth:`Solution.at` at the method's own accuracy between the
        output times.  Default True; it holds s + 1 values per step where the step ends alone hold
        one: False keeps only those (large batches over many steps), and ``at()`` then interpolates
        the outputs by cubic Hermite polynomials.
    stages_by_default : bool
        Set to True by the options themselves where ``stages`` is left out (give ``stages``, not
        this): the stages picked from rtol are then picked again for the index of the system solved
        (:func:`stages_for_index`), and options copied with ``dataclasses.replace`` keep that.  True
        beside stages that no default picks at this rtol is an
        :class:`~daemodel.errors.InvalidOptionError`.
    fill_seconds : float
        The casadi engine's sparse systems: the most seconds the memory guard's count of their LU factors'
        fill may take where it runs in a child process (a dense row or column, whose bound from the pattern
        says little: :mod:`~daemodel.backends.radau.fill`); past it the solve is refused
        (:class:`~daemodel.errors.ResourceLimitError` naming it), since one factorisation of each Jacobian
        would take as long.  Default :data:`~daemodel.backends.radau.fill.TRIAL_SECONDS` (30); the count is
        made once per model.
    """

    stages: int | None = None
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    h0: float | None = None
    t_eval: object = None
    newton_tol: float | None = None
    max_newton_iterations: int = DEFAULT_NEWTON_ITERATIONS
    max_steps: int | None = None
    reuse_jacobian: bool = True
    dtype: str = "float64"
    device: str = "cpu"
    threads: int | None = None
    engine: str = "auto"
    start_guess: object = None
    jit: bool | str = "auto"
    estimate_bound: float | None = None
    dense_output: bool = True
    stages_by_default: bool = False
    fill_seconds: float = TRIAL_SECONDS

    def __post_init__(self) -> None:
        for name in ("h", "rtol", "atol", "h0", "newton_tol"):
            set_number(self, name, allow_none=True)
        set_number(self, "fill_seconds")  # (None was taken: the child's count waited without a bound)
        set_number(self, "max_newton_iterations", integer=True)
        object.__setattr__(self, "dtype", check_dtype(self.dtype))
        if self.h is not None and (self.rtol is not None or self.atol is not None or self.h0 is not None):
            raise InvalidOptionError("h fixes the step size; rtol/atol/h0 select adaptive steps: give one or the other")
        if self.max_steps is None:
            object.__setattr__(
                self, "max_steps", DEFAULT_MAX_ADAPTIVE_STEPS if self.adaptive else DEFAULT_MAX_FIXED_STEPS
            )
        set_number(self, "max_steps", integer=True)
        if self.adaptive:
            object.__setattr__(self, "rtol", DEFAULT_RTOL if self.rtol is None else self.rtol)
            object.__setattr__(self, "atol", DEFAULT_ATOL if self.atol is None else self.atol)
            if self.dtype == "float32" and self.rtol < FLOAT32_MIN_RTOL:
                raise InvalidOptionError(
                    f"rtol = {self.rtol:g} is below what float32 can deliver (>= {FLOAT32_MIN_RTOL:g}); "
                    "use dtype='float64'"
                )
            set_tolerances(self)
        if self.stages is None:
            object.__setattr__(self, "stages_by_default", True)
            object.__setattr__(self, "stages", adaptive_stages(self.rtol) if self.adaptive else FIXED_STAGES)
        check_stages(self.stages)
        if self.adaptive and self.stages < MIN_ADAPTIVE_STAGES:
            raise InvalidOptionError(
                f"stages = {self.stages} (implicit Euler, order 1) cannot take adaptive steps: the step-size "
                "control bounds each step's local error by rtol/atol, and a first-order method's global error "
                "then grows with the number of steps (100-4,000 x rtol measured at rtol 1e-6 to 1e-9); give "
                f"stages >= {MIN_ADAPTIVE_STAGES} (or leave stages out), or h=... for a fixed implicit Euler grid "
                "checked by its error estimate"
            )
        eps = float(np.finfo(self.dtype).eps)
        if self.newton_tol is not None and self.newton_tol < 10 * eps:
            raise InvalidOptionError(
                f"newton_tol = {self.newton_tol:g} is below 10 eps of {self.dtype} ({10 * eps:.1e}); "
                "Newton cannot reach it" + (": use dtype='float64'" if self.dtype == "float32" else "")
            )
        check_threads(self.threads)
        for name in ("reuse_jacobian", "dense_output", "stages_by_default"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidOptionError(f"{name} must be True or False; got {getattr(self, name)!r}")
        _check_stages_by_default(self)
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
        set_number(self, "estimate_bound", allow_none=True)
        if self.estimate_bound is not None and self.adaptive:
            raise InvalidOptionError(
                "estimate_bound bounds a fixed step's local error estimate (h=...); adaptive steps meet rtol/atol"
            )
        if self.estimate_bound is None and not self.adaptive:
            object.__setattr__(self, "estimate_bound", DEFAULT_ESTIMATE_BOUND)
        if not (isinstance(self.jit, bool) or (isinstance(self.jit, str) and self.jit == "auto")):
            raise InvalidOptionError(f"jit must be 'auto', True or False; got {clip(repr(self.jit), 60)}")
        if self.jit is True and self.engine == "torch":
            raise InvalidOptionError(
                "jit=True compiles the casadi engine's functions (one trajectory in float64 on the CPU); "
                "engine='torch' has nothing to compile: leave jit out, or use engine='auto' or 'casadi'"
            )
        if self.jit is True and find_compiler() is None:
            raise InvalidOptionError(
                f"jit=True needs a C compiler on PATH (tried {', '.join(COMPILERS)}); install one (e.g. gcc), "
                "or leave jit out ('auto': casadi's virtual machine where no compiler is found; the same results "
                "to rounding, slower steps)"
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


def _check_stages_by_default(options: RadauOptions) -> None:
    """Refuse ``stages_by_default=True`` beside ``stages`` that no default would pick at this rtol:
    the index would re-pick them silently (:func:`stages_for_index`).  Copies made with
    ``dataclasses.replace`` hold a default's pick and pass (an event's one fixed step keeps the adaptive
    pick it was copied from)."""
    if not (options.stages_by_default and options.adaptive):  # (fixed steps keep their stages: no re-pick)
        return
    picks = {adaptive_stages(options.rtol, index) for index in (0, 2)}
    if options.stages not in picks:
        raise InvalidOptionError(
            f"stages = {options.stages} with stages_by_default=True: the options set stages_by_default "
            f"themselves where stages is left out (the defaults here pick {' or '.join(map(str, sorted(picks)))} "
            "by the system's index), and would replace the stages given; give stages, or leave both out"
        )


def check_index_stages(options: RadauOptions, index: int, name: str) -> None:
    """Refuse adaptive steps with fewer than :data:`MIN_ADAPTIVE_STAGES_INDEX2` stages on a system of
    index 2 (``index``: the system's, ``name``: the model's), with an
    :class:`~daemodel.errors.InvalidOptionError` that says why and what to give."""
    if options.adaptive and index >= 2 and options.stages < MIN_ADAPTIVE_STAGES_INDEX2:
        raise InvalidOptionError(
            f"stages = {options.stages} cannot take adaptive steps on the index-{index} system of '{name}' (an index-3 "
            "model is solved as its index-2 reduction): the order-2 error "
            "estimate leaves a global error that is a fixed multiple of rtol, whatever rtol, and on index-2 "
            "systems that multiple reached 1,000-2,600 (the squeezing mechanism's velocities and accelerations "
            f"at rtol 1e-3 to 1e-9); give stages >= {MIN_ADAPTIVE_STAGES_INDEX2} (or leave stages out), or h=... "
            "for a fixed grid checked by its error estimate"
        )


def adaptive_stages(rtol: float, index: int = 0) -> int:
    """The stages adaptive mode uses at ``rtol`` when none are given, on a system of ``index``
    (:data:`ADAPTIVE_STAGES`; :data:`ADAPTIVE_STAGES_INDEX2` from index 2 up)."""
    table = ADAPTIVE_STAGES_INDEX2 if index >= 2 else ADAPTIVE_STAGES
    return next(stages for smallest, stages in table if rtol >= smallest)


def stages_for_index(options: RadauOptions, index: int) -> RadauOptions:
    """``options`` with the default stages of a system of ``index`` (:func:`adaptive_stages`) where the
    stages were not given and the index changes them; else ``options`` itself."""
    if not (options.adaptive and options.stages_by_default):
        return options
    stages = adaptive_stages(options.rtol, index)
    return options if stages == options.stages else dataclasses.replace(options, stages=stages)
