"""A trained Radau-PINN as a reusable solver: one network per segment, each a one-step map.

``Surrogate.train`` fits the segments on a box of initial states (and optionally of parameter
values); ``surrogate.solve(y0=...)`` then integrates any batch of new initial states with one
forward pass per segment, no Newton and no training.  ``dm.solve(..., method="pinn",
save=path)`` writes the networks of an ordinary solve in the same format, so
``Surrogate.load(path, model)`` reuses them (accurate near the trajectories they were trained on).

A surrogate is only as good as its training inputs, so it records them: the training box (the
range of every state and input parameter it was trained from) and, per segment, the range of
that segment's training inputs.  ``solve`` checks every query against both (see
:meth:`Surrogate.solve`); ``load`` refuses a model whose fixed parameters differ from the trained ones.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from daemodel.backends.checks import check_number
from daemodel.backends.pinn.certificate import CERTIFICATE_NEWTON_TOL, certify
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.segments import (
    Progress,
    fit_parallel,
    make_loss,
    make_network,
    resolve_model,
    segment_steps,
    train_segments,
)
from daemodel.backends.pinn.train import SegmentStats

from daemodel.dense import Deferred
from daemodel.errors import (
    InconsistentInitialStateError,
    InvalidOptionError,
    ModelError,
    NetworkFileError,
    OutsideTrainingBoxError,
    OutsideTrainingBoxWarning,
    ShapeError,
    UnknownSymbolError,
)
from daemodel.tableau import radau_iia

# Format 2 added the training box and each segment's input ranges; format-1 files cannot be checked.
FILE_FORMAT = "daemodel-pinn/2"
# Why an older file cannot be read, by format.
OLDER_FORMATS = {"daemodel-pinn/1": "which does not record the training box"}
# What a network file holds; a file that lacks one is damaged or was not written by Surrogate.save.
FILE_KEYS = (
    "format",
    "model",
    "fingerprint",
    "config",
    "grid",
    "inputs",
    "parameter_values",
    "box",
    "networks",
    "stats",
)
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
# Initial states drawn from a box when Surrogate.train is not told how many.
DEFAULT_BOX_SAMPLES = 256
# Surrogate.train's sources of each segment's training states.
TRAINING_STARTS = ("network", "radau")
# Surrogate.train's settings when no config is given.  Over a box the residuals cannot all
# vanish, so LM runs a fixed budget (tol=None).  Each segment starts from a fresh network: on
# the Hessenberg box, warm starts from the previous segment's fit ended 10-1000x less accurate.
# Width 16 per variable keeps one forward pass of 10,000 states over 20 segments under 1 s.
SURROGATE_CONFIG = PINNConfig(width=16, warm_start=False, tol=None, iterations=40, batch="shared")
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


def fingerprint(compiled) -> str:
    """A hash of the equations, names and events: a saved network only loads for the model it solves
    (its parameter values are checked apart: a surrogate may take parameters as inputs)."""
    return compiled.fingerprint(parameter_values=False)


class Surrogate:
    """The trained networks of a Radau-PINN over a time grid.

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
        (by default the first segment's training inputs).  For :meth:`train`, the range of the
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

    # ---- training -------------------------------------------------------------------------------
    @classmethod
    def train(
        cls,
        model,
        t_span,
        *,
        box: dict,
        parameter_box: dict | None = None,
        samples: int = DEFAULT_BOX_SAMPLES,
        config: PINNConfig | None = None,
        progress: bool | None = None,
        starts: str = "network",
        engine: str = "local",
        workers: int | None = None,
        address: str | None = None,
    ) -> Surrogate:
        """Train on ``samples`` initial states drawn uniformly from a box.

        Parameters
        ----------
        model : Model or CompiledDAE
        t_span : (float, float)
        box : dict state name -> (low, high)
            Ranges of the initial states; states not named keep the model's values.  Each
            drawn point is projected onto the constraints (least change), so the box may
            include states that the constraints determine.  The projected states' range is
            recorded as the surrogate's :attr:`box`, which :meth:`solve` checks queries against.
        parameter_box : dict parameter name -> (low, high), optional
            Parameters that become network inputs, with their training ranges (recorded in
            :attr:`box` as given).
        samples : int
            Number of training initial states (a Sobol sequence, scrambled with ``config.seed``).
        config : PINNConfig, optional
            Default ``SURROGATE_CONFIG``: per-variable networks of width 16, a fresh network
            per segment, 40 LM steps per segment (tol=None).  Its ``batch`` is always
            ``"shared"``: one set of networks over the box.
        progress : bool, optional
            Show a progress bar (default: when stderr is a terminal).
        starts : {"network", "radau"}
            Where each segment's training states come from.  ``"network"``: the previous
            segment's predictions for the training states (segments train one after another).
            ``"radau"``: radau's collocation solution of the training states at the same stages
            and h, solved as a :func:`daemodel.ensemble` on ``engine``; the segments are then
            independent and train as tasks of ``engine``.  Training states that radau cannot
            solve are left out, with a warning naming them.
        engine, workers, address
            As in :func:`daemodel.ensemble`, for ``starts="radau"``: ``engine="ray"`` solves
            the training data and trains the segments on Ray, in parallel.
        """
        from daemodel.backends.grids import fixed_grid
        from daemodel.backends.progress import show_progress
        from daemodel.backends.torch_setup import torch_device

        from daemodel.compiling.compiler import as_compiled
        from daemodel.compiling.initial_states import algebraic_values, project_states
        from daemodel.executors import check_executor
        from daemodel.solving.solver import check_span

        compiled = resolve_model(model, "Surrogate.train()")
        config = SURROGATE_CONFIG if config is None else config
        if not isinstance(config, PINNConfig):
            raise InvalidOptionError(f"config must be a dm.PINNConfig; got {type(config).__name__}")
        config = config.replace(batch="shared")  # one set of networks over the box: that is a surrogate
        t_span = check_span(t_span, compiled)
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise InvalidOptionError(f"samples must be a positive integer; got {samples!r}")
        if starts not in TRAINING_STARTS:
            raise InvalidOptionError(f"starts must be one of {', '.join(TRAINING_STARTS)}; got {starts!r}")
        check_executor(engine, workers, address, config.device)
        if engine == "ray" and starts == "network":
            raise InvalidOptionError(
                "engine='ray' trains segments in parallel, which needs starts='radau': with starts='network' "
                "each segment waits for the previous one's predictions"
            )
        torch_device(config.device)
        parameter_box = dict(parameter_box or {})
        ranges = _ranges(box, compiled.state_names, "box", "state") + _ranges(
            parameter_box, compiled.parameter_names, "parameter_box", "parameter"
        )
        if not ranges:
            raise InvalidOptionError("box names no state: give box={'y1': (low, high), ...}")
        from scipy.stats import qmc

        unit = qmc.Sobol(len(ranges), scramble=True, seed=config.seed).random(samples)
        y = np.tile(np.asarray(compiled.y0, dtype=float), (samples, 1))
        p = np.tile(np.asarray(compiled.parameter_values, dtype=float), (samples, 1))
        for column, (kind, index, low, high) in enumerate(ranges):
            target = y if kind == "state" else p
            target[:, index] = low + (high - low) * unit[:, column]
        _refuse_inconsistent_box(as_compiled(model, "Surrogate.train()"), y, p, box)  # (before any reduction)
        y = project_states(compiled, y, p)
        z = algebraic_values(compiled, compiled.t0, y, p, np.tile(np.asarray(compiled.z0, dtype=float), (samples, 1)))
        inputs = tuple(name for name in compiled.parameter_names if name in parameter_box)
        grid = fixed_grid(t_span, config.h)
        shown = show_progress(progress)
        if starts == "network":
            return cls.fit(
                compiled, config, grid, y, z, p, inputs, shown, "pinn surrogate", parameter_box=parameter_box
            )
        return cls._fit_on_radau(
            compiled, config, grid, y, z, p, inputs, shown, (engine, workers, address), parameter_box
        )

    @classmethod
    def _fit_on_radau(cls, compiled, config, grid, y, z, p, inputs, progress, engine, parameter_box) -> Surrogate:
        """Every segment trained independently from radau's solution of the training states."""
        from daemodel.errors import ConvergenceError
        from daemodel.executors import connect
        from daemodel.solving.ensemble import ensemble

        engine, workers, address = engine
        chunk = len(y)
        if engine == "ray":  # the training states spread over the cluster's CPUs, a chunk each
            chunk = max(1, -(-len(y) // int(connect(workers, address).cluster_resources().get("CPU", 1))))
        try:
            data = ensemble(
                compiled,
                (float(grid[0]), float(grid[-1])),
                y0=y,
                z0=z,
                parameters=p,
                method="radau",
                stages=config.stages,
                h=config.h,
                executor=engine,
                chunk=chunk,
            )
        except ConvergenceError as error:
            raise ConvergenceError(
                f"Surrogate.train(starts='radau'): radau solved none of the {len(y)} training states ({error}); "
                "shrink the box or the span, or take starts='network'"
            ) from None
        failures = data.stats["failures"]
        if failures:
            shown = ", ".join(str(f.index) for f in failures[:5])
            warnings.warn(
                f"Surrogate.train: radau could not solve {len(failures)} of {len(y)} training states (sample(s) "
                f"{shown}{', ...' if len(failures) > 5 else ''}; first: {failures[0].error}: {failures[0].message}); "
                "they are left out",
                stacklevel=3,
            )
        kept = data.stats["samples"]
        y, p = y[kept], p[kept]
        columns = [compiled.parameter_names.index(name) for name in inputs]
        states = np.stack([data[name] for name in compiled.state_names], axis=-1)  # (B, segments + 1, n)
        extra = np.broadcast_to(p[:, columns], (len(grid) - 1, len(kept), len(columns)))
        x = np.concatenate([states[:, :-1].transpose(1, 0, 2), extra], axis=2)  # (segments, B, d)
        algebraics = np.zeros((len(kept), len(grid), len(compiled.algebraic_names)))
        for j, name in enumerate(compiled.algebraic_names):
            algebraics[..., j] = data[name]
        algebraics = algebraics[:, :-1].transpose(1, 0, 2)  # (segments, B, m)
        bar = Progress(len(grid) - 1, progress, "pinn surrogate")
        try:
            # Ray is running now (the ensemble connected): later tasks go to the same cluster
            networks, stats, _ = fit_parallel(compiled, grid, x, algebraics, p, config, bar, engine)
        finally:
            bar.close()
        surrogate = cls(compiled, config, grid, networks, inputs, stats)
        surrogate.box.update({name: tuple(map(float, bounds)) for name, bounds in (parameter_box or {}).items()})
        return surrogate

    @classmethod
    def fit(
        cls, compiled, config, grid, y, z, p, inputs, progress: bool, label: str, parameter_box: dict | None = None
    ) -> Surrogate:
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

    # ---- evaluation -----------------------------------------------------------------------------
    def rollout(self, y0: np.ndarray, p: np.ndarray, stages: bool = False):
        """States and algebraic values at the segment ends, shape (B, segments, n+m); with
        ``stages``, also every segment's predictions ``(Y, Z, y_end, z_end)``, each (segments,
        B, ...) in float64 (what :func:`certify` checks).

        Each segment is one forward pass of its network over the whole batch; its predicted
        ``y_{n+1}`` is the next network's input.
        """
        if len(y0) > EVALUATION_CHUNK and self.networks[0].copies == 1:
            parts = [self.rollout(y0[rows], p[rows], stages) for rows in _chunks(len(y0))]
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

    def solve(
        self,
        y0=None,
        z0=None,
        parameters=None,
        *,
        outside: str = "warn",
        newton: bool = False,
        estimate: bool = False,
        tol: float | None = None,
    ):
        """Integrate a batch of consistent initial states with the trained networks.

        Parameters
        ----------
        y0, z0, parameters
            As in :func:`daemodel.solve` (by name or as arrays); ``z0`` only seeds the
            consistent algebraic values at t0.  A parameter that was fixed in training cannot
            change (an :class:`InvalidOptionError`).
        outside : {"warn", "error", "ignore"}
            What to do with a query outside what the networks were trained on: an initial
            state or input parameter outside :attr:`box`, or a predicted state that drifts
            outside the range a later segment was trained on, each by more than
            ``BOX_MARGIN`` (25%) of the range's width.  ``"warn"`` (default) issues an
            :class:`OutsideTrainingBoxWarning`, ``"error"`` raises
            :class:`OutsideTrainingBoxError` (a start outside the box before any evaluation),
            ``"ignore"`` says nothing.  Either way the Solution's ``status`` and
            ``stats["outside_training_box"]`` record it.
        newton : bool
            Correct the networks' answer by Newton: ``method="radau"`` with the surrogate's
            stages and step, every step starting from its network's stage values instead of
            an extrapolation (radau's ``start_guess``).  The answer is then the Radau IIA
            collocation solution whatever the networks' error, each step converged to rounding;
            a sample where Newton from the networks' guesses fails is solved by radau from its
            own start instead (the failing samples are found by halving the batch), and
            ``stats["path"]`` (B,) says which: ``"newton"`` or ``"radau"``; only a sample radau
            cannot solve either raises its named error.  ``stats["network_error"]`` (B,) is each sample's
            largest absolute difference between the networks' answer and it, over all variables
            and grid times (the certificate of the network-only answer), and
            ``stats["newton_iterations"]`` counts the iterations the guesses left to do (and those
            of any fallback from the samples' own starts).
        estimate : bool
            Attach to every answer an estimate of its error against that collocation solution,
            from its own Radau stage residual (f and g at the networks' predictions, no Newton):
            ``stats["error_estimate"]`` = ``{"y": (B, T), "z": (B, T)}`` on the grid (0 at t0).
            The y estimate propagates each segment's largest residual |F| (in units of y)
            through the networks' own sensitivity ``|d y_end / d y_n|`` (max row sum); the z
            estimate is ``|G| / h^2 + (propagated y error + |F|) / h`` (an index-2 variable moves
            by about residual / h^2); both are doubled (:data:`ESTIMATE_SAFETY`).  It costs n
            extra backward passes per segment.  Calibration, measured: see ESTIMATE_SAFETY and
            docs/benchmarks/surrogates.md; it is an estimate, not a proof.
        tol : float, optional
            The hybrid: every answer is checked by the certificate of the trajectory mode
            (:mod:`~daemodel.backends.pinn.certificate`): per segment, full Newton on the stage
            equations from the networks' stage values gives the Radau step from the networks' own
            start, and the differences are carried along the grid by the step map's sensitivity.
            A sample whose certified distance from the Radau IIA solution at the surrogate's h
            (largest over variables and grid times) exceeds ``tol``, or whose Newton check fails,
            is corrected by Newton from its networks' stage values (as ``newton=True``, for those
            samples only) and returns the collocation solution; the others return the networks'
            answer.  So every answer is within tol of that solution by its certificate, or is
            that solution.
            ``stats["certified_distance"]`` (B,) is each returned answer's certified distance (0
            where corrected), ``stats["corrected"]`` (B,) marks the corrected samples,
            ``stats["path"]`` (B,) says how each answer came: ``"network"``, ``"newton"`` (from
            the networks' guesses) or ``"radau"`` (from its own start, where Newton from the
            guesses failed: no ConvergenceError for a query the classical method solves),
            ``stats["newton_iterations"]`` counts the correction's, ``stats["certificate_seconds"]``
            the check's time.  Cannot be combined with ``newton=True``.

        Returns
        -------
        Solution
            On the segment grid.  With ``tol`` or ``newton=True``, ``status`` is ``"success"``
            (every answer within tol by its certificate or corrected; the collocation solution),
            with what was corrected and what lay outside the training ranges.  Without them it
            starts with ``"unchecked"`` and states what training reached (tol met on the
            training inputs, or the budget and its final residual): the networks' answer to a
            new query carries no certificate.
        """
        from daemodel.backends.base import make_solution

        from daemodel.compiling.initial_states import initial_states

        if self.networks[0].copies > 1:
            raise InvalidOptionError(
                f"these are {self.networks[0].copies} independent sets of networks, each trained for one sample of a "
                "batch: they answer that batch only; for networks that answer new queries, use Surrogate.train or "
                "PINNConfig(batch='shared')"
            )
        if outside not in OUTSIDE_POLICIES:
            raise InvalidOptionError(f"outside must be one of {', '.join(OUTSIDE_POLICIES)}; got {outside!r}")
        if tol is not None:
            tol = check_number("tol", tol)
            if newton:
                raise InvalidOptionError(
                    "newton=True corrects every sample and tol only those whose certified distance exceeds it; give one"
                )
        start = initial_states(self.compiled, y0=y0, z0=z0, parameters=parameters)
        self._check_parameters(start.p)
        x = self._network_inputs(start.y0, start.p)
        low, high = (np.array([self.box[name][i] for name in self.input_names]) for i in (0, 1))
        escaped = _outside(x[:, None, :], low[None], high[None])
        inside = np.ones(len(x), dtype=bool) if escaped is None else escaped[4]
        reports = []
        if escaped is not None:
            reports.append(self._start_report(escaped, x, low, high, start.batched))
            self._raise_or_warn(reports[-1][1], outside)
        began = time.perf_counter()
        values, estimates = self._estimate(start) if estimate else (self.trajectory(start), None)
        wall = time.perf_counter() - began
        if newton:
            return self._newton(start, values, wall, reports)
        corrected, newton_iterations = np.zeros(start.size, dtype=bool), 0
        path = np.full(start.size, "network", dtype=object)
        if tol is not None:
            checked = time.perf_counter()
            newton_tol = check_tolerance(tol, values)
            distance = np.concatenate(
                [self._certified_distance(values[rows], start.p[rows], newton_tol) for rows in _chunks(start.size)]
            )
            certificate_seconds = time.perf_counter() - checked
            corrected = ~(distance <= tol)
            if corrected.any():
                rows = np.flatnonzero(corrected)
                values[rows], path[rows], newton_iterations, _ = self._collocation(start, rows)
                distance[rows] = 0.0
                if estimates is not None:
                    for bound in estimates.values():
                        bound[rows] = 0.0
            inside = inside & ~corrected  # a corrected sample does not depend on where the networks were trained
        if len(self.networks) > 1:
            n = len(self.compiled.states)
            later = np.concatenate([values[:, 1:-1, :n], np.repeat(x[:, None, n:], len(self.networks) - 1, 1)], axis=2)
            low, high = (r[1:] for r in self.segment_ranges)
            drifted = _outside(later[inside], low, high)  # a start outside the box drifts anyway
            if drifted is not None:
                reports.append(self._drift_report(drifted, later, np.flatnonzero(inside), low, high, start.batched))
                self._raise_or_warn(reports[-1][1], outside)
        stats = {
            "mode": "surrogate",
            "segments": len(self.networks),
            "evaluation_seconds": wall,
            "max_residual": [s.max_residual for s in self.stats],
            "final_max_residual": max(s.max_residual for s in self.stats),
            "outside_training_box": [message for _, message in reports],
        }
        if estimates is not None:
            stats["error_estimate"] = estimates
        if tol is not None:
            stats.update({"mode": "surrogate, corrected above tol", "corrected": corrected, "tol": tol})
            stats.update(certified_distance=distance, certificate_seconds=certificate_seconds)
            stats["newton_iterations"] = newton_iterations
            stats["path"] = path.tolist()
        if tol is None:  # the networks' answers, unchecked: never "success"
            status = (
                f"unchecked ({training_status(self.config, self.stats)}): the networks' answer, without a certificate; "
                "pass tol= for answers within tol of the Radau solution, or newton=True for that solution"
            )
        else:  # every answer within tol of the Radau solution by its certificate, or corrected
            status = f"success (certified within tol = {tol:g} of the Radau solution, or corrected)"
        if reports:
            status = "; ".join([status, *(short for short, _ in reports)])
        if tol is not None:
            status += (
                f"; {int(corrected.sum())} of {start.size} samples corrected by Newton "
                f"(certified distance > tol = {tol:g})"
            )
            if (path == "radau").any():
                fallen = int((path == "radau").sum())
                status += f", {fallen} of them by radau from their start (Newton from the networks failed)"
        dense = None
        if not corrected.any():  # (the networks' answer throughout: their stages, on the first query)
            dense = Deferred(
                lambda: self.polynomials(values, self.rollout(start.y0, start.p, stages=True)[1]),
                f"each segment's collocation polynomial (degree {self.config.stages}) through its network's stages",
            )
        return make_solution(
            "pinn",
            self.compiled,
            start,
            None,
            self.grid,
            values,
            wall,
            stats,
            settings=dataclasses.asdict(self.config),
            status=status,
            dense=dense,
        )

    def _certified_distance(self, values: np.ndarray, p: np.ndarray, newton_tol: float) -> np.ndarray:
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

    def _estimate(self, start) -> tuple[np.ndarray, dict]:
        """The networks' values on the grid (as :meth:`trajectory`) and the error estimates of
        :meth:`solve` (``estimate=True``) along that trajectory, from one pass over the segments."""
        if start.size > EVALUATION_CHUNK:
            parts = [self._estimate(_rows_of(start, rows)) for rows in _chunks(start.size)]
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

    def _newton(self, start, network_values, network_seconds: float, reports):
        """The collocation solution from the networks' stage values (see :meth:`solve`)."""
        from daemodel.backends.base import make_solution

        began = time.perf_counter()
        values, path, iterations, solution = self._collocation(start, np.arange(start.size))
        difference = np.abs(network_values - values).reshape(start.size, -1)
        stats = {
            "mode": "surrogate + newton",
            "network_error": difference.max(axis=1),
            "network_seconds": network_seconds,
            "outside_training_box": [message for _, message in reports],
            "path": path.tolist(),
        }
        if solution is not None:  # one radau call from the networks' guesses solved every sample
            solution.stats.update(stats)
            return solution
        failed = int((path == "radau").sum())
        stats["newton_iterations"] = iterations
        return make_solution(
            "radau",
            self.compiled,
            start,
            None,
            self.grid,
            values,
            time.perf_counter() - began,
            stats,
            settings={"stages": self.config.stages, "h": self.config.h, "start_guess": "the networks"},
            status=f"success ({failed} of {start.size} samples by radau from their start: Newton from the networks "
            "failed)",
        )

    def _collocation(self, start, rows: np.ndarray) -> tuple:
        """The Radau IIA collocation solution at the surrogate's stages and step for the samples
        ``rows`` of ``start``: radau with every step started from its network's stage values,
        and, for the samples where that fails (split down to them), radau from its own start.

        Returns ``(values (R, T, n+m), path (R,) "newton" or "radau", Newton iterations, the
        Solution of the one call when every sample succeeded at once else None)``.  A sample
        that radau cannot solve from its start either is a :class:`ConvergenceError` naming it.
        """
        from daemodel.errors import ConvergenceError, SolverError

        values = np.empty((len(rows), len(self.grid), len(self.compiled.states) + len(self.compiled.algebraics)))
        path = np.empty(len(rows), dtype=object)
        iterations, whole = 0, []

        def attempt(part: np.ndarray, guessed: bool) -> list:
            """Solve the samples ``rows[part]``; halve a part that fails: the samples that fail alone."""
            nonlocal iterations
            try:
                solution = self._radau(start, rows[part], guessed)
            except SolverError as error:
                if len(part) == 1:
                    return [(int(part[0]), error)]
                half = len(part) // 2
                return attempt(part[:half], guessed) + attempt(part[half:], guessed)
            values[part] = self._values_of(solution, len(part))
            path[part] = "newton" if guessed else "radau"
            iterations += solution.stats["newton_iterations"]
            whole.append(solution)
            return []

        failed = attempt(np.arange(len(rows)), True)
        if failed:
            still = attempt(np.array([i for i, _ in failed]), False)
            if still:
                i, error = still[0]
                raise ConvergenceError(
                    f"Surrogate.solve: sample {int(rows[i])}: Newton from the networks' stage values failed, and radau "
                    f"from the sample's start too (solving it alone, so radau's 'sample 0' is this one: "
                    f"{type(error).__name__}: {error})"
                ) from None
        return values, path, iterations, whole[0] if not failed and len(whole) == 1 else None

    def _radau(self, start, rows: np.ndarray, guessed: bool):
        """radau at the surrogate's stages and step for the samples ``rows`` of ``start``, every
        step started from its network's stage values when ``guessed``."""
        from daemodel.solving.solver import solve

        grid, config = self.grid, self.config
        steps = segment_steps(grid)
        dtype = getattr(torch, config.dtype)
        p = start.p[rows]
        extra = torch.as_tensor(np.array(p[:, self.input_columns]), dtype=dtype, device=config.device)

        def guess(t, y, z):
            k = int(np.argmin(np.abs(grid[:-1] - t)))  # the segment this step is
            x = torch.cat([torch.as_tensor(y, dtype=dtype, device=config.device), extra], dim=1)
            with torch.no_grad():
                stages = []
                for chunk in _chunks(len(x)):
                    pred = self.networks[k].predict(x[chunk], steps[k][1])
                    stages.append(torch.cat([pred.Y, pred.Z], dim=2))
            return torch.cat(stages)

        return solve(
            self.compiled,
            (float(grid[0]), float(grid[-1])),
            method="radau",
            h=config.h,  # the grid the networks were trained on
            stages=config.stages,
            y0=start.y0[rows],
            z0=start.z0[rows],
            parameters=p,
            start_guess=guess if guessed else None,
            dtype=config.dtype,
            device=config.device,
        )

    def _values_of(self, solution, samples: int) -> np.ndarray:
        """A Solution's values as (samples, T, n+m), states then algebraics."""
        names = (*self.compiled.state_names, *self.compiled.algebraic_names)
        return np.stack([np.asarray(solution[name]).reshape(samples, -1) for name in names], axis=-1)

    def _network_inputs(self, y0: np.ndarray, p: np.ndarray) -> np.ndarray:
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

    def _check_parameters(self, p: np.ndarray) -> None:
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

    # ---- files ----------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the networks, the grid, the settings, the training box and the training stats
        to ``path`` (a torch file); a directory that does not exist is an :class:`InvalidOptionError`."""
        from daemodel.files import atomic_write, writable_file

        path = writable_file(path, "path")
        payload = {
            "format": FILE_FORMAT,
            "model": self.compiled.name,
            "fingerprint": fingerprint(self.compiled),
            "config": dataclasses.asdict(self.config),
            "grid": self.grid.tolist(),
            "inputs": list(self.inputs),
            "parameter_values": np.asarray(self.compiled.parameter_values, dtype=float).tolist(),
            "box": {name: list(bounds) for name, bounds in self.box.items()},
            "networks": [{k: v.detach().cpu() for k, v in net.state_dict().items()} for net in self.networks],
            "stats": [dataclasses.asdict(s) for s in self.stats],
        }
        return atomic_write(path, lambda handle: torch.save(payload, handle))

    @classmethod
    def load(cls, path, model, *, device: str | None = None) -> Surrogate:
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
        from daemodel.backends.torch_setup import torch_device

        from daemodel.files import open_file, readable_path, stored_members

        compiled = resolve_model(model, "Surrogate.load()")
        path = readable_path(path, "Surrogate.load: path", NetworkFileError)
        if not path.exists():
            raise NetworkFileError(f"no network file at {path}")
        with open_file(path, "path", NetworkFileError) as handle:
            # torch writes its archive uncompressed: the declared sizes must fit the file (no bomb)
            stored_members(handle, path, NetworkFileError, what="daemodel network file")
            try:
                payload = torch.load(handle, map_location="cpu", weights_only=True)  # no pickled code
            except Exception as error:  # torch's unpickler raises many kinds, RecursionError among them
                raise NetworkFileError(f"{path} is not a daemodel network file ({error.__class__.__name__})") from None
        found = payload.get("format") if isinstance(payload, dict) else None
        if found != FILE_FORMAT:
            older = OLDER_FORMATS.get(found) if isinstance(found, str) else None
            raise NetworkFileError(
                f"{path} is a daemodel network file of format {found!r}, {older}; "
                f"this version reads {FILE_FORMAT!r}: train and save it again"
                if older
                else f"{path} is not a daemodel network file (expected format {FILE_FORMAT!r})"
            )
        missing = [key for key in FILE_KEYS if key not in payload]
        if missing:
            raise NetworkFileError(
                f"{path} lacks the key{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))} "
                f"that a {FILE_FORMAT} file holds ({', '.join(FILE_KEYS)}): it is damaged or was not written "
                "by Surrogate.save; save the surrogate again"
            )
        if payload["fingerprint"] != fingerprint(compiled):
            raise NetworkFileError(
                f"{path} holds networks for model '{payload['model']}' with other equations than "
                f"'{compiled.name}'; load it with the model it was trained on"
            )
        _check_payload(path, compiled, payload)
        inputs = tuple(payload["inputs"])
        _check_fixed_parameters(path, compiled, payload["parameter_values"], inputs)
        try:
            config = PINNConfig(**payload["config"])
            if device is not None:
                config = config.replace(device=device)
        except (ModelError, TypeError) as error:
            raise NetworkFileError(f"{path} records settings that are not valid: {error}") from None
        torch_device(config.device)
        grid = np.asarray(payload["grid"], dtype=float)
        if len(payload["networks"]) != len(grid) - 1 or len(payload["stats"]) != len(grid) - 1:
            raise NetworkFileError(
                f"{path} holds {len(payload['networks'])} networks and {len(payload['stats'])} segment stats "
                f"for a grid of {len(grid) - 1} segments: it is damaged; save the surrogate again"
            )
        d = len(compiled.states) + len(inputs)
        networks = []
        for k, state in enumerate(payload["networks"]):
            net = make_network(compiled, config, d, k)
            try:
                net.load_state_dict(state)
            except (RuntimeError, TypeError, AttributeError) as error:
                first = str(error).strip().splitlines()[0]
                raise NetworkFileError(
                    f"{path}: the networks of segment {k + 1} do not fit the settings it records ({first}): "
                    "it is damaged; save the surrogate again"
                ) from None
            networks.append(net)
        try:
            stats = [
                SegmentStats(**{**s, "inputs_low": tuple(s["inputs_low"]), "inputs_high": tuple(s["inputs_high"])})
                for s in payload["stats"]
            ]
            box = {name: tuple(payload["box"][name]) for name in (*compiled.state_names, *inputs)}
        except (KeyError, TypeError) as error:
            raise NetworkFileError(
                f"{path} holds incomplete training records ({error.__class__.__name__}: {error}): "
                "it is damaged; save the surrogate again"
            ) from None
        return cls(compiled, config, grid, networks, inputs, stats, box)


def check_tolerance(tol: float, values: np.ndarray) -> float:
    """The Newton check's tolerance for ``Surrogate.solve(tol=)``, relative to ``1 + |value|`` as
    :func:`~daemodel.collocation.collocation_step` reads it: :data:`SURROGATE_CHECK_RESOLUTION`
    of tol in absolute terms at the largest value, between 10 eps and :data:`SURROGATE_CHECK_CAP`."""
    relative = SURROGATE_CHECK_RESOLUTION * tol / (1 + float(np.abs(values).max()))
    return min(max(relative, CERTIFICATE_NEWTON_TOL), SURROGATE_CHECK_CAP)


def _check_payload(path, compiled, payload: dict) -> None:
    """The types and sizes of a network file's fields, before anything is built from them."""

    def bad(key: str, expected: str):
        raise NetworkFileError(f"{path}: field {key!r} is not {expected}: it is damaged; save the surrogate again")

    def numbers(value) -> bool:
        return isinstance(value, list) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)

    inputs = payload["inputs"]
    if (
        not isinstance(inputs, list)
        or not all(isinstance(name, str) for name in inputs)
        or not set(inputs) <= set(compiled.parameter_names)
        or len(set(inputs)) != len(inputs)
    ):
        bad("inputs", f"a list of distinct parameters of the model ({', '.join(compiled.parameter_names)})")
    if not numbers(payload["parameter_values"]) or len(payload["parameter_values"]) != len(compiled.parameter_names):
        bad("parameter_values", f"{len(compiled.parameter_names)} numbers, one a parameter")
    if not isinstance(payload["config"], dict):
        bad("config", "a table of settings")
    grid = payload["grid"]
    if not numbers(grid) or len(grid) < 2 or not np.isfinite(grid).all() or (np.diff(grid) <= 0).any():
        bad("grid", "an increasing list of at least two finite times")
    for key in ("networks", "stats"):
        if not isinstance(payload[key], list) or not all(isinstance(item, dict) for item in payload[key]):
            bad(key, "a list with a table a segment")
    if not isinstance(payload["box"], dict):
        bad("box", "a table of ranges")


def _check_fixed_parameters(path, compiled, saved, inputs) -> None:
    """A parameter that was not a network input must have the value the networks were trained with."""
    saved = np.asarray(saved, dtype=float)
    current = np.asarray(compiled.parameter_values, dtype=float)
    for i, name in enumerate(compiled.parameter_names):
        if name in inputs or np.isclose(current[i], saved[i], rtol=1e-12, atol=0):
            continue
        trained, now = float(saved[i]), float(current[i])
        raise NetworkFileError(
            f"{path} was trained with parameter '{name}' = {trained!r} fixed, but the model has {name} = {now!r}; "
            f"the networks hold for the trained value only: load it onto a model with {name} = {trained!r} "
            f"(m.set_parameters({name}={trained!r})), or train with parameter_box={{'{name}': (low, high)}} "
            f"to make '{name}' a network input"
        )


def _chunks(total: int) -> list:
    """Row slices of at most EVALUATION_CHUNK."""
    return [slice(i, min(i + EVALUATION_CHUNK, total)) for i in range(0, total, EVALUATION_CHUNK)]


def _rows_of(start, rows: slice):
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


def _refuse_inconsistent_box(compiled, drawn: np.ndarray, p: np.ndarray, box: dict) -> None:
    """Refuse a box none of whose drawn states the constraints admit (pendulum ``y1`` in [2, 3]: no
    point of it is on the circle), naming the box and the constraint, before training on states
    outside it: the least-change projection of every drawn state leaves the box.

    ``compiled`` is the model as declared (an index-3 model's reduction keeps its position level as an
    invariant only); ``drawn`` (B, n) the states drawn in the box.
    """
    from daemodel.compiling.initial_states import _checks, project_states, state_violations

    hidden = _checks(compiled).hidden
    if not hidden:
        return
    y = project_states(compiled, drawn, p)
    names = compiled.state_names
    index = np.array([names.index(k) for k in box])
    low, high = (np.array([box[k][j] for k in box], dtype=float) for j in (0, 1))
    slack = 1e-9 * np.maximum(1.0, np.maximum(abs(low), abs(high)))  # (a projection onto a face of the box)
    if ((y[:, index] >= low - slack) & (y[:, index] <= high + slack)).all(axis=1).any():
        return
    residual, _, bad = state_violations(compiled, drawn, p)
    level = int(np.argmax(bad[0])) if bad[0].any() else int(np.argmax(np.abs(residual[0])))
    name, label, _ = hidden[level]
    given = ", ".join(f"{k} in [{lo:g}, {hi:g}]" for k, (lo, hi) in box.items())
    j = int(np.argmax(np.maximum(low - y[0, index], y[0, index] - high)))
    moved = f"{names[index[j]]} = {drawn[0, index[j]]:.6g} -> {y[0, index[j]]:.6g}"
    raise InconsistentInitialStateError(
        f"Surrogate.train(): no state drawn in the box ({given}) satisfies {label} inside it: each of the "
        f"{len(drawn)} leaves the box on its least-change projection ({name} = {residual[0, level]:.6g} at the "
        f"first, whose projection moves {moved}); choose ranges the constraints allow, or name in the box the "
        "states the constraints determine too"
    )


def _ranges(box, names, argument: str, kind: str) -> list:
    if not isinstance(box, dict):
        raise ShapeError(f"{argument} must be a dict {kind} name -> (low, high); got {type(box).__name__}")
    out = []
    for name, bounds in box.items():
        if name not in names:
            raise UnknownSymbolError(
                f"{argument} names '{name}', which is not a {kind}; the {kind}s are {', '.join(names)}"
            )
        try:
            low, high = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise ShapeError(f"{argument}['{name}'] must be a pair (low, high); got {bounds!r}") from None
        if not (np.isfinite(low) and np.isfinite(high) and low < high):
            raise InvalidOptionError(f"{argument}['{name}'] = ({low:g}, {high:g}) must be finite with low < high")
        out.append((kind, names.index(name), low, high))
    return out
