"""``method="radau"``: the backend glue (engine, controller, stepper, Solution)."""

from __future__ import annotations

import dataclasses
import time

from daemodel.backends.base import AbstractBackend, make_solution
from daemodel.backends.grids import SWEEP_FIRST_STEPS, fixed_step_sweep, grid_steps, output_times
from daemodel.backends.radau.band import BAND_SPARE_BUFFERS, BandKernel, band_entries
from daemodel.backends.radau.casadi_engine import CasadiEngine
from daemodel.backends.radau.compiled import COMPILERS, find_compiler
from daemodel.backends.radau.control import make_controller
from daemodel.backends.radau.fill import FillOverLimit, measured_fill
from daemodel.backends.radau.heap import hand_back_freed_memory
from daemodel.backends.radau.linalg import BAND_FILL_RATIO, DENSE_MAX_SIZE, dense_systems
from daemodel.backends.radau.options import RadauOptions, check_index_stages, stages_for_index
from daemodel.backends.radau.outputs import marked, prepare_outputs, resolve_outputs, resolved_outputs
from daemodel.backends.radau.records import step_record_bytes
from daemodel.backends.radau.sparse import band_orders, jacobian_pattern
from daemodel.backends.radau.stencil import uses_stencil
from daemodel.backends.radau.step import Stepper
from daemodel.backends.radau.transform import stage_transform
from daemodel.backends.torch_setup import torch_device, torch_threads, warm_up_torch

from daemodel.errors import (
    CompileError,
    ConvergenceError,
    DaemodelError,
    InvalidOptionError,
    ResourceLimitError,
    TimeLimitError,
)
from daemodel.files import MEMORY_LIMIT_VARIABLE, check_memory, memory_limit
from daemodel.messages import clip
from daemodel.tableau import radau_iia


