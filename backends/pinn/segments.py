"""The segments in time: one network per segment of the grid, trained one after another
(each from its predecessor's prediction) or independently from known start values, as tasks of
an executor (local or Ray), and the default h's segment count from a radau pre-solve.  Uses
the trainer (:mod:`.train`); builds no Solution (:mod:`.backend` and :mod:`.surrogate` do).
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from daemodel.backends.pinn.train import Segment, SegmentTrainer

from daemodel.errors import InvalidOptionError, ResourceLimitError, SolverError, TimeLimitError
from daemodel.tableau import radau_iia

# The highest index the PINN solves directly: its loss is the index-2 Radau residual (a model of
# index 3 is reduced first).
MAX_INDEX = 2
# The pre-solve that sets the default h: adaptive radau with the PINN's default tableau (Radau IIA, 3
# stages, order 5) at rtol = atol = this, about the accuracy the fast mode certifies; its mean accepted
# step becomes the segment length (the pendulum on [0, 1]: about 16 steps, h = 0.0625).  It was scipy's
# Radau, until radau's first step was probed (issue 43): scipy's took 316 s on Fekete's 160 unknowns
# (its index-reduced ODE), radau 0.5 s.
PRESOLVE_RTOL = 1e-6
PRESOLVE_STAGES = 3
PRESOLVE = f"an adaptive radau solve (stages = {PRESOLVE_STAGES}) at rtol = {PRESOLVE_RTOL:g}"
# Segments of a default h at most: a long span with a short stiff transient (a CSTR on [0, 200])
# trains this many, not one per step of the transient; as the bench's bench_max_steps.
DEFAULT_MAX_SEGMENTS = 200


def resolve_model(model, caller: str):
    """A CompiledDAE of index at most 2 from a Model or a CompiledDAE."""
    from daemodel.compiling.compiler import as_compiled

    model = as_compiled(model, caller)
    return model.reduced(MAX_INDEX) if model.index > MAX_INDEX else model


def segment_steps(grid) -> list[tuple[float, float]]:
    """``(t, h)`` of every segment of ``grid``: the one place a segment's length is taken."""
    return [(float(grid[k]), float(grid[k + 1] - grid[k])) for k in range(len(grid) - 1)]


# Copies of one segment's parameters that training holds beside the kept networks of every segment:
# measured with LM on the pendulum (width 1000 and 2000, depth 2 and 3, 1 and 3 segments), the
# peak resident memory grew by (segments + 2) times the parameters; L-BFGS adds its 50 pairs of
# history, Adam its two moments and the gradient.
TRAINING_COPIES = {"lm": 2, "lbfgs": 2 + 2 * 50, "adam": 2 + 3}
# With N > 1 inputs per set of networks (samples > 1, or a shared batch), LM's Gram matrix of the
# hidden layers (K, N w, N w) dominates: measured 10.4 GB at N = 8, w = 1000, K = 6 (the pendulum),
# 3.4 times K (N w)^2 doubles.
GRAM_COPIES = 4
# The Newton corrections that LM fits are solved from the Radau stage system, dense: its Jacobian
# ((s+1)(n+m) + m rows, (s+1)(n+m) columns) per input, and its factorisations.  Measured on the
# reaction-diffusion family (s = 3, one sample) at 400 and 800 unknowns: the peak resident memory grew
# by 16.9 and 16.1 times one such matrix (1.5 GB at 800 unknowns; 10^4 unknowns would need 200 GB).
STAGE_SYSTEM_COPIES = 16


