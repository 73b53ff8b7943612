"""``method="pinn"``: the Radau-PINN behind :func:`daemodel.solve`."""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    DEFAULT_ESTIMATE_BOUND,
    LOCAL_ERROR_BOUND,
    AbstractBackend,
    caller_level,
    make_solution,
)
from daemodel.backends.checks import check_output_memory, check_threads, set_number
from daemodel.backends.grids import SWEEP_FIRST_STEPS, SWEEP_STAGES, halving_steps, output_times
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.segments import DEFAULT_MAX_SEGMENTS, MAX_INDEX, PRESOLVE
from daemodel.backends.progress import show_progress
from daemodel.backends.torch_setup import torch_device, torch_threads, warm_up_torch

from daemodel.errors import (
    InvalidOptionError,
    LocalErrorBoundError,
    LocalErrorWarning,
    ShapeError,
    TrainingError,
    UncertifiedWarning,
)
from daemodel.executors import check_executor, refuse_engine
from daemodel.files import writable_file
from daemodel.tableau import radau_iia


@dataclass(frozen=True, kw_only=True)
class PINNOptions:
    """Options of ``method="pinn"``.

    Attributes
    ----------
    config : PINNConfig, optional
        The network, loss and optimizer settings (default: the fast mode, ``PINNConfig()``, with
        its h following the problem, below).
    stages, h : optional
        Radau IIA stages and the segment length, as for the fixed-step methods: given here, they
        replace ``config.stages`` and ``config.h`` (``method="pinn", stages=3, h=0.1`` is
        ``config=PINNConfig(stages=3, h=0.1)``).  Where neither ``h`` nor ``config`` nor
        ``segment_starts`` is given, h follows the problem: the span over the accepted steps of a
        radau solve (3 stages) at rtol = atol = 1e-6 (:func:`~daemodel.backends.pinn.segments.default_segments`;
        16 steps on the pendulum over [0, 1]), at most ``max_segments`` segments; the pre-solve is
        part of the setup time, and ``stats["h_from"]`` says where h came from.
    max_segments : int
        The most segments a default h makes (default 200): a long span with a short transient
        trains this many, flagged where radau at that h would be, not one per step of the transient.
    auto_h : bool, optional
        Take h from the problem (the pre-solve above) even with a ``config`` (True), or never
        (False); default None: where neither ``h``, ``config`` nor ``segment_starts`` is given.  A
        given ``h`` always wins.
    t_eval : array, optional
        Output times instead of the segment grid, within the interval: the values there are the
        PINN's dense output (:meth:`Solution.at`), on each segment the collocation polynomial
        through the segment's start and its network's stage values, degree ``stages``: the
        polynomial radau's ``t_eval`` evaluates on its own stages, so between the segment ends the
        values carry the method's accuracy, and at a segment end they are the grid solution's.
        Checked as radau's (:func:`~daemodel.backends.grids.output_times`: times outside the
        interval, unsorted or not finite are a :class:`~daemodel.errors.TimeSpanError`) before
        any training.  The certificate and the stats stay on the segment grid.
    segment_starts : Solution or array, optional
        Known states at the start of every segment, from a classical solve on a grid that
        contains the segment boundaries or an earlier sweep: an array (segments, n) or
        (B, segments, n) in state order, or a Solution.  The segments then train
        independently from them, as tasks of ``executor``, instead of each from the previous
        one's prediction.
    executor : {"local", "ray"}
        Where independently trained segments run: one after another in this process (the
        default; no worker processes), or one Ray task each, in parallel (``daemodel[ray]``;
        needs ``segment_starts``, on CPU).  As in :func:`daemodel.ensemble`.
    engine : None
        The old spelling of ``executor`` (``engine=`` names radau's casadi or torch engine):
        any value is an :class:`InvalidOptionError` saying so, for one release.
    workers : int, optional
        Ray only, when this call starts Ray: the CPUs of the local cluster (default: all).
    address : str, optional
        Ray only: the cluster to connect to (``"auto"``, ``"ray://host:10001"``).
    threads : int, optional
        torch's intra-op threads for training and evaluation (the caller's setting is restored
        after the solve).  Default: one: a segment's networks are too small to gain from more
        (Hessenberg's fast mode: 0.37 s on one thread, 0.46 s on two, on an idle 2-core CPU, and
        7x slower with two threads when another process holds a core).  Ray tasks take one
        CPU and one thread each.
    progress : bool, optional
        Show a progress bar with the segment, the iteration and the loss terms (default: when
        stderr is a terminal).
    strict : bool
        Raise a :class:`~daemodel.errors.TrainingError` when the answer is not certified (see
        :class:`PINNBackend`), instead of returning it flagged with an
        :class:`~daemodel.errors.UncertifiedWarning`.
    estimate_bound : float
        As radau's: a solve where radau's own local error estimate at the same h and stages (on the
        PINN's steps), in units of the solution's size ``1 + max |u|``, exceeds this is flagged
        (a :class:`~daemodel.errors.LocalErrorWarning`), certified or not; default
        :data:`~daemodel.backends.base.DEFAULT_ESTIMATE_BOUND`.  Beyond
        :data:`~daemodel.backends.base.LOCAL_ERROR_BOUND` a step has no correct digit and the solve
        raises :class:`~daemodel.errors.LocalErrorBoundError`, as radau does.
    save : str or Path, optional
        Write the trained networks here (load them with :meth:`Surrogate.load`; its training
        box is this solve's start, so other initial states are reported as outside it).  The
        directory is checked before training: one that does not exist or is not writable is
        an :class:`InvalidOptionError`.  A batch's independent networks (each answers its own
        sample only) are not saved: use ``PINNConfig(batch="shared")`` for networks to reuse.
    """

    config: PINNConfig | None = None
    stages: int | None = None
    h: float | None = None
    max_segments: int = DEFAULT_MAX_SEGMENTS
    t_eval: object = None
    segment_starts: object = None
    executor: str = "local"
    engine: object = None
    workers: int | None = None
    address: str | None = None
    threads: int | None = None
    progress: bool | None = None
    strict: bool = False
    estimate_bound: float = DEFAULT_ESTIMATE_BOUND
    save: object = None
    auto_h: bool | None = None

    def __post_init__(self) -> None:
        if (
            self.auto_h is None
        ):  # (a bool from here on, so that dataclasses.replace, as a piece between events does, keeps it)
            follows = self.config is None and self.h is None and self.segment_starts is None
            object.__setattr__(self, "auto_h", follows)
        elif not isinstance(self.auto_h, bool):
            raise InvalidOptionError(f"auto_h must be True, False or None; got {self.auto_h!r}")
        if self.h is not None:  # a given h wins (an event's trial solve over a short span gives one)
            object.__setattr__(self, "auto_h", False)
        if self.auto_h and self.segment_starts is not None:
            raise InvalidOptionError(
                "auto_h=True takes h from a pre-solve, but segment_starts must be given on a known grid: give h"
            )
        if self.config is None:
            object.__setattr__(self, "config", PINNConfig())
        set_number(self, "max_segments", integer=True)
        if not isinstance(self.config, PINNConfig):
            raise InvalidOptionError(
                f"config must be a dm.PINNConfig; got {type(self.config).__name__} (e.g. config=dm.PINNConfig(h=0.05))"
            )
        given = {name: getattr(self, name) for name in ("stages", "h") if getattr(self, name) is not None}
        if given:  # PINNConfig checks them, with its own messages
            object.__setattr__(self, "config", dataclasses.replace(self.config, **given))
        check_threads(self.threads)
        refuse_engine("method='pinn'", {} if self.engine is None else {"engine": self.engine})
        check_executor(self.executor, self.workers, self.address, self.config.device)
        if self.executor == "ray" and self.segment_starts is None:
            raise InvalidOptionError(
                "executor='ray' trains segments in parallel, which needs segment_starts (known start values); "
                "without them each segment waits for the previous one's prediction"
            )
        set_number(self, "estimate_bound")
        if not isinstance(self.strict, bool):
            raise InvalidOptionError(f"strict must be True or False; got {self.strict!r}")
        if self.progress is not None and not isinstance(self.progress, bool):
            raise InvalidOptionError(f"progress must be True, False or None; got {self.progress!r}")
        if self.save is not None:
            object.__setattr__(self, "save", writable_file(self.save, "save"))


