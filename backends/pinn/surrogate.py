"""A trained Radau-PINN as a reusable solver: one network per segment, each a one-step map.

``Surrogate.train`` fits the segments on a box of initial states (and optionally of parameter
values); ``surrogate.solve(y0=...)`` then integrates any batch of new initial states with one
forward pass per segment, no Newton and no training.  ``dm.solve(..., method="pinn",
save=path)`` writes the networks of an ordinary solve in the same format, so
``Surrogate.load(path, model)`` reuses them (accurate near the trajectories they were trained on).
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np
import torch
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.train import Progress, SegmentStats, fit_sequential, make_network

from daemodel.errors import InvalidOptionError, NetworkFileError, ShapeError, UnknownSymbolError

FILE_FORMAT = "daemodel-pinn/1"
# Initial states drawn from a box when Surrogate.train is not told how many.
DEFAULT_BOX_SAMPLES = 256
# Surrogate.train's settings when no config is given.  Over a box the residuals cannot all
# vanish, so LM runs a fixed budget (tol=None).  Each segment starts from a fresh network: on
# the Hessenberg box, warm starts from the previous segment's fit ended 10-1000x less accurate.
# Width 16 per variable keeps one forward pass of 10,000 states over 20 segments under 1 s.
SURROGATE_CONFIG = PINNConfig(width=16, warm_start=False, tol=None, iterations=40)


def fingerprint(compiled) -> str:
    """A hash of the equations and names: a saved network only loads for the model it solves."""
    text = repr(
        (
            compiled.state_names,
            compiled.algebraic_names,
            compiled.parameter_names,
            [str(e) for e in compiled.rhs],
            [str(e) for e in compiled.g],
        )
    )
    return hashlib.sha256(text.encode()).hexdigest()


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
        Per-segment training results.
    """

    def __init__(self, compiled, config: PINNConfig, grid, networks, inputs=(), stats=()):
        self.compiled, self.config = compiled, config
        self.grid = np.asarray(grid, dtype=float)
        self.networks = list(networks)
        self.inputs = tuple(inputs)
        self.stats = list(stats)

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
    ) -> Surrogate:
        """Train on ``samples`` initial states drawn uniformly from a box.

        Parameters
        ----------
        model : Model or CompiledDAE
        t_span : (float, float)
        box : dict state name -> (low, high)
            Ranges of the initial states; states not named keep the model's values.  Each
            drawn point is projected onto the constraints (least change), so the box may
            include states that the constraints determine.
        parameter_box : dict parameter name -> (low, high), optional
            Parameters that become network inputs, with their training ranges.
        samples : int
            Number of training initial states (a Sobol sequence, scrambled with ``config.seed``).
        config : PINNConfig, optional
            Default ``SURROGATE_CONFIG``: per-variable networks of width 16, a fresh network
            per segment, 40 LM steps per segment (tol=None).
        progress : bool, optional
            Show a progress bar (default: when stderr is a terminal).
        """
        from daemodel.backends.base import fixed_grid, show_progress, torch_device
        from daemodel.backends.pinn.backend import resolve_model

        from daemodel.initial_states import project_states
        from daemodel.solver import check_span

        compiled = resolve_model(model, "Surrogate.train()")
        config = SURROGATE_CONFIG if config is None else config
        torch_device(config.device)
        t_span = check_span(t_span, compiled)
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise InvalidOptionError(f"samples must be a positive integer; got {samples!r}")
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
        y = project_states(compiled, y, p)
        inputs = tuple(name for name in compiled.parameter_names if name in parameter_box)
        grid = fixed_grid(t_span, config.h)
        return cls.fit(compiled, config, grid, y, p, inputs, show_progress(progress), "pinn surrogate")

    @classmethod
    def fit(cls, compiled, config, grid, y, p, inputs, progress: bool, label: str) -> Surrogate:
        """Train the segments of ``grid`` one after the other from the states ``y`` (B, n) with
        parameters ``p`` (B, k); the parameters named in ``inputs`` become network inputs."""
        dtype = getattr(torch, config.dtype)
        columns = [compiled.parameter_names.index(name) for name in inputs]
        x0 = torch.as_tensor(np.concatenate([y, p[:, columns]], axis=1), dtype=dtype, device=config.device)
        pt = torch.as_tensor(np.array(p), dtype=dtype, device=config.device)
        bar = Progress(len(grid) - 1, progress, label)
        try:
            networks, stats = fit_sequential(compiled, grid, x0, pt, config, bar)
        finally:
            bar.close()
        return cls(compiled, config, grid, networks, inputs, stats)

    # ---- evaluation -----------------------------------------------------------------------------
    def rollout(self, y0: np.ndarray, p: np.ndarray) -> np.ndarray:
        """States and algebraic values at the segment ends, shape (B, segments, n+m).

        Each segment is one forward pass of its network over the whole batch; its predicted
        ``y_{n+1}`` is the next network's input.
        """
        dtype = getattr(torch, self.config.dtype)
        columns = [self.compiled.parameter_names.index(name) for name in self.inputs]
        extra = torch.as_tensor(np.array(p[:, columns]), dtype=dtype, device=self.config.device)
        y = torch.as_tensor(np.array(y0), dtype=dtype, device=self.config.device)
        out = []
        with torch.no_grad():
            for k, net in enumerate(self.networks):
                pred = net.predict(torch.cat([y, extra], dim=1), float(self.grid[k + 1] - self.grid[k]))
                y = pred.y_end
                out.append(torch.cat([pred.y_end, pred.z_end], dim=1))
        return torch.stack(out, dim=1).cpu().numpy()

    def trajectory(self, start) -> np.ndarray:
        """Values on the grid for :class:`InitialStates` ``start``, shape (B, segments + 1, n+m)."""
        first = np.concatenate([start.y0, start.z0], axis=1)[:, None, :]
        return np.concatenate([first, self.rollout(start.y0, start.p)], axis=1)

    def solve(self, y0=None, z0=None, parameters=None):
        """Integrate a batch of consistent initial states with the trained networks.

        Parameters are as in :func:`daemodel.solve` (by name or as arrays); ``z0`` only seeds
        the consistent algebraic values at t0.  Returns a :class:`Solution` on the segment grid.
        """
        from daemodel.backends.base import make_solution
        from daemodel.backends.pinn.backend import PINNBackend, PINNOptions

        from daemodel.initial_states import initial_states

        start = initial_states(self.compiled, y0=y0, z0=z0, parameters=parameters)
        self._check_parameters(start.p)
        began = time.perf_counter()
        values = self.trajectory(start)
        wall = time.perf_counter() - began
        stats = {"mode": "surrogate", "segments": len(self.networks), "evaluation_seconds": wall}
        return make_solution(
            PINNBackend(), self.compiled, start, PINNOptions(config=self.config), self.grid, values, wall, stats
        )

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
        """Write the networks, the grid and the settings to ``path`` (a torch file)."""
        path = Path(path)
        payload = {
            "format": FILE_FORMAT,
            "model": self.compiled.name,
            "fingerprint": fingerprint(self.compiled),
            "config": dataclasses.asdict(self.config),
            "grid": self.grid.tolist(),
            "inputs": list(self.inputs),
            "parameter_values": np.asarray(self.compiled.parameter_values, dtype=float).tolist(),
            "networks": [{k: v.detach().cpu() for k, v in net.state_dict().items()} for net in self.networks],
            "stats": [dataclasses.asdict(s) for s in self.stats],
        }
        torch.save(payload, path)
        return path

    @classmethod
    def load(cls, path, model) -> Surrogate:
        """Read networks written by :meth:`save` (or ``solve(..., save=path)``) for ``model``."""
        from daemodel.backends.pinn.backend import resolve_model

        compiled = resolve_model(model, "Surrogate.load()")
        path = Path(path)
        if not path.is_file():
            raise NetworkFileError(f"no network file at {path}")
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:
            raise NetworkFileError(f"{path} is not a daemodel network file ({error.__class__.__name__})") from None
        if not isinstance(payload, dict) or payload.get("format") != FILE_FORMAT:
            raise NetworkFileError(f"{path} is not a daemodel network file (expected format {FILE_FORMAT!r})")
        if payload["fingerprint"] != fingerprint(compiled):
            raise NetworkFileError(
                f"{path} holds networks for model '{payload['model']}' with other equations than "
                f"'{compiled.name}'; load it with the model it was trained on"
            )
        config = PINNConfig(**payload["config"])
        inputs = tuple(payload["inputs"])
        d = len(compiled.states) + len(inputs)
        networks = []
        for k, state in enumerate(payload["networks"]):
            net = make_network(compiled, config, d, k)
            net.load_state_dict(state)
            networks.append(net)
        stats = [SegmentStats(**s) for s in payload["stats"]]
        return cls(compiled, config, payload["grid"], networks, inputs, stats)


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
