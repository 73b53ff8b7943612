"""The trained PINN networks' file: what ``Surrogate.save`` (and ``solve(..., method="pinn",
save=path)``) writes and ``Surrogate.load`` reads back, checked field by field before anything is
built from it.  Written through :mod:`daemodel.files` (atomic, contained, sizes checked)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from daemodel.backends.pinn.config import PINNConfig
from daemodel.backends.pinn.segments import make_network
from daemodel.backends.pinn.train import SegmentStats

from daemodel.errors import ModelError, NetworkFileError

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


def fingerprint(compiled) -> str:
    """A hash of the equations, names and events: a saved network only loads for the model it solves
    (its parameter values are checked apart: a surrogate may take parameters as inputs)."""
    return compiled.fingerprint(parameter_values=False)


def write_networks(surrogate, path) -> Path:
    """Write the networks, the grid, the settings, the training box and the training stats of
    ``surrogate`` (a :class:`~daemodel.backends.pinn.surrogate.SurrogateNetworks`) to ``path``
    (a torch file); a directory that does not exist is an :class:`InvalidOptionError`."""
    from daemodel.files import atomic_write, writable_file

    path = writable_file(path, "path")
    payload = {
        "format": FILE_FORMAT,
        "model": surrogate.compiled.name,
        "fingerprint": fingerprint(surrogate.compiled),
        "config": dataclasses.asdict(surrogate.config),
        "grid": surrogate.grid.tolist(),
        "inputs": list(surrogate.inputs),
        "parameter_values": np.asarray(surrogate.compiled.parameter_values, dtype=float).tolist(),
        "box": {name: list(bounds) for name, bounds in surrogate.box.items()},
        "networks": [{k: v.detach().cpu() for k, v in net.state_dict().items()} for net in surrogate.networks],
        "stats": [dataclasses.asdict(s) for s in surrogate.stats],
    }
    return atomic_write(path, lambda handle: torch.save(payload, handle))


def read_networks(path, compiled, device: str | None = None) -> tuple:
    """Read networks written by :func:`write_networks` for ``compiled`` (see ``Surrogate.load``).

    Returns
    -------
    (config, grid, networks, inputs, stats, box)
        The arguments of the surrogate after ``compiled``.

    Raises
    ------
    NetworkFileError
        No file, not a network file (or an older format), a missing key, other equations,
        or a fixed parameter whose value differs from the trained one.
    """
    from daemodel.backends.torch_setup import torch_device

    from daemodel.files import open_file, readable_path, stored_members

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
    return config, grid, networks, inputs, stats, box


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