class PINNBackend(AbstractBackend):
    """Radau-PINN: one network per segment, trained on the Radau IIA stage residual.

    Every answer is certified (:mod:`daemodel.backends.pinn.certificate`): its distance from the
    Radau IIA solution at the same stages and h, set beside Radau's own error.  The Solution's
    ``status`` is ``"success"`` when the distance is within that error for every variable, grid
    time and sample (so the PINN's error is at most about twice Radau's), whatever the training
    budget; otherwise it starts with ``"flagged"``, names the worst variable, segment and sample
    with both numbers, and an :class:`~daemodel.errors.UncertifiedWarning` says the same (a
    :class:`~daemodel.errors.TrainingError` with ``strict=True``).  ``stats["certificate"]`` holds
    the per-sample verdicts and largest distances and errors; ``stats["final_max_residual"]`` the
    training's largest residual.

    The certificate proves closeness to radau, not accuracy, so the status is never better than
    radau's at the same h and stages: the certificate also carries radau's own fixed-step error
    estimate on the PINN's steps, and where radau would raise
    :class:`~daemodel.errors.LocalErrorBoundError` (a step with no correct digit) the PINN raises
    it too; where radau would be flagged (beyond ``estimate_bound``) the PINN is flagged with the
    same estimate and a :class:`~daemodel.errors.LocalErrorWarning`, certified or not.
    """

    name = "pinn"
    Options = PINNOptions
    max_index = MAX_INDEX
    # a benchmark sweep trains at most this many segments per setting (seconds each on one core)
    bench_max_steps = 200

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return [{"stages": SWEEP_STAGES, "h": h} for h in halving_steps(t_span, points, steps)]

    def check_size(self, compiled, t_span, start, options: PINNOptions) -> None:
        """Refuse a solve whose outputs would not fit in memory (on the grid of a given h, else at
        the two ends of the span: a lower bound), or whose training would not on even one segment
        (its dense Radau stage system at 10^4 unknowns and more): before the default h's pre-solve,
        a radau solve (10 s at 10^5 unknowns), and before the switches are found; :meth:`_solve`
        checks both again on its grid."""
        from daemodel.backends.pinn.segments import check_network_memory, segment_grid

        points = 2 if options.auto_h else len(segment_grid(t_span, options.config.h, strict=options.h is not None))
        points += len(output_times(options.t_eval, t_span, None)) if options.t_eval is not None else 0
        check_output_memory(self.name, compiled, start.size, points)
        inputs = len(compiled.states) + len(varying_inputs(options.config, start))
        check_network_memory(compiled, options.config, inputs, start.size, 1, at_least=True)

    def solve(self, compiled, t_span, start, options: PINNOptions):
        warm_up = warm_up_torch(options.config.device, options.config.dtype)  # counted in the setup (training)
        with torch_threads(options.threads if options.threads is not None else 1, 0):
            return self._solve(compiled, t_span, start, options, warm_up)

    def _solve(self, compiled, t_span, start, options: PINNOptions, warm_up: float = 0.0):
        from daemodel.backends.pinn.certificate import certify
        from daemodel.backends.pinn.segments import (
            Progress,
            copies_for,
            default_segments,
            fit_parallel,
            segment_grid,
            train_segments,
        )
        from daemodel.backends.pinn.surrogate import SurrogateNetworks

        config = options.config
        torch_device(config.device)
        presolve, h_from = 0.0, "given"
        if options.auto_h:  # h from a radau solve, in the setup
            count, steps, presolve = default_segments(compiled, t_span, start, options.max_segments)
            config = dataclasses.replace(config, h=(t_span[1] - t_span[0]) / count)
            h_from = f"{PRESOLVE}: {steps} steps, {count} segments"
            if count == options.max_segments and steps > count:
                h_from += f" (at most max_segments = {options.max_segments})"
        grid = segment_grid(t_span, config.h, strict=options.h is not None)  # a short piece: one segment
        segments = len(grid) - 1
        outputs = output_times(options.t_eval, t_span, grid)  # (checked before any training)
        check_output_memory(
            self.name, compiled, start.size, len(grid) + (len(outputs) if options.t_eval is not None else 0)
        )
        # Shared networks take the parameters that differ between samples as inputs; independent
        # ones (one set per sample) hold each sample's values as constants.
        independent = copies_for(config, start.size) > 1
        varying = varying_inputs(config, start)
        if independent and options.save is not None:
            raise InvalidOptionError(
                f"save writes networks that solve any start in their box; the independent networks of a batch of "
                f"{start.size} each solve their own sample only: use config=dm.PINNConfig(batch='shared') to save them"
            )
        inputs = tuple(compiled.parameter_names[i] for i in varying)
        began = time.perf_counter()
        radau_iia(config.stages + 1)  # (the certificate's (s+1)-stage tableau, exact, once per process: setup)
        if options.segment_starts is None:
            networks, stats = train_segments(
                compiled, config, grid, start.y0, start.z0, start.p, varying, show_progress(options.progress), "pinn"
            )
            mode = "sequential"
        else:
            known, algebraics = _segment_starts(options.segment_starts, compiled, grid, start)
            starts = np.concatenate(
                [known, np.broadcast_to(start.p[:, varying], (segments, *start.p[:, varying].shape))], axis=2
            )
            bar = Progress(segments, show_progress(options.progress), "pinn")
            try:
                networks, stats, memory = fit_parallel(
                    compiled,
                    grid,
                    starts,
                    algebraics,
                    start.p,
                    config,
                    bar,
                    options.executor,
                    options.workers,
                    options.address,
                )
            finally:
                bar.close()
            mode = "parallel"
        surrogate = SurrogateNetworks(compiled, config, grid, networks, inputs, stats)  # evaluates and saves them
        trained = time.perf_counter()
        values, predictions = surrogate.trajectory(start, stages=True)
        evaluated = time.perf_counter()
        certificate = certify(
            compiled,
            config,
            grid,
            surrogate.networks,
            surrogate.input_columns,
            values,
            start.p,
            predictions=predictions,
            estimate_bound=options.estimate_bound,
        )
        done = time.perf_counter()
        networks, stats = surrogate.networks, surrogate.stats
        summary = {
            "mode": mode,
            "optimizer": config.optimizer,
            "segments": segments,
            # per sample: independent copies hold one set each
            "networks_per_segment": networks[0].count // networks[0].copies,
            "batch": "independent" if networks[0].copies > 1 else ("shared" if start.size > 1 else "one trajectory"),
            "parameters_per_segment": networks[0].parameter_count() // networks[0].copies,
            "torch_threads": torch_threads_now(),
            "h_from": h_from,
            "presolve_seconds": presolve,
            "training_seconds": trained - began,
            "torch_warm_up_seconds": warm_up,
            "evaluation_seconds": evaluated - trained,
            "certificate_seconds": done - evaluated,
            "certificate": certificate.summary((*compiled.state_names, *compiled.algebraic_names)),
            **{key: [getattr(s, key) for s in stats] for key in ("iterations", "L_f", "L_g", "L_s", "max_residual")},
            "final_max_residual": max(s.max_residual for s in stats),
            "segment_seconds": [s.seconds for s in stats],
        }
        if mode == "parallel":
            # how far the chained prediction drifted from the given start values
            summary["start_mismatch"] = (
                float(np.abs(values[:, 1:-1, : known.shape[2]] - known[1:].transpose(1, 0, 2)).max())
                if segments > 1
                else 0.0
            )
        if options.save is not None:
            surrogate.save(options.save)
        if mode == "parallel" and options.executor == "ray":
            summary["peak_memory_mb"] = memory
        settings = {**dataclasses.asdict(config), "executor": options.executor}
        check_local_error_bound(compiled, grid, certificate, start.batched)  # where radau raises, so does the PINN
        status = certified_status(compiled, config, grid, stats, certificate, start.batched)
        if status != "success":
            if options.strict:
                raise TrainingError(f"pinn: {status.removeprefix('flagged: ')}")
            warnings.warn(f"pinn: {status}", UncertifiedWarning, stacklevel=4)
        estimated = estimate_status(compiled, grid, certificate, options.estimate_bound, start.batched)
        if estimated != "success":  # radau at the same h and stages is flagged: so is the PINN, certified or not
            warnings.warn(f"pinn: {estimated}", LocalErrorWarning, stacklevel=caller_level())
            status = estimated if status == "success" else f"{status}; {estimated.removeprefix('flagged: ')}"
        dense = surrogate.polynomials(values, predictions)
        times = grid
        if options.t_eval is not None:  # the dense output at the user's times (as radau's t_eval)
            times, values = outputs, dense(outputs)
        return make_solution(
            self,
            compiled,
            start,
            options,
            times,
            values,
            done - trained,  # evaluating the trained networks and certifying their answer
            summary,
            settings=settings,
            status=status,
            setup_time=trained - began + warm_up + presolve,  # the h pre-solve, training, torch's first use
            dense=dense,
        )