class RadauBackend(AbstractBackend):
    """``method="radau"``: batched Radau IIA with Newton, fixed or adaptive steps."""

    name = "radau"
    Options = RadauOptions
    # index 3 would need h^-2-conditioned Newton matrices; solve() reduces it to index 2
    max_index = 2
    stops = True  # solve(..., stop=...): the event search ends a solve at a crossing (base.py, rule 8)

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return fixed_step_sweep(t_span, points, steps)

    def times_follow_samples(self, options: RadauOptions) -> bool:
        return options.adaptive and options.t_eval is None  # a batch steps together, on its own times

    def solve(self, compiled, t_span, start, options: RadauOptions, stop=None):
        if stop is not None and start.size != 1:
            raise InvalidOptionError(f"stop=... reads one sample's outputs; this solve has {start.size} samples")
        options = stages_for_index(options, compiled.index)
        check_index_stages(options, compiled.index, compiled.name)
        if make_engine_name(start, options) == "casadi":
            return self._solve(compiled, t_span, start, options, stop=stop)
        warm_up = warm_up_torch(options.device, options.dtype)  # torch's first use: counted in the setup
        with torch_threads(options.threads, start.size * (len(compiled.states) + len(compiled.algebraics))):
            return self._solve(compiled, t_span, start, options, warm_up, stop=stop)

    def _solve(
        self, compiled, t_span, start, options: RadauOptions, warm_up: float = 0.0, check: bool = True, stop=None
    ):
        began = time.perf_counter()  # (the memory estimate reads the Jacobian's pattern: setup)
        engine_name, D = make_engine_name(start, options), len(compiled.states) + len(compiled.algebraics)
        parts = memory_parts(
            compiled, t_span, start.size, options, engine_name
        )  # (made once: one LU of the pattern, .fill)
        check_memory(f"radau on {start.size} sample(s) of {D} unknowns", parts)
        machine_code, said = jit_choice(engine_name, options, D)
        # "auto" remembers a failed compile of this model for the process (and its pieces between events
        # and breakpoints, which share its cache): a failing or hanging compiler is tried once, not per solve
        failed = compiled.cached("radau-jit-auto-failed", list)
        if machine_code and options.jit == "auto" and failed:
            machine_code, said = False, f"{failed[0]}, earlier in this process"
        try:
            engine, stepper = self._stepper(compiled, start, options, machine_code)
        except CompileError as error:
            if options.jit is True:
                raise
            # "auto": the compiler failed (every compile runs here, in the setup): the virtual machine
            machine_code, (engine, stepper) = False, self._stepper(compiled, start, options, False)
            said = f"casadi's virtual machine: the C compiler failed ({clip(str(error), 300)})"
            failed.append(said)
        if machine_code and engine.cache_outcome() is None:  # (every compile ran in the setup: none did)
            said = (
                "casadi's virtual machine: nothing to compile for this solve (sparse systems run in machine code "
                "only in adaptive steps whose LU takes a fixed pivot order; here SuperLU on the general path)"
            )
        hand_back_freed_memory(start.size * D)  # (before the factors' buffers: not in the setup's freed pages)
        if engine.name == "casadi" and isinstance(engine._order, BandKernel):  # (its buffers made in the setup)
            real = sum(sigma.imag == 0 for sigma in engine.transform.shifts(1.0))  # (the systems of a factorisation)
            engine._order.reserve({False: real, True: len(engine.transform.shifts(1.0)) - real})
        if options.adaptive:
            # adaptive steps keep a record each: how many fit in the memory the solve may take (a fixed
            # grid's records were counted before the solve)
            known = sum(parts.values())
            stepper.record_budget = (memory_limit() - known) // step_record_bytes(D, start.size, options)
        prepare_outputs(options, compiled)  # (a piece's model between events: its code made here, in the setup)
        setup = time.perf_counter() - began + warm_up
        began = time.perf_counter()
        try:
            times, values = stepper.integrate(t_span, stop)
            stepper.drop_factors()  # (the band kernel's buffers back to its spares for the next solve: .band)
        except ConvergenceError as error:
            where = getattr(error, "sign_change", None)
            if where is None or options.adaptive or not check:
                raise
            raise self._at_a_smaller_step(compiled, t_span, start, options, error, where) from None
        if engine.name == "torch" and engine.device.type == "cuda":
            engine.torch.cuda.synchronize(engine.device)
        # (adaptive steps, index 2 or more: the algebraic variables at the outputs from the states, .outputs)
        values, resolved, signs = resolve_outputs(self.name, compiled, start, options, times, values, stepper.stats)
        wall = time.perf_counter() - began
        if said is not None:
            stepper.stats["jit"] = said
        if engine.name == "casadi" and isinstance(engine._order, BandKernel):  # (.band: its LU in C)
            widths = f"band widths {engine._order.kl} and {engine._order.ku}"
            stepper.stats["band_lu"] = f"machine code ({widths}; cache: {', '.join(engine.band_outcomes)})"
        if engine.name == "casadi" and engine.stencil is not None:  # (f and g of a repeated stencil in C: .stencil)
            stepper.stats["stencil"] = engine.stencil
        if engine.name == "casadi" and engine.static is not None:
            # (factorisations the fixed pivot order did not hold, each factored by LAPACK or SuperLU: .pivots)
            stepper.stats["pivot_failures"] = engine.pivot_failures
        if engine.name == "casadi" and engine.cache_outcome() is not None:
            stepper.stats["compiled_cache"] = engine.cache_outcome()  # (daemodel.cache: hit, miss, refused: ...)
        if engine.name == "torch":
            stepper.stats["torch_threads"] = engine.torch.get_num_threads()
            stepper.stats["torch_warm_up_seconds"] = warm_up
        if options.adaptive:  # (flagged where a newton_tol looser than the stages' default was given)
            status = stepper.controller.status(self.name)
            if resolved is not None:
                status = resolved if status == "success" else f"{status}; {resolved}"
        else:
            status = stepper.error.status(self.name, options.estimate_bound)
        return make_solution(
            self,
            compiled,
            start,
            options,
            times,
            values,
            wall,
            stepper.stats,
            status=status,
            setup_time=setup,
            dense=marked(stepper.polynomials(), resolved_outputs(options, compiled)),
            branch_signs=signs,  # (read off the solve at the outputs: .outputs)
        )

    @staticmethod
    def _stepper(compiled, start, options: RadauOptions, machine_code: bool):
        """The engine (in machine code or not: :func:`jit_choice`) and the stepper of a solve."""
        engine = make_engine(compiled, start, options, machine_code)
        return engine, Stepper(compiled, start, options, engine, make_controller(options))

    def _at_a_smaller_step(self, compiled, t_span, start, options: RadauOptions, error, where) -> ConvergenceError:
        """The error for a determinant that changed sign on a fixed grid: ``error`` where the change
        remains at ``h / SMALLER_STEP`` too (the solution passes a point where z is undetermined), else
        one that says the change is the step's own, too large for the solution there, and which h
        passes (a CSTR at h = 1 was told to reformulate its constraints, where h = 0.5 works)."""
        smaller = options.h / SMALLER_STEP
        end = min(float(t_span[1]), where[1] + options.h)
        try:
            finer = dataclasses.replace(options, h=smaller, t_eval=None)
            self._solve(compiled, (t_span[0], end), start, finer, check=False)
        except TimeLimitError:  # (the time ran out: it says nothing about the step)
            raise
        except DaemodelError:
            return error
        return ConvergenceError(
            f"radau: with h = {options.h:.3g} the determinant of the constraints' iteration matrix (g_z, or g_y "
            f"f_z at index 2) changes sign between t = {where[0]:.6g} and {where[1]:.6g}, but with h = {smaller:.3g} "
            f"the solve passes t = {end:.6g} without it: the change is the step's own, too large for the "
            f"solution there; take h = {smaller:.3g} or smaller, or the adaptive mode (rtol=..., atol=...)"
        )


