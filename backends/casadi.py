"""casadi's integrators: Radau collocation, and IDAS on the index-1 reduction.

Both build one casadi integrator per solve and call it once per sample (casadi integrates
one initial state per call).  ``casadi-collocation`` applies Radau IIA collocation with
``stages`` points and one finite element per step ``h`` to the system as compiled (index 2
is fine: its root finder solves the same stage equations as ``method="radau"``);
``casadi-idas`` needs index 1, so :func:`daemodel.solve` hands it the index-1 reduction and
the original constraints' drift is reported through :meth:`Solution.drift`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    DEFAULT_OUTPUT_POINTS,
    AbstractBackend,
    check_number,
    check_stages,
    fixed_grid,
    fixed_step_sweep,
    make_solution,
    output_times,
    tolerance_sweep,
)

from daemodel.errors import ConvergenceError, InvalidOptionError

# Steps of casadi-collocation over the interval when h is not given.
DEFAULT_STEPS = 100


@dataclass(frozen=True, kw_only=True)
class CollocationOptions:
    """Options of ``method="casadi-collocation"``.

    Attributes
    ----------
    stages : int
        Collocation points per step (casadi's ``interpolation_order``), Radau scheme.
    h : float, optional
        Step size; default: the interval in 100 steps.  Values are reported on the step grid.
    """

    stages: int = 3
    h: float | None = None

    def __post_init__(self) -> None:
        check_stages(self.stages)
        check_number("h", self.h, allow_none=True)


@dataclass(frozen=True, kw_only=True)
class IDASOptions:
    """Options of ``method="casadi-idas"``.

    Attributes
    ----------
    rtol, atol : float
        IDAS's relative and absolute tolerances.
    t_eval : array, optional
        Output times; default 101 equally spaced.
    max_num_steps : int
        IDAS's step limit per output interval.
    """

    rtol: float = 1e-8
    atol: float = 1e-10
    t_eval: object = None
    max_num_steps: int = 100_000

    def __post_init__(self) -> None:
        check_number("rtol", self.rtol)
        check_number("atol", self.atol)
        check_number("max_num_steps", self.max_num_steps, integer=True)
        if self.rtol < 1e-14:
            raise InvalidOptionError(f"rtol = {self.rtol:g} is below what float64 IDAS can deliver (>= 1e-14)")


def _dae(compiled) -> dict:
    dae = compiled.casadi_dae()
    return {key: dae[key] for key in ("x", "z", "p", "t", "ode", "alg") if key in dae}


def _run(integrator, name, compiled, start, grid) -> tuple[np.ndarray, dict]:
    """Call ``integrator`` for each sample; values (B, T, n+m) including t0, and casadi's stats."""

    B, T = start.size, len(grid)
    n, m = len(compiled.states), len(compiled.algebraics)
    out = np.empty((B, T + 1, n + m))
    out[:, 0, :n], out[:, 0, n:] = start.y0, start.z0
    for b in range(B):
        try:
            result = integrator(x0=start.y0[b], z0=start.z0[b], p=start.p[b])
        except RuntimeError as error:
            raise ConvergenceError(
                f"{name}: casadi failed for sample {b} of '{compiled.name}': {str(error).splitlines()[-1]}"
            ) from None
        out[b, 1:, :n] = np.asarray(result["xf"]).T.reshape(T, n)
        out[b, 1:, n:] = np.asarray(result["zf"]).T.reshape(T, m)
        if not np.all(np.isfinite(out[b])):
            raise ConvergenceError(f"{name}: casadi returned non-finite values for sample {b} of '{compiled.name}'")
    try:
        stats = {k: v for k, v in integrator.stats().items() if isinstance(v, (int, float, bool, str))}
    except (RuntimeError, AttributeError):
        stats = {}
    return out, {"batch": B, "casadi_calls": B, **stats}


class CollocationBackend(AbstractBackend):
    """``method="casadi-collocation"``: casadi's collocation integrator, Radau scheme."""

    name = "casadi-collocation"
    Options = CollocationOptions
    max_index = 2

    def work_precision(self, t_span, points):
        return fixed_step_sweep(t_span, points)

    def solve(self, compiled, t_span, start, options: CollocationOptions):
        import casadi

        h = options.h if options.h is not None else (t_span[1] - t_span[0]) / DEFAULT_STEPS
        grid = fixed_grid(t_span, h)
        began = time.perf_counter()
        integrator = casadi.integrator(
            "collocation",
            "collocation",
            _dae(compiled),
            float(grid[0]),
            [float(t) for t in grid[1:]],
            {
                "collocation_scheme": "radau",
                "interpolation_order": options.stages,
                "number_of_finite_elements": 1,
            },
        )
        values, stats = _run(integrator, self.name, compiled, start, grid[1:])
        wall = time.perf_counter() - began
        stats = {"stages": options.stages, "steps": len(grid) - 1, **stats}
        return make_solution(self, compiled, start, options, grid, values, wall, stats)


class IDASBackend(AbstractBackend):
    """``method="casadi-idas"``: SUNDIALS IDAS (BDF, variable order) on the index-1 reduction."""

    name = "casadi-idas"
    Options = IDASOptions
    max_index = 1

    def work_precision(self, t_span, points):
        return tolerance_sweep(points)

    def solve(self, compiled, t_span, start, options: IDASOptions):
        import casadi

        times = output_times(options.t_eval, t_span, np.linspace(*t_span, DEFAULT_OUTPUT_POINTS))
        grid = times[1:] if times[0] == t_span[0] else times
        began = time.perf_counter()
        integrator = casadi.integrator(
            "idas",
            "idas",
            _dae(compiled),
            float(t_span[0]),
            [float(t) for t in grid],
            {
                "abstol": options.atol,
                "reltol": options.rtol,
                "max_num_steps": options.max_num_steps,
                "calc_ic": False,  # solve() hands over consistent values
            },
        )
        values, stats = _run(integrator, self.name, compiled, start, grid)
        wall = time.perf_counter() - began
        if times[0] != t_span[0]:
            values = values[:, 1:]
        return make_solution(self, compiled, start, options, times, values, wall, stats)