def varying_inputs(config, start) -> list[int]:
    """The columns of ``start.p`` that shared networks take as inputs after the states: the parameters
    that differ between the samples (none for independent networks, one set per sample)."""
    from daemodel.backends.pinn.segments import copies_for

    if copies_for(config, start.size) > 1:
        return []
    return [i for i in range(start.p.shape[1]) if np.ptp(start.p[:, i]) > 0]


def _segment_starts(given, compiled, grid, start) -> tuple[np.ndarray, np.ndarray]:
    """Known start states of each segment, shape (segments, B, n), and their algebraic values
    (segments, B, m): a Solution's own, or those the states determine (the batched algebraic
    solve of the initialisation, at each segment's start time, from the previous segment's)."""
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.solution import Solution

    segments, n, batch = len(grid) - 1, len(compiled.states), start.size
    algebraics = None
    if isinstance(given, Solution):
        rows = []
        for t in grid[:-1]:
            hit = np.flatnonzero(np.isclose(given.t, t, rtol=0, atol=1e-9 * max(1.0, abs(t))))
            if hit.size == 0:
                raise ShapeError(
                    f"segment_starts: the solution has no value at t = {t:g}; solve it on a grid that "
                    f"contains the segment boundaries (e.g. method='radau', h={grid[1] - grid[0]:g})"
                )
            rows.append(hit[0])
        values = np.stack([np.atleast_2d(given[name])[:, rows] for name in compiled.state_names], axis=-1)  # (B', S, n)
        if compiled.algebraic_names:
            algebraics = np.stack([np.atleast_2d(given[name])[:, rows] for name in compiled.algebraic_names], axis=-1)
    else:
        values = np.asarray(given, dtype=float)
        if values.ndim == 2:
            values = values[None]
    if values.ndim != 3 or values.shape[1:] != (segments, n) or values.shape[0] not in (1, batch):
        raise ShapeError(
            f"segment_starts must have shape ({segments}, {n}) or ({batch}, {segments}, {n}) "
            f"(segments, states {', '.join(compiled.state_names)}); got {np.shape(values)}"
        )
    if not np.all(np.isfinite(values)):
        raise ShapeError("segment_starts holds non-finite values")
    values = np.ascontiguousarray(np.broadcast_to(values, (batch, segments, n)).transpose(1, 0, 2))
    if algebraics is not None and algebraics.shape[0] in (1, batch):
        algebraics = np.ascontiguousarray(
            np.broadcast_to(algebraics, (batch, segments, algebraics.shape[2])).transpose(1, 0, 2)
        )
    else:  # each segment's from the previous one's, the first from the consistent start
        z, algebraics = start.z0, []
        for k in range(segments):
            z = algebraic_values(compiled, float(grid[k]), values[k], start.p, z)
            algebraics.append(z)
        algebraics = np.stack(algebraics)
    return values, algebraics