# A determinant's sign change on a fixed grid is checked at this many times smaller steps.
SMALLER_STEP = 4


# The fill of the s D-sized full Newton system's SuperLU factors, over s^2 times that of one D-sized
# system (:func:`.fill.measured_fill`): 0.72-0.74 measured on reaction-diffusion at 600
# unknowns, 0.92-0.94 on the chain of 60 pendulums (300), s = 3, 5, 7.
STAGE_FILL = 1.0


def memory_parts(compiled, t_span, B: int, options: RadauOptions, engine: str = "torch") -> dict:
    """What a solve of ``B`` samples holds, in bytes, as far as it is known before it starts: the
    Newton matrices (a stage Jacobian and the factored transformed systems: about (2s + 1) D^2 a
    sample where they are dense, the torch engine's and the casadi engine's small or full systems;
    on the casadi engine's sparse systems the Jacobian's nonzeros and s factors of the fill SuperLU
    makes of its pattern, :func:`.fill.measured_fill`, and on fixed steps the full Newton
    system of s D unknowns, about s^2 that fill: :data:`STAGE_FILL`), and the outputs (a fixed grid's
    points, or t_eval's; with t_eval or ``dense_output``, each step's stages for the dense output).
    Adaptive steps add per step what :func:`step_record_bytes` says.  A :class:`ResourceLimitError` where
    the fill is known to be beyond :func:`memory_limit` before it is measured (:mod:`.fill`)."""
    n, D, s = len(compiled.states), len(compiled.states) + len(compiled.algebraics), options.stages
    itemsize = 4 if options.dtype == "float32" else 8
    parts = {"Newton matrices": B * (2 * s + 1) * D * D * itemsize}
    steps = None if options.adaptive else grid_steps(t_span, options.h, max_steps=options.max_steps)
    outputs = {}
    if options.t_eval is not None:
        outputs["outputs"] = B * len(output_times(options.t_eval, t_span, ())) * D * 8  # validated first
    if steps is not None:
        if options.t_eval is not None:
            name = "step records"
        else:
            name = "outputs with the dense output (dense_output=False keeps the step ends only)"
            name = name if options.dense_output else "outputs"
        outputs[name] = steps * step_record_bytes(D, B, options)
    if engine == "casadi" and D > DENSE_MAX_SIZE:
        rows, cols = jacobian_pattern(compiled, uses_stencil(compiled, options.jit, jit_choice(engine, options, D)[0]))
        if not dense_systems(D, rows.size):
            # a fixed step's full Newton (where simplified Newton fails, or from start_guess) factors the s D-sized
            # system, its matrix and its factors in float64: s^2 nonzeros of J's, and STAGE_FILL s^2 times the fill
            # (2.2-6.4x s times it at s = 3-7: the guard under-counted)
            full = not options.adaptive or options.start_guess is not None
            fixed, per_entry = rows.size * 8 * (s + 1) + (s * s * rows.size * 8 if full else 0), s * 16
            per_entry += s * s * STAGE_FILL * 8 if full else 0
            left = (memory_limit() - sum(outputs.values()) - fixed) / per_entry  # (the fill the limit leaves)
            try:  # (per model)
                fill = compiled.cached(
                    "radau-factor-entries", lambda: measured_fill(rows, cols, n, D, max(left, 0), options.fill_seconds)
                )
            except FillOverLimit as over:
                allowed = f"the {memory_limit() / 2**30:.3g} GiB allowed"
                setting = f"set {MEMORY_LIMIT_VARIABLE}, e.g. '64G', to change it"
                if over.entries is None:
                    held = f"could not be counted within {allowed} ({over.reason}; {setting})"
                else:
                    gib = (fixed + per_entry * over.entries) / 2**30
                    held = (
                        f"would hold about {over.entries:.3g} entries or more ({over.reason}), {gib:.3g} GiB with "
                        f"its {s} stages' systems, more than {allowed} (the fill that fits: {max(left, 0):.3g} "
                        f"entries; {setting})"
                    )
                raise ResourceLimitError(
                    f"radau on {B} sample(s) of {D} unknowns: the LU factors of its sparse Newton systems {held}: "
                    "fewer unknowns, or a Jacobian pattern that fills less (banded, block-diagonal), would fit"
                ) from None
            # (the complex systems' factors at 16 bytes an entry, the real one's at 8: s of them in all)
            order, systems = band_orders(compiled, rows, cols, n, D), s * fill
            if order is not None:  # (factored in it: at most this more fill)
                fill = BAND_FILL_RATIO * fill
                systems = s * fill
                band = band_entries(order, rows, cols, n, D)  # (the band LU in C: its storage, and its spares)
                if band is not None and options.jit is not False and find_compiler() is not None:
                    systems = (s + 2 * BAND_SPARE_BUFFERS) * band
            matrices = rows.size * 8 * (s + 1) + systems * 16
            if full:
                matrices += s * s * (rows.size + STAGE_FILL * fill) * 8
            parts = {"Newton matrices (sparse)": int(matrices)}
    return parts | outputs


