"""``dm.Surrogate``: a trained Radau-PINN as a reusable solver, one network per segment.

``Surrogate.train`` fits the segments on a box of initial states (and optionally of parameter
values; with ``starts="radau"`` on radau's solution of them, an :func:`~daemodel.ensemble`);
``surrogate.solve(y0=...)`` then integrates any batch of new initial states with one forward pass
per segment, no Newton and no training, and with ``tol=`` or ``newton=True`` checks or corrects
the answers against the Radau IIA solution, falling back to radau where Newton from the networks
fails.  These parts run other solves, so they live here in the solving layer; the networks, their
evaluation, their checks against the training inputs and their file are
:class:`~daemodel.backends.pinn.surrogate.SurrogateNetworks` (the backends layer).
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np
import torch

from daemodel.backends.checks import check_number
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.segments import Progress, resolve_model, segment_steps
from daemodel.backends.pinn.surrogate import (
    OUTSIDE_POLICIES,
    SurrogateNetworks,
    check_tolerance,
    chunks,
    training_status,
)
from daemodel.dense import Deferred
from daemodel.errors import InvalidOptionError

# Initial states drawn from a box when Surrogate.train is not told how many.
DEFAULT_BOX_SAMPLES = 256
# Surrogate.train's sources of each segment's training states.
TRAINING_STARTS = ("network", "radau")
# Surrogate.train's settings when no config is given.  Over a box the residuals cannot all
# vanish, so LM runs a fixed budget (tol=None).  Each segment starts from a fresh network: on
# the Hessenberg box, warm starts from the previous segment's fit ended 10-1000x less accurate.
# Width 16 per variable keeps one forward pass of 10,000 states over 20 segments under 1 s.
SURROGATE_CONFIG = PINNConfig(width=16, warm_start=False, tol=None, iterations=40, batch="shared")


class Surrogate(SurrogateNetworks):
    """The trained networks of a Radau-PINN over a time grid, as a solver: :meth:`train` over a
    box, :meth:`solve` (the networks' answer, certified or corrected on request), :meth:`save`
    and :meth:`load`.  Attributes as :class:`~daemodel.backends.pinn.surrogate.SurrogateNetworks`."""

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
        executor: str = "local",
        workers: int | None = None,
        address: str | None = None,
        **renamed,
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
            and h, solved as a :func:`daemodel.ensemble` on ``executor``; the segments are then
            independent and train as tasks of ``executor``.  Training states that radau cannot
            solve are left out, with a warning naming them.
        executor : {"local", "ray"}
            Where the tasks of ``starts="radau"`` run: ``executor="ray"`` solves the training
            data and trains the segments on Ray, in parallel (``engine=`` names radau's casadi or
            torch engine; this option's old spelling ``engine="ray"`` is an
            :class:`InvalidOptionError`).
        workers, address
            Ray's, as in :func:`daemodel.ensemble`.
        """
        from daemodel.backends.grids import fixed_grid
        from daemodel.backends.pinn.surrogate_box import draw_training_states
        from daemodel.backends.progress import show_progress
        from daemodel.backends.torch_setup import torch_device
        from daemodel.executors import check_executor, refuse_engine
        from daemodel.solving.solver import check_span

        refuse_engine("Surrogate.train()", renamed)
        if renamed:  # what Python says of any other unknown keyword
            raise TypeError(f"Surrogate.train() got an unexpected keyword argument {next(iter(renamed))!r}")
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
        check_executor(executor, workers, address, config.device)
        if executor == "ray" and starts == "network":
            raise InvalidOptionError(
                "executor='ray' trains segments in parallel, which needs starts='radau': with starts='network' "
                "each segment waits for the previous one's predictions"
            )
        torch_device(config.device)
        parameter_box = dict(parameter_box or {})
        y, z, p, inputs = draw_training_states(model, compiled, box, parameter_box, samples, config.seed)
        grid = fixed_grid(t_span, config.h)
        shown = show_progress(progress)
        if starts == "network":
            return cls.fit(
                compiled, config, grid, y, z, p, inputs, shown, "pinn surrogate", parameter_box=parameter_box
            )
        return cls._fit_on_radau(
            compiled, config, grid, y, z, p, inputs, shown, (executor, workers, address), parameter_box
        )

    @classmethod
    def _fit_on_radau(cls, compiled, config, grid, y, z, p, inputs, progress, executor, parameter_box) -> Surrogate:
        """Every segment trained independently from radau's solution of the training states."""
        from daemodel.errors import ConvergenceError
        from daemodel.executors import connect
        from daemodel.solving.ensemble import ensemble

        name, workers, address = executor
        chunk = len(y)
        if name == "ray":  # the training states spread over the cluster's CPUs, a chunk each
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
                executor=name,
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
        for j, variable in enumerate(compiled.algebraic_names):  # not `name`: that is the executor's
            algebraics[..., j] = data[variable]
        algebraics = algebraics[:, :-1].transpose(1, 0, 2)  # (segments, B, m)
        bar = Progress(len(grid) - 1, progress, "pinn surrogate")
        try:
            # Ray is running now (the ensemble connected): later tasks go to the same cluster
            return cls.fit_on_starts(compiled, config, grid, x, algebraics, p, inputs, bar, name, parameter_box)
        finally:
            bar.close()

    # ---- solving --------------------------------------------------------------------------------
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
            by about residual / h^2); both are doubled
            (:data:`~daemodel.backends.pinn.surrogate.ESTIMATE_SAFETY`).  It costs n extra backward
            passes per segment.  Calibration, measured: see ESTIMATE_SAFETY and
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
        x, inside, reports = self.check_start(start, outside)
        began = time.perf_counter()
        values, estimates = self.estimate(start) if estimate else (self.trajectory(start), None)
        wall = time.perf_counter() - began
        if newton:
            return self._newton(start, values, wall, reports)
        corrected, newton_iterations = np.zeros(start.size, dtype=bool), 0
        path = np.full(start.size, "network", dtype=object)
        if tol is not None:
            checked = time.perf_counter()
            newton_tol = check_tolerance(tol, values)
            distance = np.concatenate(
                [self.certified_distance(values[rows], start.p[rows], newton_tol) for rows in chunks(start.size)]
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
        drift = self.check_drift(values, x, inside, start.batched, outside)
        if drift is not None:
            reports.append(drift)
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
        from daemodel.errors import ConvergenceError, SolverError, TimeLimitError

        values = np.empty((len(rows), len(self.grid), len(self.compiled.states) + len(self.compiled.algebraics)))
        path = np.empty(len(rows), dtype=object)
        iterations, whole = 0, []

        def attempt(part: np.ndarray, guessed: bool) -> list:
            """Solve the samples ``rows[part]``; halve a part that fails: the samples that fail alone."""
            nonlocal iterations
            try:
                solution = self._radau(start, rows[part], guessed)
            except TimeLimitError:  # (the caller's time is up: no half may run on)
                raise
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
                for chunk in chunks(len(x)):
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