def certified_status(compiled, config, grid, stats, certificate, batched: bool) -> str:
    """ "success" when ``certificate`` certifies every sample, else "flagged: ..." naming, for the
    first sample that is not certified, the first step whose Newton check failed or whose Radau
    error estimate has no correct digit, or else the variable, segment and sample farthest
    beyond Radau's error, with both numbers; and the first segment that missed ``config.tol``
    (or the fixed budget)."""
    from daemodel.backends.pinn.certificate import CERTIFICATE_SAFETY, ESTIMATE_FAILED, NEWTON_FAILED, NO_DIGIT
    from daemodel.backends.pinn.train import segment_label

    if bool(certificate.certified.all()):
        return "success"
    names = (*compiled.state_names, *compiled.algebraic_names)
    uncertified = np.flatnonzero(~certificate.certified)
    count = f"{len(uncertified)} of {len(certificate.certified)} samples" if batched else "the answer"
    steps = [(b, k) for b in uncertified for k in np.flatnonzero(certificate.failed[b])]
    if steps:
        b, k = steps[0]
        where = segment_label(k, grid[k], grid[k + 1]) + (f", sample {b}" if batched else "")
        if certificate.failed[b, k] == NEWTON_FAILED:
            what = (
                f"at {where}, Newton from the networks' stages does not converge to a Radau step (values outside "
                "f's domain, or a singular step)"
            )
        elif certificate.failed[b, k] == ESTIMATE_FAILED:
            what = (
                f"at {where}, the networks are {CERTIFICATE_SAFETY * certificate.local_distance[b, k].max():.3g} from "
                f"the Radau step, but the {config.stages + 1}-stage step that estimates Radau's own error does not "
                "converge there (values outside f's domain, or a singular step): no error estimate to certify "
                "against at this h"
            )
        else:
            what = (
                f"at {where}, Radau's own step has no correct digit (its estimated local error is beyond "
                f"{LOCAL_ERROR_BOUND:g} of the solution's size): no Radau solution to certify against at this h"
            )
    else:
        b, t, j, _ = certificate.worst()
        where = segment_label(t - 1, grid[t - 1], grid[t]) + (f", sample {b}" if batched else "")
        what = (
            f"at {where}, '{names[j]}' is {certificate.distance[b, t, j]:.3g} from the Radau solution at the same h, "
            f"beyond Radau's own error {certificate.bound()[b, t, j]:.3g} there"
        )
    missed = [s for s in stats if not s.converged]
    if missed:
        first = missed[0]
        training = (
            f"; training stopped above tol = {config.tol:g} in {len(missed)} segment(s), first segment "
            f"{first.segment + 1} ({first.max_residual:.3g}: {first.largest}) after {first.iterations} "
            f"{config.optimizer} iterations"
        )
    elif config.tol is None:
        training = f"; a fixed budget of {config.iterations} {config.optimizer} iterations per segment"
    else:
        training = ""
    # where the networks are on the Radau step but there is no error to certify against, more
    # training cannot help
    at_radau = steps and certificate.failed[steps[0]] in (ESTIMATE_FAILED, NO_DIGIT) and not missed
    fix = "shorten h" if at_radau else "raise iterations or tighten tol, shorten h,"
    return f"flagged: not certified ({count}): {what}{training}; {fix} or use the Radau solution (method='radau')"


