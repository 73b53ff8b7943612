"""What casadi-collocation and casadi-idas share: casadi's integrators built once per model and
kept (:func:`cached_integrator`), the model as casadi's DAE dict on each time scale (:func:`scaled_dae`:
:func:`dae_of`, :func:`shifted_dae`, :func:`normalised_dae`), one call per sample with casadi's output
captured (:func:`run_samples`), casadi's statistics and messages read back, and the check for non-finite values."""

from __future__ import annotations

import collections
import re
import threading

import numpy as np
from daemodel.backends.progress import captured_output

from daemodel.errors import ConvergenceError, DaemodelError, TimeSpanError
from daemodel.executors import struck_limit

# Options that stop casadi from printing a warning for every non-finite evaluation (tens of
# thousands of lines when Newton wanders into a singularity).
QUIET = {"show_eval_warnings": False}
# Integrators kept per model (least recently used dropped first): a sweep's tolerances or steps, a
# few start values; each holds its output times (a 20,000-step grid is 160 kB) and casadi's memory.
KEPT_INTEGRATORS = 32
# Lines of casadi's captured output quoted in an error that cannot be translated.
QUOTED_LINES = 3
# IDACalcIC's own artificial step (IDAS's hic = 0.001 x casadi's first_time): this share of IDAS's first step.
# Left to casadi, first_time is the last output time, and IDACalcIC, whose Newton iteration moves the algebraic
# variables by a share of hic z' (0.05 here), left them off their constraints: on the wheelset a trial solve over
# 2.2e-5 from consistent values (|g| 2.6e-12) started from z 13 of its tolerances off (|g| 1.5e-5), and IDAS
# failed its error test at every step down to 7e-17 (IDA_ERR_FAIL): its step was 2,600 times IDAS's first
# (8.4e-12).  At 1e-4 to 1e2 times it, IDAS's values there agreed with those from y'(t0) = f given exactly
# (calc_ic off) to 1e-14.
IC_STEP_SHARE = 1e-2


def cached_integrator(compiled, plugin: str, scale: str, t0, times, settings: dict):
    """casadi's ``plugin`` integrator of the model's DAE on the time scale ``scale`` (:func:`scaled_dae`) from
    ``t0`` to ``times``, built once per model, scale, times, settings and thread, and kept with the model (its
    setup, 2-30 ms, otherwise paid on every solve of a sweep); the :data:`KEPT_INTEGRATORS` most recently used
    are kept.

    Per thread: a solve reads the integrator's statistics after its calls, which another thread's call
    of a shared integrator would overwrite in between."""
    import json

    import casadi

    times = [float(t) for t in times]
    key = (plugin, scale, float(t0), tuple(times), json.dumps(settings, sort_keys=True), threading.get_ident())
    with _KEPT_LOCK:
        kept = compiled.cached("casadi-integrators", collections.OrderedDict)  # the most recently used last
        if key in kept:
            kept.move_to_end(key)
            return kept[key]
    built = casadi.integrator(plugin, plugin, scaled_dae(compiled, scale), float(t0), times, settings)
    with _KEPT_LOCK:
        kept[key] = built
        while len(kept) > KEPT_INTEGRATORS:
            kept.popitem(last=False)
    return built


_KEPT_LOCK = threading.Lock()  # (the kept integrators of every model: a cache shared by threads)


def consistent_start(first_output: float, step0: float | None) -> dict:
    """IDAS's settings to start from IDACalcIC's consistent ``y'(t0)`` (and z, from nearly consistent values):
    its artificial step :data:`IC_STEP_SHARE` of IDAS's first one, ``step0``, or IDAS's own first guess, 0.001 of
    the first output's distance (both on the integrator's own time)."""
    first = step0 if step0 is not None else 1e-3 * first_output
    if not first > 0.0:  # (IDACalcIC's step 0: it never returned, at t0 = 1e13 over 11 float64 spacings)
        raise TimeSpanError(
            f"casadi-idas: its first output lies at its start (IDACalcIC's step would be {first!r}, on which it "
            "never returns): the span is shorter than float64 resolves at its |t|; start t_span nearer 0 (shift the "
            "model's time)"
        )
    return {"calc_ic": True, "first_time": 1e3 * IC_STEP_SHARE * first}


def scaled_dae(compiled, scale: str) -> dict:
    """The model's casadi DAE on the time scale ``scale``: ``"own"`` (its t), ``"shifted"`` (the time since t0:
    :func:`shifted_dae`) or ``"normalised"`` (:func:`normalised_dae`), built once per model and kept with it
    (a substitution into every equation: built per solve, 344 of them took 0.37 s of the 956 humps' search)."""
    if scale not in TIME_SCALES:
        raise ValueError(f"unknown time scale {scale!r}; the scales are {', '.join(TIME_SCALES)}")
    return compiled.cached(("casadi-dae", scale), lambda: TIME_SCALES[scale](dae_of(compiled)))


