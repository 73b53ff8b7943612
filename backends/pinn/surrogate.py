"""A trained Radau-PINN's networks over a time grid, one a segment, each a one-step map: their
evaluation (one forward pass per segment over any batch of states), their dense output, the checks
of a query against their training inputs, the training on given states, and their file.

The user's class, :class:`daemodel.Surrogate` (``Surrogate.train`` over a box, ``surrogate.solve``
with its certified hybrid that falls back to radau), is :class:`daemodel.solving.surrogates.Surrogate`,
built on :class:`SurrogateNetworks`: the parts that run other solves live in the solving layer.
``dm.solve(..., method="pinn", save=path)`` writes the networks of an ordinary solve in the same
format (:mod:`.surrogate_files`), so ``Surrogate.load(path, model)`` reuses them.

A surrogate is only as good as its training inputs, so it records them: the training box (the
range of every state and input parameter it was trained from) and, per segment, the range of
that segment's training inputs; :meth:`SurrogateNetworks.check_start` and
:meth:`SurrogateNetworks.check_drift` check every query against both.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import torch
from daemodel.backends.pinn.certificate import CERTIFICATE_NEWTON_TOL, certify
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.segments import fit_parallel, make_loss, segment_steps, train_segments
from daemodel.backends.pinn.surrogate_files import read_networks, write_networks

from daemodel.errors import InvalidOptionError, OutsideTrainingBoxError, OutsideTrainingBoxWarning
from daemodel.tableau import radau_iia

# A query counts as outside the training box (or a segment's training inputs) when it lies beyond
# a face by more than this fraction of the box's width.  The recorded box is the min/max of the
# training states, which undercuts the distribution they came from: on the Hessenberg box
# (0.98, 1.02)^4 with 64 training states, held-out states from the same box go up to 18% of the
# width beyond it (start and later segments).  A query 25% outside has errors 3x those inside;
# 100% outside 50x, 500% outside 6000x (0.09 against 1.5e-5).
BOX_MARGIN = 0.25
# ... plus this much relative to max(1, |bound|), so that a range of zero width (a state the box
# does not vary, or the single start of an ordinary solve) still accepts its own value recomputed
# in another order and the drift of chained predictions (a segment-parallel fit's start mismatch).
BOX_FLOOR = 1e-6
# What Surrogate.solve does with a query outside its training inputs.
OUTSIDE_POLICIES = ("warn", "error", "ignore")
# Queries evaluated (and certified, with tol=) at once.  In one batch the (networks, queries, width) activations and the
# estimate's (states, queries, ...) cotangents leave the caches: on one CPU thread 10^5 queries
# took 26x (networks) and 40x (estimate) the time of 10^4.  On 5*10^4 pendulum queries, chunks
# of 1,024 / 2,048 / 8,192 / 16,384 took 1.66 / 1.52 / 1.60 / 1.71 s (networks) and 5.4 / 5.6 /
# 6.8 / 12.0 s (with the estimate).
EVALUATION_CHUNK = 2048
# Surrogate.solve(tol=) certifies each answer with a Newton check that stops when its increments
# fall below this fraction of tol (:func:`check_tolerance`): the distance is then resolved far
# below tol in two iterations from trained networks, where the trajectory mode's check (to 10 eps)
# takes four.  The check's relative tolerance is at most SURROGATE_CHECK_CAP, whatever tol.
SURROGATE_CHECK_RESOLUTION = 1e-3
SURROGATE_CHECK_CAP = 1e-10
# Surrogate.solve(estimate=True) multiplies its propagated residual sums by this.  Measured on
# 1,000 held-out states of pendulum and Hessenberg surrogates (16 training states, +-1 %,
# [0, 0.25]): the unscaled y estimate bounded the error against radau's collocation solution for
# 95-96 % of the states (largest ratio error / estimate 2.3); doubled, 99.9 and 100 %.  The z
# estimate bounded every state unscaled (largest ratio 0.4 and 0.1).
ESTIMATE_SAFETY = 2.0


class SurrogateNetworks:
    """The trained networks of a Radau-PINN over a time grid (evaluation, checks, file); the
    user's :class:`daemodel.Surrogate` adds the training over a box and the solves.

    Attributes
    ----------
    compiled : CompiledDAE
    config : PINNConfig
    grid : ndarray, shape (segments + 1,)
        Segment boundaries.
    networks : list of RadauNetwork
        One per segment.
    inputs : tuple of str
        Parameters that are network inputs (after the states), by name.
    stats : list of SegmentStats
        Per-segment training results, with each segment's training-input range.
    box : dict name -> (low, high)
        The training box: for every state and input parameter, the range it was trained from
        (by default the first segment's training inputs).  For ``Surrogate.train``, the range of the
        training states after projection onto the constraints, and the ``parameter_box``; for
        ``solve(..., method="pinn")``, the start state(s) of that solve.  Either way widened by
        the ``radius`` box around each start when ``config.samples > 1``.
    """

    def __init__(self, compiled, config: PINNConfig, grid, networks, inputs=(), stats=(), box=None):
        self.compiled, self.config = compiled, config
        self.grid = np.asarray(grid, dtype=float)
        self.networks = list(networks)
        self.inputs = tuple(inputs)
        self.stats = list(stats)
        if box is None:
            first = self.stats[0]
            box = {name: (first.inputs_low[i], first.inputs_high[i]) for i, name in enumerate(self.input_names)}
        self.box = {name: (float(box[name][0]), float(box[name][1])) for name in self.input_names}

    @property
    def input_names(self) -> tuple[str, ...]:
        """The networks' inputs: the states, then the parameters in :attr:`inputs`."""
        return (*self.compiled.state_names, *self.inputs)

    @property
    def input_columns(self) -> list[int]:
        """Where the input parameters (:attr:`inputs`) sit in the model's parameter vector."""
        return [self.compiled.parameter_names.index(name) for name in self.inputs]

    @property
    def segment_ranges(self) -> tuple[np.ndarray, np.ndarray]:
        """Low and high ends of each segment's training inputs, each of shape (segments, d)."""
        return (
            np.array([s.inputs_low for s in self.stats], dtype=float),
            np.array([s.inputs_high for s in self.stats], dtype=float),
        )

    # ---- training (on given states) -------------------------------------------------------------
    @classmethod
    def fit(
        cls, compiled, config, grid, y, z, p, inputs, progress: bool, label: str, parameter_box: dict | None = None
    ) -> SurrogateNetworks:
        """Train the segments of ``grid`` one after the other from the consistent states ``y``
        (B, n), ``z`` (B, m) with parameters ``p`` (B, k); the parameters named in ``inputs``
        become network inputs.

        The training box is the first segment's training-input range, with the input
        parameters' ranges replaced by ``parameter_box`` where given (the range they were drawn from).
        """
        columns = [compiled.parameter_names.index(name) for name in inputs]
        networks, stats = train_segments(compiled, config, grid, y, z, p, columns, progress, label)
        surrogate = cls(compiled, config, grid, networks, inputs, stats)
        surrogate.box.update({name: tuple(map(float, bounds)) for name, bounds in (parameter_box or {}).items()})
        return surrogate

    @classmethod
    def fit_on_starts(
        cls, compiled, config, grid, x, algebraics, p, inputs, progress, executor, parameter_box=None
    ) -> SurrogateNetworks:
        """Train every segment of ``grid`` independently on known start values, as tasks of
        ``executor`` ("local", or "ray" on the cluster Ray is connected to): ``x`` (segments, B, d) each segment's
        network inputs (states then input parameters), ``algebraics`` (segments, B, m) their
        algebraic values, ``p`` (B, k) the parameters; ``progress`` a
        :class:`~daemodel.backends.pinn.segments.Progress`.  The box as in :meth:`fit`."""
        networks, stats, _ = fit_parallel(compiled, grid, x, algebraics, p, config, progress, executor)
        surrogate = cls(compiled, config, grid, networks, inputs, stats)
        surrogate.box.update({name: tuple(map(float, bounds)) for name, bounds in (parameter_box or {}).items()})
        return surrogate

    # ---- evaluation -----------------------------------------------------------------------------
    def rollout(self, y0: np.ndarray, p: np.ndarray, stages: bool = False):
        """States and algebraic values at the segment ends, shape (B, segments, n+m); with
        ``stages``, also every segment's predictions ``(Y, Z, y_end, z_end)``, each (segments,
        B, ...) in float64 (what :func:`certify` checks).

        Each segment is one forward pass of its network over the whole batch; its predicted
        ``y_{n+1}`` is the next network's input.
        """
        if len(y0) > EVALUATION_CHUNK and self.networks[0].copies == 1:
            parts = [self.rollout(y0[rows], p[rows], stages) for rows in chunks(len(y0))]
            if not stages:
                return np.concatenate(parts)
            predictions = tuple(torch.cat([part[1][i] for part in parts], dim=1) for i in range(4))
            return np.concatenate([part[0] for part in parts]), predictions
        dtype = getattr(torch, self.config.dtype)
        extra = torch.as_tensor(np.array(p[:, self.input_columns]), dtype=dtype, device=self.config.device)
        y = torch.as_tensor(np.array(y0), dtype=dtype, device=self.config.device)
        out, kept = [], []
        with torch.no_grad():
            for net, (_, h) in zip(self.networks, segment_steps(self.grid), strict=True):
                pred = net.predict(torch.cat([y, extra], dim=1), h)
                y = pred.y_end
                out.append(torch.cat([pred.y_end, pred.z_end], dim=1))
                if stages:
                    kept.append([a.to(torch.float64) for a in (pred.Y, pred.Z, pred.y_end, pred.z_end)])
        values = torch.stack(out, dim=1).cpu().numpy()
        if not stages:
            return values
        return values, tuple(torch.stack([row[i] for row in kept]) for i in range(4))

    def trajectory(self, start, stages: bool = False):
        """Values on the grid for :class:`InitialStates` ``start``, shape (B, segments + 1, n+m)
        (and with ``stages`` the predictions of :meth:`rollout`)."""
        first = np.concatenate([start.y0, start.z0], axis=1)[:, None, :]
        ends = self.rollout(start.y0, start.p, stages)
        values = np.concatenate([first, ends[0] if stages else ends], axis=1)
        return (values, ends[1]) if stages else values

    def polynomials(self, values: np.ndarray, predictions):
        """The networks' dense output: on each segment the collocation polynomial through the
        segment's start (``values`` (B, segments + 1, n+m), :meth:`trajectory`'s) and the stage
        values its network predicted (``predictions``, :meth:`rollout`'s), with the segment's end
        value at ``c_s = 1`` (the value the solution reports there: the network's ``y_{n+1}``).
        The same polynomial radau's dense output evaluates, on the networks' stage values."""
        from daemodel.dense import CollocationPolynomials

        Y, Z = (a.cpu().numpy() for a in predictions[:2])  # (segments, B, s, n), (segments, B, s, m)
        stages = np.concatenate([Y, Z], axis=3).transpose(1, 0, 2, 3)  # (B, segments, s, n+m)
        stages[:, :, -1] = values[:, 1:]
        nodes = np.concatenate([values[:, :-1, None], stages], axis=2)
        steps = np.array(segment_steps(self.grid), dtype=float)
        return CollocationPolynomials(
            c=np.asarray(radau_iia(self.config.stages).c, dtype=float),
            starts=steps[:, 0],
            lengths=steps[:, 1],
            nodes=nodes,
        )

    def certified_distance(self, values: np.ndarray, p: np.ndarray, newton_tol: float) -> np.ndarray:
        """Each sample's certified distance from the collocation solution (largest over the grid
        and variables, plus the check's own resolution; inf where its Newton check failed), for
        ``solve(tol=)``: the networks' answers ``values`` (B, T, n+m) at parameters ``p``, the
        check's Newton tolerance ``newton_tol`` (:func:`check_tolerance`)."""
        certificate = certify(
            self.compiled,
            self.config,
            self.grid,
            self.networks,
            self.input_columns,
            values,
            p,
            radau_error=False,
            newton_tol=newton_tol,
        )
        return (certificate.distance + certificate.rounding).max(axis=(1, 2))

    def estimate(self, start) -> tuple[np.ndarray, dict]:
        """The networks' values on the grid (as :meth:`trajectory`) and the error estimates of
        ``Surrogate.solve(estimate=True)`` along that trajectory, from one pass over the segments."""
        if start.size > EVALUATION_CHUNK:
            parts = [self.estimate(rows_of(start, rows)) for rows in chunks(start.size)]
            values = np.concatenate([values for values, _ in parts])
            return values, {key: np.concatenate([estimates[key] for _, estimates in parts]) for key in parts[0][1]}
        config, n = self.config, len(self.compiled.states)
        dtype = getattr(torch, config.dtype)
        loss = make_loss(self.compiled, config)
        p = torch.as_tensor(np.array(start.p), dtype=dtype, device=config.device)
        extra = p[:, self.input_columns]
        y = torch.as_tensor(np.array(start.y0), dtype=dtype, device=config.device)
        B = y.shape[0]
        E_y = torch.zeros(B, dtype=dtype, device=config.device)
        est_y, est_z, ends = [np.zeros(B)], [np.zeros(B)], []
        # one cotangent per row of d y_end / d y_n, all rows in one batched backward pass
        rows = torch.eye(n, dtype=dtype, device=config.device)[:, None, :].expand(n, B, n)
        for network, (t_k, h) in zip(self.networks, segment_steps(self.grid), strict=True):
            y_n = y.detach().clone().requires_grad_(True)
            out = network.predict(torch.cat([y_n, extra], dim=1), h)
            (jacobian,) = torch.autograd.grad(out.y_end, y_n, rows, is_grads_batched=True)  # (row, B, column)
            growth = jacobian.abs().sum(-1).amax(0)  # max row sum of d y_end / d y_n
            with torch.no_grad():
                ends.append(torch.cat([out.y_end, out.z_end], dim=1))
                res = loss.residuals(t_k, h, y_n.detach(), p, out)
                F = res.F.abs().amax(dim=(1, 2))
                G = res.G.abs().amax(dim=(1, 2)) if res.G.numel() else torch.zeros_like(F)
                carried = growth * E_y
                E_y = carried + F
                est_y.append((ESTIMATE_SAFETY * E_y).cpu().numpy())
                est_z.append((ESTIMATE_SAFETY * (G / h**2 + E_y / h)).cpu().numpy())
            y = out.y_end.detach()
        estimates = {"y": np.stack(est_y, axis=1)}
        if self.compiled.algebraics:
            estimates["z"] = np.stack(est_z, axis=1)
        first = np.concatenate([start.y0, start.z0], axis=1)[:, None, :]
        return np.concatenate([first, torch.stack(ends, dim=1).cpu().numpy()], axis=1), estimates

    def network_inputs(self, y0: np.ndarray, p: np.ndarray) -> np.ndarray:
        """States then input parameters, shape (B, d)."""
        return np.concatenate([y0, p[:, self.input_columns]], axis=1)

    def _start_report(self, escaped, x, low, high, batched: bool) -> tuple[str, str]:
        count, b, _, j, _ = escaped
        name, total = self.input_names[j], len(x)
        sample = f"sample {b}: " if batched else ""
        short = f"{count} of {total} initial states outside the training box"
        return short, (
            f"{count} of {total} initial states lie outside the box the surrogate was trained on, "
            f"e.g. {sample}{_seen(name, x[b, j], low[j], high[j])}; "
            "the networks were not trained there and may be far off: train on a box that "
            "covers it, or pass outside='ignore'"
        )

    def _drift_report(self, drifted, later, rows, low, high, batched: bool) -> tuple[str, str]:
        count, b, k, j, _ = drifted
        b = int(rows[b])  # drifted counts among the samples that started inside the box
        name, total, segment = self.input_names[j], len(later), k + 1  # later starts at segment index 1
        t0, t1 = self.grid[segment], self.grid[segment + 1]
        sample = f"sample {b}: " if batched else ""
        short = f"{count} of {total} samples drift outside the inputs a later segment was trained on"
        return short, (
            f"{count} of {total} samples drift outside the inputs a later segment was trained on, "
            f"first at segment {segment + 1} (t = {t0:.6g} to {t1:.6g}), "
            f"e.g. {sample}predicted {_seen(name, later[b, k, j], low[k, j], high[k, j])}; "
            "from there on the networks extrapolate: train on a box that covers these trajectories, "
            "or pass outside='ignore'"
        )

    @staticmethod
    def _raise_or_warn(message: str, outside: str) -> None:
        if outside == "error":
            raise OutsideTrainingBoxError(message)
        if outside == "warn":
            warnings.warn(message, OutsideTrainingBoxWarning, stacklevel=3)

    def check_parameters(self, p: np.ndarray) -> None:
        fixed = [i for i, name in enumerate(self.compiled.parameter_names) if name not in self.inputs]
        if fixed:
            trained = np.asarray(self.compiled.parameter_values, dtype=float)[fixed]
            moved = ~np.isclose(p[:, fixed], trained, rtol=1e-12, atol=0)
            if moved.any():
                name = self.compiled.parameter_names[fixed[int(np.argwhere(moved)[0, 1])]]
                raise InvalidOptionError(
                    f"parameter '{name}' was fixed when these networks were trained; train with "
                    f"parameter_box={{'{name}': (low, high)}} to vary it"
                )

    def check_start(self, start, outside: str) -> tuple:
        """Check the initial states and input parameters of :class:`InitialStates` ``start``
        against the training box; warn or raise as ``outside`` says (see ``Surrogate.solve``).

        Returns ``(x (B, d) the network inputs, inside (B,) the samples inside the box, reports)``,
        ``reports`` a list of ``(short, message)``.
        """
        self.check_parameters(start.p)
        x = self.network_inputs(start.y0, start.p)
        low, high = (np.array([self.box[name][i] for name in self.input_names]) for i in (0, 1))
        escaped = _outside(x[:, None, :], low[None], high[None])
        inside = np.ones(len(x), dtype=bool) if escaped is None else escaped[4]
        reports = []
        if escaped is not None:
            reports.append(self._start_report(escaped, x, low, high, start.batched))
            self._raise_or_warn(reports[-1][1], outside)
        return x, inside, reports

    def check_drift(self, values: np.ndarray, x: np.ndarray, inside: np.ndarray, batched: bool, outside: str):
        """Check the predicted states ``values`` (B, T, n+m) of the samples ``inside`` against the
        inputs each later segment was trained on; warn or raise as ``outside`` says.  Returns the
        ``(short, message)`` report, or None when no sample drifts."""
        if len(self.networks) < 2:
            return None
        n = len(self.compiled.states)
        later = np.concatenate([values[:, 1:-1, :n], np.repeat(x[:, None, n:], len(self.networks) - 1, 1)], axis=2)
        low, high = (r[1:] for r in self.segment_ranges)
        drifted = _outside(later[inside], low, high)  # a start outside the box drifts anyway
        if drifted is None:
            return None
        report = self._drift_report(drifted, later, np.flatnonzero(inside), low, high, batched)
        self._raise_or_warn(report[1], outside)
        return report

    # ---- files ----------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the networks, the grid, the settings, the training box and the training stats
        to ``path`` (a torch file, :mod:`.surrogate_files`); a directory that does not exist is an
        :class:`InvalidOptionError`."""
        return write_networks(self, path)

    @classmethod
    def load(cls, path, model, *, device: str | None = None):
        """Read networks written by :meth:`save` (or ``solve(..., save=path)``) for ``model``.

        Parameters
        ----------
        path : str or Path
        model : Model or CompiledDAE
            The model it was trained on: the same equations and names, and the same values of
            the parameters that were not network inputs (the networks hold for those values
            only).  Parameters that were inputs are checked against their box at every solve.
        device : str, optional
            Where to put the networks (default: the device they were trained on).

        Raises
        ------
        NetworkFileError
            No file, not a network file (or an older format), a missing key, other equations,
            or a fixed parameter whose value differs from the trained one.
        """
        from daemodel.backends.pinn.segments import resolve_model

        compiled = resolve_model(model, "Surrogate.load()")
        return cls(compiled, *read_networks(path, compiled, device))


def check_tolerance(tol: float, values: np.ndarray) -> float:
    """The Newton check's tolerance for ``Surrogate.solve(tol=)``, relative to ``1 + |value|`` as
    :func:`~daemodel.collocation.collocation_step` reads it: :data:`SURROGATE_CHECK_RESOLUTION`
    of tol in absolute terms at the largest value, between 10 eps and :data:`SURROGATE_CHECK_CAP`."""
    relative = SURROGATE_CHECK_RESOLUTION * tol / (1 + float(np.abs(values).max()))
    return min(max(relative, CERTIFICATE_NEWTON_TOL), SURROGATE_CHECK_CAP)


def chunks(total: int) -> list:
    """Row slices of at most EVALUATION_CHUNK."""
    return [slice(i, min(i + EVALUATION_CHUNK, total)) for i in range(0, total, EVALUATION_CHUNK)]


def rows_of(start, rows: slice):
    """An InitialStates batch restricted to ``rows``."""
    return dataclasses.replace(start, y0=start.y0[rows], z0=start.z0[rows], p=start.p[rows])


def training_status(config: PINNConfig, stats) -> str:
    """What the networks' training reached, for a surrogate's status: the tolerance met on the
    training inputs, the segments that stopped above it, or for a fixed budget (tol=None) the
    budget and the final residual.  None of these certifies an answer to a new query."""
    worst = max(s.max_residual for s in stats)
    if config.tol is not None:
        missed = sum(not s.converged for s in stats)
        if missed:
            return (
                f"training stopped above tol = {config.tol:g} in {missed} of {len(stats)} segments "
                f"(final max residual {worst:.2g})"
            )
        return f"trained to tol = {config.tol:g} on its training inputs"
    fewest = min(s.iterations for s in stats)
    budget = f"{config.iterations} {config.optimizer} iterations per segment"
    if fewest < config.iterations:
        budget = f"up to {budget} (as few as {fewest}, where the loss stopped decreasing)"
    return f"budget: {budget}, final max residual {worst:.2g} (no tolerance set)"


def _seen(name: str, value: float, low: float, high: float) -> str:
    if low == high:
        return f"{name} = {value:.8g}, but training saw {name} = {low:.8g} only"
    return f"{name} = {value:.8g} not in [{low:.8g}, {high:.8g}] (give or take {BOX_MARGIN:.0%} of the width)"


def _outside(x: np.ndarray, low: np.ndarray, high: np.ndarray):
    """Where inputs ``x`` (B, K, d) leave the ranges ``[low, high]`` (K, d) by more than the margin.

    Returns None when none does, else ``(count, b, k, j, inside)``: how many samples leave at
    any k, the worst excursion at the first k where one happens (sample b, input j), and the
    mask (B,) of samples that never leave.
    """
    margin = BOX_MARGIN * (high - low) + BOX_FLOOR * np.maximum(1.0, np.maximum(np.abs(low), np.abs(high)))
    out = ~((x >= low - margin) & (x <= high + margin))  # a prediction gone non-finite is outside too
    if not out.any():
        return None
    excess = np.where(np.isfinite(x), np.maximum(low - margin - x, x - high - margin), np.inf)
    k = int(np.flatnonzero(out.any(axis=(0, 2)))[0])
    relative = np.where(out[:, k], excess[:, k] / (high[k] - low[k] + margin[k]), -np.inf)
    b, j = np.unravel_index(int(np.argmax(relative)), relative.shape)
    inside = ~out.any(axis=(1, 2))
    return int((~inside).sum()), int(b), k, int(j), inside