def check_local_error_bound(compiled, grid, certificate, batched: bool) -> None:
    """Raise :class:`LocalErrorBoundError` where radau at the same h and stages raises it: at the first
    step whose radau estimate (:attr:`Certificate.estimate`, from the networks' start there) is beyond
    :data:`LOCAL_ERROR_BOUND`.  The certificate puts the PINN next to the Radau solution; where that
    has no correct digit, neither has the PINN."""
    beyond = certificate.beyond_bound()
    if beyond is None:
        return
    sample, step, j, value = beyond
    names = (*compiled.state_names, *compiled.algebraic_names)
    n = len(compiled.state_names)
    index = int(compiled.algebraic_index[j - n]) if j >= n else 1
    size = f"1 + max|{names[j]}|" if index == 1 else f"(1 + max|{names[j]}|) / h^{index - 1}"
    t, h = float(grid[step]), float(grid[step + 1] - grid[step])
    raise LocalErrorBoundError(
        f"pinn: step {step + 1} from t = {t:.6g} with h = {h:.3g}: radau's local error estimate at the same h "
        f"and stages, from the networks' values there, of '{names[j]}'"
        + (f" (sample {sample})" if batched else "")
        + f" is {value:.3g} times the solution's size {size} so far, beyond LOCAL_ERROR_BOUND = "
        f"{LOCAL_ERROR_BOUND:g}: the Radau solution the PINN is certified against has no correct digit there (the "
        "solution may be singular, switch or change too fast); take a smaller h, or method='radau' with rtol=..."
    )


def estimate_status(compiled, grid, certificate, bound: float, batched: bool) -> str:
    """ "success" where radau's own local error estimate at the same h and stages stays within ``bound``
    on every step (:meth:`Certificate.largest_estimate`), as radau's fixed step judges its own; else a
    "flagged: ..." status naming the step, variable and sample (radau's words, for the PINN)."""
    worst = certificate.largest_estimate()
    if worst is None or worst[3] <= bound:
        return "success"
    sample, step, j, value = worst
    name = (*compiled.state_names, *compiled.algebraic_names)[j]
    t, h = float(grid[step]), float(grid[step + 1] - grid[step])
    where = f"step {step + 1} from t = {t:.6g} (h = {h:.3g}), in '{name}'" + (f", sample {sample}" if batched else "")
    return (
        f"flagged: radau's local error estimate at the same h and stages, on the PINN's steps, reaches {value:.3g} "
        f"of the solution's size at {where}, beyond estimate_bound = {bound:g}: the Radau solution the PINN is "
        "certified against keeps fewer digits than the bound asks, and so does the PINN; take a smaller h, or "
        "method='radau' with rtol=..."
    )


def torch_threads_now() -> int:
    import torch

    return torch.get_num_threads()
