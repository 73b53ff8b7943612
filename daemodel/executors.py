"""Where independent pieces of work run: one after another in this process (``"local"``, the
default: no worker processes, so nothing re-runs the calling script), or as Ray tasks
(``"ray"``, the optional extra ``daemodel[ray]``) on a local cluster or an existing one.

Ensemble chunks and segment-parallel PINN training both go through :func:`run_tasks`: a
module-level function, one object every task shares (the compiled model; Ray stores it once
and each worker unpickles it, regenerating its code without sympy's analysis) and a list of
per-task arguments.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from daemodel.errors import InvalidOptionError, TimeLimitError, WorkerError

EXECUTORS = ("local", "ray")
# Seconds a Ray task may run before it is stopped with a TimeLimitError (task_timeout=): far above
# an ensemble chunk's or a PINN segment's usual minutes, short of a forgotten overnight hang.
DEFAULT_TASK_TIMEOUT = 3600.0
# Where a cluster that daemodel starts listens: this machine only, unless an address is given.
LOOPBACK = "127.0.0.1"
# Shared objects (compiled models, with the code they generate) a Ray worker process keeps, by
# reference: the latest calls', so that the tasks of one call generate code once per worker.
HELD_OBJECTS = 2
# Once a time limit has struck, it strikes again this often until the task ends: code that swallows
# the first TimeLimitError (casadi's Python wrappers catch every exception in their type checks, so
# a limit that strikes while casadi builds a model's functions was lost, and the task ran on to its
# end: the transistor amplifier's IDAS at rtol 1e-9 under a 0.01 s limit ran 9.5 s) meets it again.
TIME_LIMIT_REPEAT = 0.25
# The time limits whose blocks run now (in the main thread), innermost last: see struck_limit.
_ACTIVE_LIMITS: list = []
_HELD: dict = {}


def check_timeout(task_timeout) -> None:
    """``task_timeout``: positive seconds or None."""
    if task_timeout is not None and (
        isinstance(task_timeout, bool) or not isinstance(task_timeout, int | float) or not task_timeout > 0
    ):
        raise InvalidOptionError(f"task_timeout must be a positive number of seconds or None; got {task_timeout!r}")


def check_executor(executor, workers, address, device="cpu") -> None:
    """The executor options' errors, named before any work starts (``device``: the torch device
    the tasks would compute on; Ray tasks request no GPU)."""
    if executor not in EXECUTORS:
        raise InvalidOptionError(f"executor must be one of {', '.join(EXECUTORS)}; got {executor!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidOptionError(f"workers must be a positive integer; got {workers!r}")
    if address is not None and not isinstance(address, str):
        raise InvalidOptionError(f"address must be a string such as 'auto' or 'ray://host:10001'; got {address!r}")
    if executor == "local" and (workers is not None or address is not None):
        raise InvalidOptionError("workers and address are Ray's: pass executor='ray' with them")
    if executor == "ray" and str(device) != "cpu":
        raise InvalidOptionError(
            f"executor='ray' runs each task on one of the workers' CPUs (no GPU requested); device = {str(device)!r} "
            "runs here: take executor='local' for it"
        )


def refuse_engine(caller: str, options: dict) -> None:
    """A clear error for the spelling ``engine='local' | 'ray'`` of ``caller``'s executor (renamed
    ``executor=``: ``engine=`` means casadi or torch for radau)."""
    if "engine" not in options:
        return
    engine = options["engine"]
    if isinstance(engine, str) and engine in EXECUTORS:
        raise InvalidOptionError(
            f"{caller}: engine={engine!r} is now spelled executor={engine!r} "
            "(engine= names radau's casadi or torch engine)"
        )
    raise InvalidOptionError(
        f"{caller} takes no engine= (radau's casadi or torch engine); got engine={engine!r}. "
        "Where its tasks run is executor='local' or 'ray'"
    )


def run_tasks(
    function: Callable,
    shared,
    tasks: list,
    *,
    executor: str,
    workers: int | None = None,
    address: str | None = None,
    label: str,
    on_result: Callable | None = None,
    task_timeout: float | None = DEFAULT_TASK_TIMEOUT,
) -> list:
    """``function(shared, *task)`` for every task; the results in task order.

    ``"local"`` calls them in order, here.  ``"ray"`` submits one task each (one CPU, torch on
    one thread), on the cluster :func:`connect` gives; a cluster it starts stays up for later
    calls.  ``on_result(i, result)`` runs here as each finishes (in completion order on Ray).
    On Linux, a result that is a dict gains ``"peak_memory_mb"``: the Ray worker's peak
    resident memory during the task.

    Raises
    ------
    WorkerError
        A Ray worker died before returning (killed, out of memory, crashed); ``label`` and the
        task's index name it.  An exception the function raised is re-raised as itself.
    TimeLimitError
        A Ray task ran longer than ``task_timeout`` seconds (None: no limit).
    InvalidOptionError
        ``executor`` is neither ``"local"`` nor ``"ray"`` (a mistyped name never starts Ray).
    """
    if executor not in EXECUTORS:
        raise InvalidOptionError(f"{label}: executor must be one of {', '.join(EXECUTORS)}; got {executor!r}")
    if executor == "local":
        results = []
        for i, task in enumerate(tasks):
            results.append(function(shared, *task))
            if on_result is not None:
                on_result(i, results[-1])
        return results
    ray = connect(workers, address)
    remote = ray.remote(num_cpus=1)(_on_worker)
    # Nested in a list, the reference reaches the task unresolved: each worker process fetches
    # and unpickles the shared object once and keeps it (with the code it generates) for the
    # call's later tasks, instead of once per task.
    stored = [ray.put(shared)]
    pending = {remote.remote(function, stored, (task_timeout, label, i), *task): i for i, task in enumerate(tasks)}
    results = [None] * len(tasks)
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(done[0])
            results[i] = _result(ray, done[0], label, i)
            if on_result is not None:
                on_result(i, results[i])
    finally:
        for reference in pending:
            ray.cancel(reference)
    return results


def connect(workers: int | None, address: str | None):
    """Ray, initialised: the running instance, the cluster at ``address``, or (``workers`` given)
    a new local cluster of that many CPUs; with neither, Ray's own choice (``RAY_ADDRESS``, the
    cluster ``ray start`` left on this machine, else a new local one)."""
    try:
        import ray
    except ImportError:
        raise InvalidOptionError(
            "executor='ray' needs Ray, which is not installed: pip install 'daemodel[ray]' (or pip install ray)"
        ) from None
    if not ray.is_initialized():
        if workers is not None and address not in (None, "local"):
            raise InvalidOptionError(
                f"workers sets the CPUs of a local cluster that this call starts; the cluster at "
                f"address={address!r} has its own: leave workers out"
            )
        if address is None and workers is None and not os.environ.get("RAY_ADDRESS"):
            try:  # a cluster that `ray start` left on this machine
                ray.init(address="auto", log_to_driver=False)
                return ray
            except ConnectionError:
                pass
        if address in (None, "local"):  # a new cluster: on the loopback interface, no dashboard
            with _loopback():
                ray.init(
                    address="local",
                    num_cpus=workers,
                    log_to_driver=False,
                    include_dashboard=False,
                    _node_ip_address=LOOPBACK,
                )
        else:
            ray.init(address=address, log_to_driver=False)
        return ray
    if address is not None:
        raise InvalidOptionError("Ray is already running in this process: leave out address (or ray.shutdown() first)")
    if workers is not None:
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus != workers:
            raise InvalidOptionError(
                f"Ray is already running in this process with {cpus:g} CPUs, not workers={workers}: leave out "
                "workers, or call ray.shutdown() first"
            )
    return ray


def _result(ray, reference, label: str, index: int):
    try:
        return ray.get(reference)
    except ray.exceptions.RayTaskError as error:
        cause = getattr(error, "cause", None)
        if isinstance(cause, Exception):
            # the function's own exception, without Ray's wrapping; the worker's traceback as a note
            cause.add_note(f"raised in a Ray worker, in {label}'s task {index}:\n{error}")
            raise cause from None
        raise
    except ray.exceptions.RayError as error:
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise WorkerError(
            f"{label}: the Ray worker running task {index} stopped before returning ({type(error).__name__}: "
            f"{reason}); give each task less work or the workers more memory"
        ) from None


def _on_worker(function, stored: list, limit: tuple, *task):
    """What a Ray task runs: the function on one torch thread (Ray gives the task one CPU), with
    the shared object this worker process already holds for the call, or fetches now, stopped by
    a TimeLimitError after ``limit`` = (seconds or None, label, index)."""
    import ray
    import torch

    torch.set_num_threads(1)
    (reference,) = stored
    key = reference.hex()
    if key not in _HELD:
        if len(_HELD) >= HELD_OBJECTS:
            _HELD.pop(next(iter(_HELD)))  # the oldest call's
        _HELD[key] = ray.get(reference)
    shared = _HELD[key]
    measured = _reset_peak_memory()
    with _time_limit(*limit):
        result = function(shared, *task)
    peak = _peak_memory_mb() if measured else None
    if isinstance(result, dict) and peak is not None:
        result["peak_memory_mb"] = peak
    return result


def _reset_peak_memory() -> bool:
    """Reset this process's peak resident memory (Linux: VmHWM), so that the next reading is
    this task's; False where the system has no such counter (then no reading is reported)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_memory_mb() -> float | None:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return None