def dae_of(compiled) -> dict:
    dae = compiled.casadi_dae()
    return {key: dae[key] for key in ("x", "z", "p", "t", "ode", "alg") if key in dae}


def last_number(pattern: str, text: str) -> float | None:
    """The last number ``pattern`` captures in ``text`` (casadi's latest message comes last)."""
    found = re.findall(pattern, text)
    return float(found[-1]) if found else None


def last_lines(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return " | ".join(lines[-QUOTED_LINES:])


def run_samples(call, compiled, start, T: int, explain) -> np.ndarray:
    """``call(sample)`` for each sample, quietly: values (B, T + 1, n + m) with t0 first.

    ``call`` returns casadi's result (``xf`` (n, T), ``zf`` (m, T)) or raises casadi's
    RuntimeError; ``explain(sample, error, printed)`` turns that failure (its text and what
    casadi printed meanwhile) into the exception to raise.
    """
    B = start.size
    n, m = len(compiled.states), len(compiled.algebraics)
    out = np.empty((B, T + 1, n + m))
    out[:, 0, :n], out[:, 0, n:] = start.y0, start.z0
    for b in range(B):
        with captured_output() as printed:
            try:
                result = call(b)
            except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
                raise
            except RuntimeError as error:
                failure = struck_limit() or explain(b, str(error), printed.getvalue())
            else:
                failure = None
        if failure is not None:
            raise failure from None
        out[b, 1:, :n] = np.asarray(result["xf"]).T.reshape(T, n)
        out[b, 1:, n:] = np.asarray(result["zf"]).T.reshape(T, m)
    return out


def integrator_stats(integrator) -> dict:
    """casadi's scalar statistics of the integrator's last call."""
    try:
        return {k: v for k, v in integrator.stats().items() if isinstance(v, (int, float, bool, str))}
    except (RuntimeError, AttributeError):
        return {}


def first_non_finite(name: str, compiled, times, values, fix: str, what: str = "") -> ConvergenceError | None:
    """The error for the earliest non-finite value of any sample, or None when all are finite.

    ``values`` (B, T, n + m) are the solution's, or (``what="f at"``) the right-hand sides ``f``
    and constraints ``g`` evaluated there.
    """
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    sample, k, j = min(zip(*np.nonzero(bad), strict=True), key=lambda hit: (hit[1], hit[0]))
    names = (*compiled.state_names, *compiled.algebraic_names)
    if what:
        rows = (*(f"{y}'" for y in compiled.state_names), *compiled.constraint_names)
        subject = f"the right-hand side of {rows[j]} is not finite at the returned values"
    else:
        subject = f"'{names[j]}' is not finite"
    return ConvergenceError(
        f"{name}: {subject} at t = {times[k]:.6g} (sample {sample} of '{compiled.name}', "
        f"after t = {times[max(k - 1, 0)]:.6g}): the solution may be singular there or leave the domain of the "
        f"equations; {fix}"
    )


def shifted_dae(dae: dict) -> dict:
    """``dae`` on the time since the start, ``t = t0 + s``, with ``t0`` appended to its parameters: the
    integrator's own time ``s`` starts at 0, where float64 resolves its steps.

    On t itself IDAS's time advanced by steps that t + h rounds to t's spacing, and its outputs were read
    off that time: x' = v, v' = -x from t0 = 1e13 over 2 at rtol 1e-8 ended 0.12 off, y' = cos(t) 44 off,
    both "success".  Shifted, only t's rounding inside f and g is left (flagged where it matters:
    :mod:`daemodel.solving.resolution`)."""
    import casadi

    t0, s = casadi.SX.sym("t0"), casadi.SX.sym("s")
    now = t0 + s
    return {
        "x": dae["x"],
        "z": dae["z"],
        "p": casadi.vertcat(dae["p"], t0),
        "t": s,
        "ode": casadi.substitute(dae["ode"], dae["t"], now),
        "alg": casadi.substitute(dae["alg"], dae["t"], now),
    }


def normalised_dae(dae: dict) -> dict:
    """``dae`` on normalised time ``t = tau + h s``, ``s`` in [0, 1], with ``tau`` and ``h`` appended to
    its parameters: one integrator from s = 0 to 1 serves any step or interval."""
    import casadi

    tau, h, s = casadi.SX.sym("tau"), casadi.SX.sym("h"), casadi.SX.sym("s")
    now = tau + h * s
    return {
        "x": dae["x"],
        "z": dae["z"],
        "p": casadi.vertcat(dae["p"], tau, h),
        "t": s,
        "ode": h * casadi.substitute(dae["ode"], dae["t"], now),
        "alg": casadi.substitute(dae["alg"], dae["t"], now),
    }


# The time scales an integrator runs on (cached_integrator's ``scale``): the DAE on each, from the model's own.
TIME_SCALES = {"own": lambda dae: dae, "shifted": shifted_dae, "normalised": normalised_dae}