def network_memory(compiled, config, inputs: int, batch: int, segments: int) -> dict:
    """Bytes that training ``segments`` segments of networks with ``inputs`` inputs for ``batch``
    samples takes, by part, computed before any network exists: the trained networks of every
    segment, training's working copies of one segment's (:data:`TRAINING_COPIES`), and with more
    than one input per set of networks, LM's Gram matrices (:data:`GRAM_COPIES`) or its normal
    matrices in parameter space, whichever it solves in (see ``SegmentTrainer._normal_system``)."""
    from daemodel.backends.pinn.network import output_sizes, parameter_count_of

    itemsize = 4 if config.dtype == "float32" else 8
    copies = copies_for(config, batch)
    P = parameter_count_of(inputs, len(compiled.states), len(compiled.algebraics), config, copies)
    parts = {
        f"the networks of {segments} segment(s)": segments * P * itemsize,
        "training's working copies": TRAINING_COPIES[config.optimizer] * P * itemsize,
    }
    rows = batch * config.samples // copies  # inputs each set of networks sees
    D, m = len(compiled.states) + len(compiled.algebraics), len(compiled.algebraics)
    R, U = (config.stages + 1) * D + m, (config.stages + 1) * D
    # (every input's stage system at once, (batch samples, R, U): independent networks' too)
    parts["the Radau stage system, dense"] = STAGE_SYSTEM_COPIES * max(batch * config.samples, 1) * R * U * itemsize
    if config.optimizer == "lm" and rows > 1:
        count, out = output_sizes(len(compiled.states), len(compiled.algebraics), config.stages, config.architecture)
        K, w = count * copies, config.width
        if rows * out <= P // K:
            parts["LM's Gram matrices"] = GRAM_COPIES * K * (rows * w) ** 2 * itemsize
        else:
            parts["LM's normal matrices"] = K * (P // K) ** 2 * itemsize
    return parts


def check_network_memory(compiled, config, inputs: int, batch: int, segments: int, at_least: bool = False) -> None:
    """A :class:`ResourceLimitError` naming width and depth when the networks and their training
    (:func:`network_memory`) would need more than the memory allowed
    (:func:`daemodel.files.memory_limit`), before anything is allocated.  ``at_least``: ``segments``
    is a lower bound on the segments (the grid is not known yet), and the message says "at least"."""
    from daemodel.files import MEMORY_LIMIT_VARIABLE, memory_limit

    parts = network_memory(compiled, config, inputs, batch, segments)
    limit, total = memory_limit(), sum(parts.values())
    if total <= limit:
        return
    need = f"{'at least ' if at_least else ''}{total / 2**30:.3g} GiB"
    itemised = ", ".join(f"{name} {size / 2**30:.3g} GiB" for name, size in parts.items())
    fewer = " or fewer samples" if any(name.startswith("LM's") for name in parts) else ""
    stage_system = parts["the Radau stage system, dense"]
    # (the model's size, more than the networks', is what does not fit; or the stage system alone does not:
    # at 10^5 unknowns 17 segments' networks outweighed it, and the message said to take a smaller width)
    if stage_system >= max(parts.values()) or stage_system > limit:
        D, inputs_all = len(compiled.states) + len(compiled.algebraics), batch * config.samples
        many = f" with {inputs_all} training inputs" if inputs_all > 1 else ""
        raise ResourceLimitError(
            f"pinn: a model of {D} unknowns{many} is too large for the PINN: its Levenberg-Marquardt solves the "
            f"Radau stage system of {config.stages} stages densely{' for every input at once' if many else ''}, "
            f"which would need {need} to train ({itemised}), more than the {limit / 2**30:.3g} GiB "
            f"allowed (set {MEMORY_LIMIT_VARIABLE} to change it); solve it with method='radau' (sparse), or take "
            f"fewer stages{' or fewer samples' if many else ''}"
        )
    raise ResourceLimitError(
        f"pinn: networks of width = {config.width} and depth = {config.depth} for {batch} sample(s) of "
        f"{len(compiled.states) + len(compiled.algebraics)} unknowns would need {need} to train "
        f"({itemised}), more than the {limit / 2**30:.3g} GiB allowed (set {MEMORY_LIMIT_VARIABLE}, e.g. '64G', "
        f"to change it); take a smaller width or depth{fewer} (PINNConfig's defaults: width = 20, depth = 2)"
    )


def segment_grid(t_span, h: float, *, strict: bool = False) -> np.ndarray:
    """The segment boundaries of a solve over ``t_span``: ``t0, t0 + h, ...`` with the last segment
    shortened to end at t1 (:func:`~daemodel.backends.grids.fixed_grid`), and one segment of the
    span's length where the span is shorter than ``h``: ``config.h`` is a segment length, and a piece
    between two events or breakpoints may be shorter than it.  ``strict``: ``h`` was given as the
    solve's own ``h=`` option, which, as radau's, may not exceed the interval
    (:class:`~daemodel.errors.StepSizeError`)."""
    from daemodel.backends.grids import fixed_grid

    t0, t1 = t_span
    return fixed_grid(t_span, h if strict else min(h, t1 - t0))


def default_segments(compiled, t_span, start, max_segments: int) -> tuple[int, int, float]:
    """The segment count of the default h over ``t_span``: the accepted steps of an adaptive
    radau solve with the PINN's tableau (3 stages) at :data:`PRESOLVE_RTOL`, on casadi's virtual machine
    (no compile in the setup), at least one and at most ``max_segments``.

    Returns
    -------
    segments : int
    steps : int
        The pre-solve's accepted steps (a batch's samples step together, on one h).
    seconds : float
        The pre-solve's time (the PINN counts it in its setup).

    Raises
    ------
    ConvergenceError, StepLimitError
        The pre-solve failed: the message says so and how to skip it (give ``h``).
    """
    from daemodel.backends.radau.backend import RadauBackend
    from daemodel.backends.radau.options import RadauOptions

    began = time.perf_counter()
    options = RadauOptions(
        rtol=PRESOLVE_RTOL, atol=PRESOLVE_RTOL, stages=PRESOLVE_STAGES, jit=False, t_eval=list(t_span),
        dense_output=False,
    )  # fmt: skip
    try:
        solution = RadauBackend().solve(compiled, tuple(t_span), start, options)
    except TimeLimitError:  # (the time ran out: not a pre-solve that failed)
        raise
    except SolverError as error:
        raise type(error)(
            f"pinn: the default h comes from {PRESOLVE}, which failed ({error}); give the segment length, e.g. "
            "h=0.05, to train without it"
        ) from error
    steps = int(solution.stats["steps"])
    # (radau steps a batch's samples together: its steps are the batch's, not a sum over the samples, which
    # scipy's pre-solve gave and which was divided by the samples here, 4 segments for 4 pendulums, not 16)
    segments = min(max(1, steps), max_segments)
    return segments, steps, time.perf_counter() - began


def make_network(compiled, config, inputs: int, segment: int, copies: int = 1):
    """A fresh network for ``segment`` (``copies`` independent ones for a batch), seeded from
    ``config.seed`` and the segment number."""
    from daemodel.backends.pinn.network import RadauNetwork

    generator = torch.Generator().manual_seed(config.seed * 100_003 + segment)
    net = RadauNetwork(inputs, len(compiled.states), len(compiled.algebraics), config, generator, copies)
    return net.to(config.device)


def fresh_network(compiled, config, inputs: torch.Tensor, z: torch.Tensor, segment: int, copies: int):
    """A new network for ``segment`` with its inputs normalised on ``inputs`` (N, d) and, in the
    increment form, at rest on their start values (``z`` (N, m): the algebraic ones)."""
    net = make_network(compiled, config, inputs.shape[1], segment, copies)
    net.normalise(inputs)
    if config.increment:
        net.start_at_rest(inputs, z)
    return net


def extrapolated_start(previous, y_prev, z_prev, h_prev: float, h: float, c):
    """Radau's start guess for a step of length ``h`` that follows a step of ``h_prev``: that step's
    collocation polynomial (through ``(0, (y_prev, z_prev))`` and its stages ``previous.Y``,
    ``previous.Z`` at the nodes ``c``, a step of ``h_prev``) extrapolated to this step's nodes.
    Returns the stage values ``(Y, Z)``, (B, s, n) and (B, s, m)."""
    from daemodel.collocation import extrapolation_matrix

    L = torch.as_tensor(extrapolation_matrix(c, h / h_prev), dtype=y_prev.dtype, device=y_prev.device)
    Y = L @ torch.cat([y_prev[:, None, :], previous.Y], dim=1)  # (s, s+1) @ (B, s+1, n)
    Z = L @ torch.cat([z_prev[:, None, :], previous.Z], dim=1)
    return Y, Z


def copies_for(config, batch: int) -> int:
    """Independent network copies for a batch of ``batch`` samples: one each with
    ``batch="independent"`` (1 for a single trajectory), else 1 shared set."""
    if config.batch != "independent" or batch == 1:
        return 1
    if config.samples > 1:
        raise InvalidOptionError(
            f"samples = {config.samples} trains each network on a box around its start, which independent networks "
            f"for a batch of {batch} do not have: use batch='shared' (one set of networks over the batch), or samples=1"
        )
    return batch


def make_loss(compiled, config):
    from daemodel.backends.pinn.loss import CasadiKernel, RadauLoss

    dtype = getattr(torch, config.dtype)
    functions = compiled.torch_functions(dtype=dtype, device=config.device)
    tableau = radau_iia(config.stages)
    # one trajectory in float64 on the CPU: LM's residuals and Jacobians from casadi's kernels
    kernel = CasadiKernel(compiled, tableau) if config.dtype == "float64" and config.device == "cpu" else None
    loss = RadauLoss(functions, tableau, config, dtype, config.device, kernel)
    loss.names = (compiled.state_names, compiled.constraint_names, compiled.algebraic_names)
    return loss


def training_inputs(x: torch.Tensor, p: torch.Tensor, n: int, config, generator: torch.Generator):
    """A segment's training inputs and their parameter vectors: the rows of ``x`` (B, d), each
    followed by ``samples - 1`` points uniform in a box of half-width ``radius * max(1, |y|)``
    around its states (parameters are not perturbed)."""
    if config.samples == 1:
        return x, p
    B, d = x.shape
    noise = torch.rand(B, config.samples - 1, n, generator=generator, dtype=torch.float64).to(x) * 2 - 1
    half = config.radius * torch.clamp(x[:, None, :n].abs(), min=1.0)
    extra = x[:, None, :].repeat(1, config.samples - 1, 1)
    extra[..., :n] = extra[..., :n] + half * noise
    # extra rows are grouped by their source row, as are their parameter vectors
    return torch.cat([x, extra.reshape(-1, d)]), torch.cat([p, p.repeat_interleave(config.samples - 1, dim=0)])


class Progress:
    """A tqdm bar over segments whose postfix shows the iteration and the loss terms."""

    def __init__(self, total: int, enabled: bool, label: str):
        from daemodel.backends.progress import LOG_PROGRESS_SECONDS, progress_bar, stderr_is_terminal

        self.bar = progress_bar(total, label, "segment") if enabled else None
        # a terminal shows every report in place; a log gets one line every LOG_PROGRESS_SECONDS
        self.every = 0.0 if stderr_is_terminal() else LOG_PROGRESS_SECONDS
        self.shown = -math.inf  # perf_counter of the last redraw
        self.segment = 0

    def report(self, iteration: int, terms: dict) -> None:
        if self.bar is not None:
            shown = " ".join(f"{k}={v:.1e}" for k, v in terms.items())
            self.bar.set_postfix_str(f"seg {self.segment + 1} it {iteration} {shown}", refresh=False)
            if time.perf_counter() - self.shown >= self.every:
                self.bar.refresh()
                self.shown = time.perf_counter()

    def advance(self) -> None:
        self.segment += 1
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _starts(compiled, config, previous, inputs, z, k: int, copies: int, target):
    """Segment k's start networks in order of preference, each with its raw outputs at ``inputs``
    and the forward pass's intermediates where known (else None), each made only where the one
    before it is refused: with ``target`` (the predictor's raw outputs), a copy of ``previous``
    (warm) or a fresh network with its output biases shifted onto them; a copy of ``previous``."""

    def begin():
        if previous is None:
            return fresh_network(compiled, config, inputs, z, k, copies)
        net = previous.clone()
        net.normalise(inputs)
        return net

    if target is not None:
        predicted = begin()
        yield predicted, predicted.start_at(inputs, target)
    if previous is not None:
        yield begin(), None


def fit_sequential(compiled, grid, x0: torch.Tensor, p: torch.Tensor, z0: torch.Tensor, config, progress: Progress):
    """Train the segments one after the other (time-domain decomposition).

    Segment k trains on the states its predecessor predicted (``x0`` (B, d) for the first), plus
    the box samples of ``config``; its predicted ``y_{n+1}`` becomes segment k+1's input.  A fresh
    network starts at rest on the consistent algebraic values ``z0`` (B, m) (the previous
    segment's predicted ``z_{n+1}`` later on); with ``warm_start`` a segment starts from a copy
    of the previous one's network, and with ``predictor`` (one input per set of networks) its
    output biases then put its stages on the previous segment's extrapolated collocation
    polynomial (:func:`extrapolated_start`).

    Returns
    -------
    networks : list of RadauNetwork
    stats : list of SegmentStats
    """
    n = len(compiled.states)
    check_network_memory(compiled, config, x0.shape[1], x0.shape[0], len(grid) - 1)
    loss = make_loss(compiled, config)
    generator = torch.Generator().manual_seed(config.seed)
    copies = copies_for(config, x0.shape[0])
    # the predictor sets each network's outputs at its input: one input per set of networks
    predict = config.predictor and x0.shape[0] == copies and config.samples == 1
    c = radau_iia(config.stages).c
    x, z, networks, stats, previous = x0, z0, [], [], None
    for k, (t, h) in enumerate(segment_steps(grid)):
        inputs, samples_p = training_inputs(x, p, n, config, generator)
        segment = Segment(index=k, t=t, h=h, x=inputs, p=samples_p)
        # the start, in order of preference: predicted, warm, fresh (at rest in the increment
        # form); each but the last only where its predictions keep f and g finite (akzo-nobel's
        # sqrt: the previous segment's slopes, or the extrapolation, can leave the domain)
        warm = bool(networks) and config.warm_start
        target = None  # the predictor's raw outputs: the previous collocation polynomial, extrapolated
        if predict and networks:
            target = networks[-1].raw_outputs(*extrapolated_start(*previous, h, c), x[:, :n], h)
        candidates = _starts(compiled, config, networks[-1] if warm else None, inputs, z, k, copies, target)
        report = progress.report if progress.bar is not None else None
        trainers = ((SegmentTrainer(net, loss, config, report), raw) for net, raw in candidates)
        trainer = next((trainer for trainer, raw in trainers if trainer.finite_start(segment, raw)), None)
        if trainer is None:
            trainer = SegmentTrainer(fresh_network(compiled, config, inputs, z, k, copies), loss, config, report)
        net = trainer.net
        stats.append(trainer.train(segment))
        out = trainer.predict(x, h)  # bit for bit what the rollout will evaluate
        previous = (out, x[:, :n], z, h)
        x, z = torch.cat([out.y_end, x[:, n:]], dim=1), out.z_end
        networks.append(net)
        progress.advance()
    return networks, stats


def train_segments(compiled, config, grid, y, z, p, input_columns, progress: bool, label: str):
    """:func:`fit_sequential` from numpy arrays: the states ``y`` (B, n), their consistent
    algebraic values ``z`` (B, m) and parameters ``p`` (B, k), whose columns ``input_columns``
    are network inputs after the states; with a progress bar when ``progress``."""
    dtype = getattr(torch, config.dtype)

    def tensor(array):
        return torch.as_tensor(np.array(array, dtype=float), dtype=dtype, device=config.device)

    bar = Progress(len(grid) - 1, progress, label)
    try:
        return fit_sequential(
            compiled, grid, tensor(np.concatenate([y, p[:, input_columns]], axis=1)), tensor(p), tensor(z), config, bar
        )
    finally:
        bar.close()


def fit_one(shared: tuple, k: int, t: float, h: float, x, z) -> dict:
    """Train segment k from the known inputs ``x`` (B, d) and algebraic values ``z`` (B, m): an
    executor task, plain data in and out.  ``shared`` is (compiled, config, p)."""
    compiled, config, p = shared
    dtype = getattr(torch, config.dtype)
    x, z, p = (torch.as_tensor(np.array(a), dtype=dtype, device=config.device) for a in (x, z, p))
    generator = torch.Generator().manual_seed(config.seed * 100_003 + k)
    inputs, samples_p = training_inputs(x, p, len(compiled.states), config, generator)
    net = fresh_network(compiled, config, inputs, z, k, copies_for(config, x.shape[0]))
    segment = Segment(k, t, h, inputs, samples_p)
    stats = SegmentTrainer(net, make_loss(compiled, config), config).train(segment)
    return {"state": {name: value.cpu() for name, value in net.state_dict().items()}, "stats": stats}


def fit_parallel(
    compiled, grid, starts, algebraics, p, config, progress: Progress, executor="local", workers=None, address=None
):
    """Train every segment independently on known start values, as tasks of ``executor``
    (:func:`daemodel.executors.run_tasks`: one after another here, or in parallel on Ray).

    Parameters
    ----------
    starts : ndarray, shape (segments, B, d)
        Network inputs at each segment's start (from a classical solve or an earlier sweep).
    algebraics : ndarray, shape (segments, B, m)
        The consistent algebraic values at each segment's start.

    Returns
    -------
    networks, stats, peak_memory_mb
        The last: each Ray task's peak resident memory (empty for the local executor).
    """
    from daemodel.executors import run_tasks

    check_network_memory(compiled, config, starts.shape[2], starts.shape[1], len(grid) - 1)
    tasks = [(k, t, h, starts[k], algebraics[k]) for k, (t, h) in enumerate(segment_steps(grid))]
    results = run_tasks(
        fit_one,
        (compiled, config, np.asarray(p)),
        tasks,
        executor=executor,
        workers=workers,
        address=address,
        label="pinn",
        on_result=lambda *_: progress.advance(),
    )
    networks = []
    for k, result in enumerate(results):
        net = make_network(compiled, config, starts.shape[2], k, copies_for(config, starts.shape[1]))
        net.load_state_dict(result["state"])
        networks.append(net)
    memory = [result["peak_memory_mb"] for result in results if "peak_memory_mb" in result]
    return networks, [result["stats"] for result in results], memory