class time_limit:
    """Raise :class:`TimeLimitError` with ``message`` in this (main) thread once ``seconds`` have
    passed (SIGALRM; a long call into compiled code is interrupted when it returns to Python).
    ``seconds=None``, or a thread other than the main one: no limit.  ``expired`` says afterwards
    whether the limit struck: code that catches exceptions from a callback (casadi's integrators)
    may hand the error on as its own failure.  Code that swallows the error meets it again every
    :data:`TIME_LIMIT_REPEAT` seconds, until the ``with`` block ends; an import under way is not
    interrupted (:func:`importing`): the limit strikes after it."""

    def __init__(self, seconds: float | None, message: str):
        self.seconds, self.message, self.expired = seconds, message, False
        self.active = seconds is not None and threading.current_thread() is threading.main_thread()
        self.closing = False

    def _expired(self, signum, frame):
        if self.closing:  # (the block is ending: its own exception, or its result, goes through)
            return
        self.expired = True
        if importing(frame):  # (it strikes again TIME_LIMIT_REPEAT later, after the import)
            return
        raise TimeLimitError(self.message)

    def __enter__(self):
        if self.active:
            self.closing = False
            self.previous = signal.signal(signal.SIGALRM, self._expired)
            signal.setitimer(signal.ITIMER_REAL, self.seconds, TIME_LIMIT_REPEAT)
            _ACTIVE_LIMITS.append(self)
        return self

    def __exit__(self, *_):
        if self.active:
            self.closing = True
            signal.setitimer(signal.ITIMER_REAL, 0)
            if self in _ACTIVE_LIMITS:
                _ACTIVE_LIMITS.remove(self)
            signal.signal(signal.SIGALRM, signal.SIG_DFL if self.previous is None else self.previous)