def make_engine_name(start, options: RadauOptions) -> str:
    """The engine ``options.engine`` picks for ``start`` ("auto": see :func:`make_engine`)."""
    if options.engine != "auto":
        return options.engine
    on_cpu = options.device == "cpu" or torch_device(options.device).type == "cpu"
    return "casadi" if start.size == 1 and options.dtype == "float64" and on_cpu else "torch"


# jit="auto" compiles models of at most this many unknowns (n + m).  Measured on reaction-diffusion,
# cold cache, one shared core: the first compile costs 5 s at 100 unknowns, 16 s at 200, 68 s at 500 and
# 96 s at 1,000, for 6-7 ms saved per solve (at 1,000 the machine code's solve was slower); at issue
# 44's 10^5 it would not finish.  jit=True compiles at any size.
JIT_AUTO_MAX_SIZE = 200


def jit_choice(name: str, options: RadauOptions, D: int) -> tuple[bool, str | None]:
    """Whether the engine ``name`` runs the steps of ``D`` unknowns in machine code (``options.jit``:
    "auto", True, False; "auto" up to :data:`JIT_AUTO_MAX_SIZE` unknowns), and what ``stats["jit"]``
    says of it (None on the torch engine, which compiles nothing)."""
    if name != "casadi":
        return False, None
    if options.jit is False:
        return False, "casadi's virtual machine (jit=False)"
    if options.jit == "auto" and D > JIT_AUTO_MAX_SIZE:
        return False, (
            f"casadi's virtual machine: {D} unknowns, above jit='auto''s {JIT_AUTO_MAX_SIZE} (compiling would "
            "take minutes for little saved per solve; jit=True compiles at any size)"
        )
    compiler = find_compiler()
    if compiler is None:  # (jit=True without a compiler was refused by RadauOptions)
        return False, f"casadi's virtual machine: no C compiler on PATH (tried {', '.join(COMPILERS)})"
    return True, f"machine code ({compiler})"


def make_engine(compiled, start, options: RadauOptions, machine_code: bool | None = None):
    """The engine ``options.engine`` names; ``"auto"``: casadi for one trajectory in float64 on the CPU
    (compiled functions, no per-operation dispatch), torch for batches, float32 and GPUs.  The casadi
    engine's steps run in machine code where ``machine_code`` says so (default: :func:`jit_choice`)."""
    tableau = radau_iia(options.stages)
    transform = stage_transform(tableau)
    name = make_engine_name(start, options)
    if options.jit is True and name != "casadi":
        raise InvalidOptionError(
            f"jit=True compiles the casadi engine's functions, for one trajectory in float64 on the CPU; this "
            f"solve ({start.size} sample(s), {options.dtype}, device {options.device!r}) runs on the torch engine: "
            "leave jit out"
        )
    if machine_code is None:
        machine_code = jit_choice(name, options, len(compiled.states) + len(compiled.algebraics))[0]
    if name == "casadi":
        if start.size != 1:
            raise InvalidOptionError(
                f"engine='casadi' solves one trajectory; this batch has {start.size} samples: use engine='torch' "
                "(or 'auto')"
            )
        # (narrow band orders' LU in C wherever machine code may run: a small library, whatever the size)
        band = options.jit is not False and find_compiler() is not None
        return CasadiEngine(compiled, start, tableau, transform, jit=machine_code, band=band)
    import torch
    from daemodel.backends.radau.torch_engine import TorchEngine

    return TorchEngine(compiled, start, tableau, transform, getattr(torch, options.dtype), torch_device(options.device))
