"""A neural method plugged into daemodel from outside: one network over the whole span.

Another kind of method than daemodel's Radau-PINN (which fits Radau stage values segment by
segment): one network ``N(s)``, ``s = (t - t0) / (t1 - t0)`` in [0, 1], gives the whole trajectory,
trained on the differential equations at collocation points, in the manner of DAE-PINN (Moya & Lin,
"DAE-PINN: a physics-informed neural network model for simulating differential-algebraic equations
with application to power networks", Neural Computing and Applications, 2023) with the constraints
built into the output as far as the structure allows:

* the initial values are hard: ``y(s) = y0 + s * Ny(s)``, ``z(s) = z0 + s * Nz(s)``;
* the constraints that do not involve z (index 2: ``g(t, y) = 0``) are a hard output layer: each
  is solved for one state (chosen at t0 by pivoting on ``dg/dy``) by :data:`NEWTON_STEPS` Newton
  steps, the network giving the others, so every output keeps them to rounding;
* the constraints that involve z (index 1) are a penalty in the loss.

The loss is the mean square of ``dy/ds - (t1 - t0) f(t, y, z)``, ``dy/ds`` carried forward through
the network's layers and, for the solved states, by the implicit function theorem; it is minimised
by Levenberg-Marquardt (the residuals' Jacobian by ``torch.func.jacrev``), in float64.

Accuracy, honestly: after training, the network's values at the output times are compared with an
adaptive radau solve at ``check_rtol`` (on the solve clock: it is the method's error estimate); the
run is ``"success"`` only when that distance, relative to ``1 + max|u|`` of each variable, is within
``tol``, else ``"flagged: ..."`` with the estimate and an :class:`AccuracyWarning`.

The backend keeps daemodel's contract (``daemodel.backends.base``, docs/methods.md#writing-a-method)
and uses daemodel's public API only: no change to daemodel is needed to run it through ``dm.solve``
and ``dm.compare``.  Installed (``pip install examples/plugin_method``), its pyproject's entry point
makes it the method ``"whole-span-pinn"``; without installing, ``dm.methods.register`` does.

Run: python examples/plugin_method/whole_span_pinn.py [--quick]
"""

from __future__ import annotations

import dataclasses
import itertools
import sys
import time
import warnings
from typing import ClassVar

import numpy as np
from daemodel.backends.base import AbstractBackend, make_solution
from daemodel.backends.checks import check_number
from daemodel.backends.grids import output_times

import daemodel as dm
from daemodel.compiling.compiled import SYMBOLIC_JACOBIAN_MAX_ENTRIES
from daemodel.errors import ConvergenceError, InvalidOptionError, UnsupportedModelError

NAME = "whole-span-pinn"
# Newton steps of the hard constraint layer: one solves a constraint linear in its state (Hessenberg's,
# the pendulum's), and from a network output near the constraints each further step squares the residual.
NEWTON_STEPS = 3
# Penalty weight of the constraints that involve z (index 1), against the equations' mean square.
PENALTY = 10.0
# Levenberg-Marquardt: the damping starts at LM_DAMPING (times the diagonal of J^T J), is divided
# by 3 after a step that lowers the loss and multiplied by 4 after one that does not; training ends
# when it passes LM_MAX_DAMPING (no step helps) or the loss falls below LOSS_FLOOR (rounding).
LM_DAMPING, LM_MIN_DAMPING, LM_MAX_DAMPING, LOSS_FLOOR = 1e-3, 1e-12, 1e10, 1e-28
# Fewest collocation points.
MIN_POINTS = 8
# Output times without t_eval.
DEFAULT_OUTPUTS = 101