def importing(frame) -> bool:
    """Whether ``frame`` runs inside an import (importlib's frames below it).  A time limit does not
    strike there: a module whose import is interrupted can stay broken for the process (torch, stopped
    half-imported by an ensemble chunk's limit, raised "partially initialized module 'torch' has no
    attribute 'types'" in every later solve)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def struck_limit() -> TimeLimitError | None:
    """The error of the innermost time limit that has struck while its block still runs, else None.

    Code that turns a failed call into an error of its own (casadi reports an exception raised in a
    callback as the call's failure: IDAS's IDA_RES_FAIL) raises this instead, so that the time that ran
    out is not taken for the method's failure (an ensemble chunk bisected and solved again).
    """
    for limit in reversed(_ACTIVE_LIMITS):
        if limit.expired:
            return TimeLimitError(limit.message)
    return None


def _time_limit(seconds: float | None, label: str, index: int) -> time_limit:
    """A Ray task's :class:`time_limit` (``task_timeout``), its message naming ``label`` and the task."""
    return time_limit(
        seconds,
        f"{label}: task {index} ran past its time limit of {seconds:g} s (task_timeout) and was stopped; give each "
        "task less work (a smaller chunk) or a longer task_timeout"
        if seconds is not None
        else "",
    )


def run_processes(
    function: Callable, tasks: list, *, workers: int, label: str, on_result: Callable | None = None
) -> list:
    """``function(*task)`` for every task on ``workers`` processes of this machine (started fresh,
    not forked: a forked torch can hang on its thread pools); the results in task order.
    ``on_result(i, result)`` runs here as each finishes (in completion order).

    Raises
    ------
    WorkerError
        A worker process died before returning (killed, out of memory, crashed); ``label`` and
        the task's index name it.  An exception the function raised is re-raised as itself.
    InvalidOptionError
        ``workers`` is not a positive integer.
    """
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidOptionError(f"{label}: workers must be a positive integer; got {workers!r}")
    results = [None] * len(tasks)
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        pending = {pool.submit(function, *task): i for i, task in enumerate(tasks)}
        try:
            while pending:
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                for future in done:
                    i = pending.pop(future)
                    try:
                        results[i] = future.result()
                    except BrokenProcessPool as error:
                        raise WorkerError(
                            f"{label}: the worker process running task {i} stopped before returning ({error}); give "
                            "each task less work or the machine more memory"
                        ) from None
                    if on_result is not None:
                        on_result(i, results[i])
        finally:
            for future in pending:
                future.cancel()
    return results


@contextmanager
def _loopback():
    """While a new local cluster starts: Ray resolves a loopback node address to the machine's
    network address unless it runs in its single-machine mode (its default on macOS and Windows,
    switched by RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER); take that mode so that its servers listen on
    127.0.0.1 only."""
    from ray._private import ray_constants

    variable, saved = ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR, ray_constants.ENABLE_RAY_CLUSTER
    previous = os.environ.get(variable)
    os.environ[variable], ray_constants.ENABLE_RAY_CLUSTER = "0", False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved
        if previous is None:
            os.environ.pop(variable, None)
        else:
            os.environ[variable] = previous
