"""torch set-up for the methods that use it: devices, threads, the first use's warm-up."""

from __future__ import annotations

import time
from contextlib import contextmanager

from daemodel.errors import InvalidOptionError

# torch work (samples x unknowns per operation) below which intra-op threads cost more than they
# give: measured on 2 cores, batched radau on 100 pendulums takes 0.064 s on 1 thread and 0.117 s
# on 2, while 10,000 take 1.37 s and 1.07 s, and 50,000 7.4 s and 4.2 s.
SMALL_TORCH_WORK = 20_000


@contextmanager
def torch_threads(threads: int | None, work: int):
    """torch's intra-op threads for one computation, the caller's setting restored after it.

    ``threads`` None: one thread when ``work`` (samples x unknowns per operation) is below
    :data:`SMALL_TORCH_WORK`, where more only add synchronisation, and torch's own setting (the
    caller's ``torch.set_num_threads``) otherwise.
    """
    import torch

    wanted = threads if threads is not None else (1 if work < SMALL_TORCH_WORK else None)
    before = torch.get_num_threads()
    if wanted is not None and wanted != before:
        torch.set_num_threads(wanted)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


# (device, dtype) pairs on which torch has run its first operations in this process (see warm_up_torch).
_TORCH_WARM: set[tuple[str, str]] = set()


def warm_up_torch(device="cpu", dtype: str = "float64") -> float:
    """Import torch and run its first operations on ``device`` in ``dtype``, once per process; the
    seconds this call took (0.0 when already warm).

    torch's first use in a process costs 1-4 s (the import, then the first matrix product and LU,
    which load their kernels and LAPACK; a CUDA device's context on top).  A backend that uses torch
    calls this inside its timed setup, so that the cost lands on the setup clock of the solve that
    pays it instead of on no clock (the solve after it would look 100 times faster).
    """
    key = (str(device), str(dtype))
    if key in _TORCH_WARM:
        return 0.0
    began = time.perf_counter()
    import torch

    a = torch.eye(4, dtype=getattr(torch, dtype), device=torch_device(device)) + 1.0  # a named error for a bad device
    factors = torch.linalg.lu_factor(a)
    torch.linalg.lu_solve(*factors, a @ a)
    if a.device.type == "cuda":
        torch.cuda.synchronize(a.device)
    _TORCH_WARM.add(key)
    return time.perf_counter() - began


def torch_device(name):
    """``torch.device(name)`` for a device daemodel's torch solvers can use here: the CPU or a visible CUDA device.

    Raises :class:`InvalidOptionError` naming the device and the valid choices for anything else
    (not a device name, ``"meta"``, ``"mps"``, a CUDA device torch cannot see).
    """
    import torch

    choices = device_choices()
    if isinstance(name, torch.device):
        device = name
    elif isinstance(name, str):
        try:
            device = torch.device(name)
        except (RuntimeError, ValueError):
            raise InvalidOptionError(
                f"device = {name!r} names no torch device; the choices here are {choices}"
            ) from None
    else:
        raise InvalidOptionError(f"device must be a string such as 'cpu'; got {name!r}; the choices here are {choices}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InvalidOptionError(f"device = {name!r} but torch sees no CUDA device; use device='cpu'")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InvalidOptionError(
                f"device = {name!r} but torch sees {torch.cuda.device_count()} CUDA device(s); the choices here "
                f"are {choices}"
            )
    elif device.type != "cpu":
        raise InvalidOptionError(
            f"device = {name!r}: daemodel's torch solvers run on the CPU or a CUDA device, not on "
            f"{device.type!r} (float64, LU factorisation); the choices here are {choices}"
        )
    return device


def device_choices() -> str:
    """The devices :func:`torch_device` accepts on this machine, as a readable list."""
    import torch

    names = ["'cpu'"]
    if torch.cuda.is_available():
        count = torch.cuda.device_count()
        names += ["'cuda'", "'cuda:0'" if count == 1 else f"'cuda:0' to 'cuda:{count - 1}'"]
    return ", ".join(names)