class AccuracyWarning(UserWarning):
    """A whole-span network whose error estimate exceeds its ``tol``: the values are flagged."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class WholeSpanOptions:
    """Options of ``method="whole-span-pinn"``.

    Attributes
    ----------
    width, depth : int
        Hidden width and number of hidden layers (tanh).
    points : int
        Collocation points over the span (Chebyshev points: denser near the ends).
    iterations : int
        Most Levenberg-Marquardt iterations (the training loop's bound).
    tol : float
        The stated accuracy: the largest error of a variable relative to ``1 + max|u|`` of it.
    check_rtol : float
        Tolerance of the radau solve the estimate is measured against (below ``tol``).
    seed : int
        Seed of the network's initial weights.
    t_eval : array-like, optional
        Output times (default 101 across the span).
    """

    width: int = 20
    depth: int = 2
    points: int = 48
    iterations: int = 150
    tol: float = 1e-3
    check_rtol: float = 1e-10
    seed: int = 0
    t_eval: object = None

    def __post_init__(self):
        for name in ("width", "depth", "points", "iterations"):
            object.__setattr__(self, name, check_number(name, getattr(self, name), integer=True))
        object.__setattr__(self, "seed", check_number("seed", self.seed, integer=True, positive=False))
        if self.seed < 0:
            raise InvalidOptionError(f"seed must be a non-negative integer; got {self.seed}")
        if self.points < MIN_POINTS:
            raise InvalidOptionError(
                f"points must be at least {MIN_POINTS} (collocation points over the span); got {self.points}"
            )
        for name in ("tol", "check_rtol"):
            object.__setattr__(self, name, check_number(name, getattr(self, name)))
        if not self.check_rtol < self.tol:
            raise InvalidOptionError(
                f"check_rtol = {self.check_rtol:g} must be below tol = {self.tol:g}: the estimate's reference must be "
                "more accurate than what it checks"
            )


class WholeSpanPINN(AbstractBackend):
    """One network over the whole span, the index-2 constraints as a hard output layer."""

    name: ClassVar[str] = NAME
    Options: ClassVar[type] = WholeSpanOptions
    max_index: ClassVar[int] = 2
    # One network per call over [t0, t1]: daemodel's piece-by-piece solve of events and switches
    # would train one per trial solve; such models are refused (UnsupportedModelError).
    solves_pieces: ClassVar[bool] = False

    def describe(self, options) -> str:
        return f"{NAME} (width {options.width}, depth {options.depth}, {options.iterations} iterations)"

    def work_precision(self, t_span, points, steps=10) -> list[dict]:
        """Longer training from cheap to accurate: 25, 50, 100, ... iterations."""
        return [{"iterations": 25 * 2**k} for k in range(points)]

    def solve(self, compiled, t_span, start, options):
        import torch

        began = time.perf_counter()
        t0, t1 = (float(v) for v in t_span)
        times = output_times(options.t_eval, t_span, np.linspace(t0, t1, DEFAULT_OUTPUTS))
        tf = compiled.torch_functions()
        layer = ConstraintLayer(compiled, tf, start)
        networks, trained = [], []
        for b in range(len(start.p)):  # (a batch: one network per sample)
            torch.manual_seed(options.seed)
            net = Trajectory(compiled, start, b, t_span, layer, options)
            trained.append(train(net, tf, options))
            networks.append(net)
        trained_at = time.perf_counter()

        s = torch.as_tensor((times - t0) / (t1 - t0), dtype=torch.float64)
        with torch.no_grad():
            values = np.stack([torch.cat(net(s), dim=-1).numpy() for net in networks])  # (B, T, n+m)
        if not np.all(np.isfinite(values)):
            raise ConvergenceError(f"{NAME}: the trained network gives non-finite values; train with another seed")
        estimate, where = error_estimate(compiled, t_span, start, times, values, options.check_rtol)
        if estimate <= options.tol:
            status = "success"
        else:
            status = (
                f"flagged: {NAME}'s error estimate (its distance to radau at rtol = {options.check_rtol:g}) reaches "
                f"{estimate:.3g} of the solution's size at {where}, beyond tol = {options.tol:g}: train longer "
                "(iterations=...), or a wider network (width=...)"
            )
            warnings.warn(status, AccuracyWarning, stacklevel=user_level())
        stats = {
            "iterations": [r["iterations"] for r in trained],
            "final_loss": [r["loss"] for r in trained],
            "error_estimate": estimate,
            "training_seconds": trained_at - began,
        }
        checked = time.perf_counter()
        return make_solution(
            self,
            compiled,
            start,
            options,
            times,
            values,
            solve_time=checked - trained_at,
            stats=stats,
            status=status,
            setup_time=trained_at - began,
        )


def user_level() -> int:
    """The ``stacklevel`` of the first frame outside this module and daemodel: the user's call."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] in ("daemodel", __name__):
        frame, level = frame.f_back, level + 1
    return level


class ConstraintLayer:
    """The hard output layer: the constraints that do not involve z solved for one state each.

    The states solved for are chosen at t0 by Gaussian elimination with complete pivoting on
    ``G = dg/dy`` (the structure allows it where ``dg/dy_d`` stays nonsingular along the solution);
    the other states are the network's.  Newton gives ``y_d`` from ``g(t, y_f, y_d) = 0`` and the
    implicit function theorem its derivative, ``dy_d = -g_{y_d}^-1 (g_t + g_{y_f} dy_f)``.
    """

    def __init__(self, compiled, tf, start):
        n, m = len(compiled.states), len(compiled.algebraics)
        if tf.jacobian is None:
            entries = len(compiled.jacobian_pattern()[0])
            raise UnsupportedModelError(
                f"{NAME}: model '{compiled.name}' has no symbolic Jacobian, which the constraint layer needs "
                f"(daemodel writes one for at most {SYMBOLIC_JACOBIAN_MAX_ENTRIES} nonzeros, this one has "
                f"{entries}, and none where an equation's derivative is not generated, e.g. of Abs): use radau"
            )
        rows, cols = (np.asarray(a) for a in tf.jacobian_pattern)
        in_g = rows >= n
        with_z = {int(r) - n for r, c in zip(rows[in_g], cols[in_g], strict=True) if c >= n}
        self.hard = [i for i in range(m) if i not in with_z]  # index-2 constraints: solved for y_d
        self.soft = sorted(with_z)  # index-1 constraints: penalised
        self.entries = [
            (k, int(r) - n, int(c)) for k, (r, c) in enumerate(zip(rows, cols, strict=True)) if r >= n and c < n
        ]
        self.n, self.m, self.tf = n, m, tf
        self.on_time = any(compiled.t in c.free_symbols for c in compiled.g)
        self.dependent = self.choose(start) if self.hard else []
        self.free = [j for j in range(n) if j not in self.dependent]

    def gy(self, t, y, z, p):
        """``dg/dy`` of the hard constraints, (..., h, n)."""
        J = self.tf.jacobian(t, y, z, p)
        G = y.new_zeros((*y.shape[:-1], self.m, self.n))
        for k, i, j in self.entries:
            G[..., i, j] = J[..., k]
        return G[..., self.hard, :]

    def choose(self, start) -> list[int]:
        """One state per hard constraint: complete pivoting on ``dg/dy`` at t0 (sample 0)."""
        import torch

        y0, z0, p = (torch.as_tensor(np.array(a[0]), dtype=torch.float64) for a in (start.y0, start.z0, start.p))
        G = self.gy(torch.tensor(0.0, dtype=torch.float64), y0, z0, p).numpy().copy()
        chosen = []
        for _ in range(len(self.hard)):
            i, j = np.unravel_index(int(np.abs(G).argmax()), G.shape)
            if G[i, j] == 0:
                raise UnsupportedModelError(f"{NAME}: the constraints' dg/dy is singular at t0: no hard output layer")
            chosen.append(int(j))
            G = G - np.outer(G[:, j], G[i]) / G[i, j]
            G[i] = 0.0
        return chosen

    def complete(self, t, y, dy, z, p):
        """``(y, dy)`` with the dependent states solved from the hard constraints; ``dy`` may be None."""
        import torch

        if not self.hard:
            return y, dy
        hard, dep, free = (torch.tensor(a) for a in (self.hard, self.dependent, self.free))
        for _ in range(NEWTON_STEPS):
            G = self.gy(t, y, z, p)
            step = torch.linalg.solve(G[..., dep], self.tf.g(t, y, z, p)[..., hard].unsqueeze(-1)).squeeze(-1)
            y = y.index_add(-1, dep, -step)
        if dy is None:
            return y, None
        G = self.gy(t, y, z, p)
        rate = (G[..., free] @ dy[..., free].unsqueeze(-1)).squeeze(-1)
        if self.on_time:  # g_t, by forward-mode differentiation of g in t
            import torch.autograd.forward_ad as fwAD

            with fwAD.dual_level():
                g = self.tf.g(fwAD.make_dual(t, torch.ones_like(t)), y, z, p)
                rate = rate + fwAD.unpack_dual(g).tangent[..., hard]
        dy_dep = -torch.linalg.solve(G[..., dep], rate.unsqueeze(-1)).squeeze(-1)
        dy = dy.index_copy(-1, dep, dy_dep)
        return y, dy


class Trajectory:
    """``s -> (y (T, n), z (T, m))`` of one sample, and ``dy/ds``: the network (its derivative carried
    forward through the layers), the hard initial values and the constraint layer.  Its weights are
    one flat vector ``theta``, so that Levenberg-Marquardt can take the residuals' Jacobian in it."""

    def __init__(self, compiled, start, b, t_span, layer, options):
        import torch

        n, m = len(compiled.states), len(compiled.algebraics)
        sizes = [1, *([options.width] * options.depth), n + m]
        layers = [torch.nn.Linear(a, c, dtype=torch.float64) for a, c in itertools.pairwise(sizes)]
        weights = [q.detach() for layer in layers for q in (layer.weight, layer.bias)]
        self.shapes = [q.shape for q in weights]
        self.theta = torch.cat([q.reshape(-1) for q in weights])
        self.y0 = torch.tensor(start.y0[b], dtype=torch.float64)
        self.z0 = torch.tensor(start.z0[b], dtype=torch.float64)
        self.p = torch.tensor(start.p[b], dtype=torch.float64)
        self.scale = 1.0 + float(np.abs(start.y0[b]).max()) if n else 1.0
        self.t0, self.span = float(t_span[0]), float(t_span[1] - t_span[0])
        self.layer, self.n = layer, n

    def __call__(self, s, theta=None, derivative: bool = False):
        import torch

        theta = self.theta if theta is None else theta
        weights, at = [], 0
        for shape in self.shapes:
            size = int(np.prod(shape))
            weights.append(theta[at : at + size].reshape(shape))
            at += size
        x, dx = 2 * s.unsqueeze(-1) - 1, 2 * torch.ones_like(s).unsqueeze(-1)  # (the input in [-1, 1])
        for W, b in zip(weights[:-2:2], weights[1:-2:2], strict=True):
            x = torch.tanh(x @ W.T + b)
            dx = (1 - x * x) * (dx @ W.T)
        raw, draw = x @ weights[-2].T + weights[-1], dx @ weights[-2].T
        s = s.unsqueeze(-1)
        y = self.y0 + s * self.scale * raw[..., : self.n]
        dy = self.scale * (raw[..., : self.n] + s * draw[..., : self.n]) if derivative else None
        z = self.z0 + s * raw[..., self.n :]
        t = self.t0 + self.span * s.squeeze(-1)
        y, dy = self.layer.complete(t, y, dy, z, self.p)
        return (y, z, dy) if derivative else (y, z)


def train(net: Trajectory, tf, options) -> dict:
    """Levenberg-Marquardt on the residuals at Chebyshev points (the equations, scaled, and the
    penalised constraints); ``net.theta`` is left at the best weights.  The count and final loss."""
    import torch
    from torch.func import jacrev

    k = np.arange(options.points)
    s = torch.as_tensor(0.5 - 0.5 * np.cos(np.pi * (k + 0.5) / options.points), dtype=torch.float64)
    t = net.t0 + net.span * s
    soft = torch.tensor(net.layer.soft, dtype=torch.long)

    def residuals(theta):
        y, z, dy = net(s, theta, derivative=True)
        parts = [((dy - net.span * tf.f(t, y, z, net.p)) / net.scale).reshape(-1)]
        if len(soft):
            parts.append(PENALTY**0.5 * tf.g(t, y, z, net.p)[..., soft].reshape(-1))
        return torch.cat(parts) / len(s) ** 0.5

    theta, damping = net.theta, LM_DAMPING
    r = residuals(theta)
    loss = float(r @ r)
    done = 0
    for done in range(1, options.iterations + 1):  # (the loop's bound: iterations)
        J = jacrev(residuals)(theta)
        A, gradient = J.T @ J, J.T @ r
        scale = A.diagonal() + 1e-12
        while damping <= LM_MAX_DAMPING:  # (a bounded search: the damping grows 4x a try)
            step = torch.linalg.solve(A + damping * torch.diag(scale), -gradient)
            trial = residuals(theta + step)
            trial_loss = float(trial @ trial)
            if trial_loss < loss:
                theta, r, loss, damping = theta + step, trial, trial_loss, max(damping / 3, LM_MIN_DAMPING)
                break
            damping *= 4
        if not np.isfinite(loss):
            raise ConvergenceError(f"{NAME}: the loss went non-finite at iteration {done}")
        if damping > LM_MAX_DAMPING or loss < LOSS_FLOOR:  # (no step lowers it further, or nothing left)
            break
    net.theta = theta
    return {"iterations": done, "loss": loss}


def error_estimate(compiled, t_span, start, times, values, rtol) -> tuple[float, str]:
    """The largest distance of ``values`` (B, T, n+m) from radau at ``rtol`` on the same times, relative
    to ``1 + max|u|`` of each variable, and where it is."""
    check = dm.solve(
        compiled,
        t_span,
        method="radau",
        rtol=rtol,
        atol=rtol,
        jit=False,  # (casadi's virtual machine: nothing to compile for a check of a few unknowns)
        t_eval=times,
        y0=start.y0,
        z0=start.z0,
        parameters=start.p,
    )
    names = (*compiled.state_names, *compiled.algebraic_names)
    worst, where = 0.0, ""
    for i, name in enumerate(names):
        reference = np.asarray(check[name]).reshape(values.shape[0], -1)
        distance = np.abs(values[..., i] - reference) / (1.0 + np.abs(reference).max(axis=1, keepdims=True))
        if distance.max() > worst:
            b, k = np.unravel_index(int(distance.argmax()), distance.shape)
            worst, where = float(distance.max()), f"t = {times[k]:.4g} ({name}, sample {b})"
    return worst, where


def main(argv=None):
    """Compare the method with radau on Hessenberg against its exact solution; the Comparison."""
    import argparse

    from daemodel.problems import HESSENBERG

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one short training (CI)")
    args = parser.parse_args(argv)
    if NAME not in dm.methods():  # (installed, the entry point has made it known)
        dm.methods.register(NAME, WholeSpanPINN)
    settings = [{"iterations": 150}] if args.quick else [{"iterations": 50}, {"iterations": 150}, {"iterations": 300}]
    result = dm.compare(
        HESSENBERG.model(),
        (0.0, 1.0),
        [NAME, "radau"],
        reference=HESSENBERG.exact_solution(),
        sweep={NAME: settings},
        points=2,
    )
    print(result.table())
    run = next(r for r in result.runs if r.method == NAME)
    worst = max(v["max"] for v in run.errors.values())
    print(f"{NAME}: max error against the exact solution {worst:.2e}, status {run.status!r}")
    assert run.status == "success" and worst < 1e-3
    return result


if __name__ == "__main__":
    main()
