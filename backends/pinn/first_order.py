"""The first-order optimizers of one segment's networks: Adam (eager, or one captured CUDA graph per
iteration on a GPU) and L-BFGS, on the squared Radau residual.  Each takes a
:class:`~daemodel.backends.pinn.train.SegmentTrainer` (the network, the loss, the settings and the
loss-term checks) and a :class:`~daemodel.backends.pinn.train.Segment`, and returns ``(iterations,
None)`` as the trainer's methods do (None: the trainer evaluates the final residuals itself).
Levenberg-Marquardt, the default, is the trainer's own (:mod:`.train`).
"""

from __future__ import annotations

import dataclasses
import time

import torch

# L-BFGS runs in chunks of this many iterations between tolerance checks.
LBFGS_CHUNK = 20
# Progress is reported at most this often (seconds).
REPORT_SECONDS = 0.2
# Adam on a GPU (one CUDA graph per iteration): eager iterations before the capture, and
# iterations between two reads of the loss terms.
GRAPH_WARMUP = 3
GRAPH_CHECK_EVERY = 100


def adam(trainer, segment) -> tuple:
    """Adam on ``trainer``'s network: one captured CUDA graph per iteration on a GPU
    (:func:`adam_graphed`), else eager (:func:`adam_eager`).  Returns ``(iterations, None)``."""
    return adam_graphed(trainer, segment) if segment.x.is_cuda else adam_eager(trainer, segment)


def adam_eager(trainer, segment) -> tuple:
    """Adam, one iteration after another, the loss terms checked at every one."""
    optimizer = torch.optim.Adam(trainer.net.parameters(), lr=trainer.config.learning_rate)
    start, last_report = None, 0.0
    for iteration in range(trainer.config.iterations):
        optimizer.zero_grad()
        residuals = trainer.residuals(segment)
        r = trainer.loss.vector(residuals, segment.x.shape[0])
        loss = (r**2).sum()
        terms = trainer.check_terms(segment, residuals, iteration, start)
        start = trainer.weighted(terms) if start is None else start
        if time.perf_counter() - last_report > REPORT_SECONDS:
            trainer.report(iteration, terms)
            last_report = time.perf_counter()
        if trainer.reached_tol(residuals):
            return iteration, None
        loss.backward()
        optimizer.param_groups[0]["lr"] = trainer.config.learning_rate_at(iteration)
        optimizer.step()
    return trainer.config.iterations, None


def adam_graphed(trainer, segment) -> tuple:
    """Adam on a GPU, each iteration (forward, loss, backward, step) replayed as one captured
    CUDA graph.  A segment's networks see one or a few inputs, so eager Adam is bound by
    kernel launches (hundreds per iteration); the graph launches them at once.  The loss terms
    are read, checked and compared with ``tol`` every :data:`GRAPH_CHECK_EVERY` iterations,
    at the parameters reached so far, by one more evaluation outside the graph."""
    params = list(trainer.net.parameters())
    N, device = segment.x.shape[0], segment.x.device
    scheduled = trainer.config.schedule != "constant"
    # a scheduled rate lives on the device, set before each replay (a float is baked into the graph)
    rate = torch.tensor(trainer.config.learning_rate, dtype=segment.x.dtype, device=device) if scheduled else None
    optimizer = torch.optim.Adam(params, lr=rate if scheduled else trainer.config.learning_rate, capturable=True)
    # t and h as tensors on the device: a Python float would be copied from the host inside the graph
    graphed = dataclasses.replace(
        segment,
        t=torch.tensor(segment.t, dtype=segment.x.dtype, device=device),
        h=torch.tensor(segment.h, dtype=segment.x.dtype, device=device),
    )

    def iteration():
        r = trainer.loss.vector(trainer.residuals(graphed), N)
        (r**2).sum().backward()
        optimizer.step()

    def check(done: int, start):
        with torch.no_grad():
            residuals = trainer.residuals(segment)
        terms = trainer.check_terms(segment, residuals, done, start)
        trainer.report(done, terms)
        return terms, trainer.reached_tol(residuals)

    total = trainer.config.iterations
    terms, finished = check(0, None)
    start = trainer.weighted(terms)
    if finished or total == 0:
        return 0, None
    warmup = min(GRAPH_WARMUP, total)  # eager iterations on a side stream: Adam's state, autograd's buffers
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for k in range(warmup):
            if scheduled:
                rate.fill_(trainer.config.learning_rate_at(k))
            optimizer.zero_grad(set_to_none=True)
            iteration()
    torch.cuda.current_stream(device).wait_stream(side)
    done = warmup
    graph = torch.cuda.CUDAGraph()
    optimizer.zero_grad(set_to_none=True)  # the graph's backward allocates .grad in its own pool
    with torch.cuda.graph(graph):
        iteration()
    while done < total:
        for _ in range(min(GRAPH_CHECK_EVERY - done % GRAPH_CHECK_EVERY, total - done)):
            if scheduled:
                rate.fill_(trainer.config.learning_rate_at(done))
            graph.replay()
            done += 1
        terms, finished = check(done, start)
        if finished:
            return done, None
    return done, None


def lbfgs(trainer, segment) -> tuple:
    """L-BFGS with a strong-Wolfe line search, in chunks of :data:`LBFGS_CHUNK` iterations between
    tolerance checks; it stops where an L-BFGS call makes no progress (the loss flat to rounding)."""
    optimizer = torch.optim.LBFGS(
        trainer.net.parameters(),
        lr=trainer.config.learning_rate,
        max_iter=LBFGS_CHUNK,
        history_size=50,
        tolerance_grad=0.0,
        tolerance_change=0.0,
        line_search_fn="strong_wolfe",
    )
    start = None

    def closure():
        optimizer.zero_grad()
        r = trainer.residual_vector(segment, trainer.net(segment.x))
        loss = (r**2).sum()
        loss.backward()
        return loss

    done = 0
    while done < trainer.config.iterations:
        with torch.no_grad():
            residuals = trainer.residuals(segment)
        terms = trainer.check_terms(segment, residuals, done, start)
        start = trainer.weighted(terms) if start is None else start
        trainer.report(done, terms)
        if trainer.reached_tol(residuals):
            return done, None
        before = optimizer.state[optimizer._params[0]].get("n_iter", 0)
        optimizer.step(closure)
        after = optimizer.state[optimizer._params[0]].get("n_iter", 0)
        if after == before:  # L-BFGS made no progress: the loss is flat to rounding
            break
        done += after - before
    return done, None
