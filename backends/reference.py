"""A tight-tolerance reference: scipy's ``solve_ivp`` on the underlying ODE.

The algebraic variables are eliminated: ``z(t, y)`` solves the determining equations (the
constraints differentiated until z appears: ``g = 0`` at index 1, ``g_y f = 0`` at index 2,
...) by Newton, so the integrator sees the ODE ``y' = f(t, y, z(t, y))``.  The functions are
sympy's numpy lambdas, independent of the torch code generator that ``method="radau"`` uses,
and the default is DOP853 at ``rtol = atol = 1e-12``; pass ``integrator="Radau"`` for stiff
problems.  This is the reference the paper used for the pendulum, which has no closed form.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    DEFAULT_OUTPUT_POINTS,
    AbstractBackend,
    check_number,
    make_solution,
    output_times,
    tolerance_sweep,
)

from daemodel.errors import ConvergenceError, InvalidOptionError
from daemodel.init import NumericSystem

INTEGRATORS = ("DOP853", "RK45", "Radau", "BDF", "LSODA")
# Newton for z(t, y): iterations, and the relative size of the last step that ends it.
Z_NEWTON_MAXITER, Z_NEWTON_TOL = 30, 1e-15


@dataclass(frozen=True, kw_only=True)
class ReferenceOptions:
    """Options of ``method="reference"``.

    Attributes
    ----------
    rtol, atol : float
        solve_ivp's tolerances (default 1e-12 both).
    integrator : str
        solve_ivp's method: DOP853 (default), RK45, Radau, BDF or LSODA.
    t_eval : array, optional
        Output times; default 101 equally spaced.
    """

    rtol: float = 1e-12
    atol: float = 1e-12
    integrator: str = "DOP853"
    t_eval: object = None

    def __post_init__(self) -> None:
        check_number("rtol", self.rtol)
        check_number("atol", self.atol)
        if self.integrator not in INTEGRATORS:
            raise InvalidOptionError(f"integrator must be one of {', '.join(INTEGRATORS)}; got {self.integrator!r}")


class ReferenceBackend(AbstractBackend):
    """``method="reference"``: scipy on the underlying ODE, algebraic variables by Newton."""

    name = "reference"
    Options = ReferenceOptions
    max_index = 3

    def work_precision(self, t_span, points):
        return tolerance_sweep(points)

    def solve(self, compiled, t_span, start, options: ReferenceOptions):
        from scipy.integrate import solve_ivp

        times = output_times(options.t_eval, t_span, np.linspace(*t_span, DEFAULT_OUTPUT_POINTS))
        numeric = NumericSystem(compiled.t, compiled.states, compiled.algebraics, compiled.parameters)
        f = numeric.function(compiled.rhs)
        determining = [c.determining for c in compiled.constraints]
        H, Hz = numeric.function(determining), numeric.jacobian(determining, compiled.algebraics)
        n, m = len(compiled.states), len(compiled.algebraics)
        values = np.empty((start.size, len(times), n + m))
        stats = {"integrator": options.integrator, "batch": start.size, "nfev": 0, "njev": 0, "nlu": 0}
        began = time.perf_counter()
        for b in range(start.size):
            p = start.p[b]
            guess = [start.z0[b].copy()]

            def z_of(t, y, p=p, guess=guess):
                z = guess[0]
                for _ in range(Z_NEWTON_MAXITER):
                    step = np.linalg.solve(Hz(t, y, z, p), -H(t, y, z, p)) if m else z
                    z = z + step
                    if not m or np.max(np.abs(step)) <= Z_NEWTON_TOL * (1 + np.max(np.abs(z))):
                        break
                guess[0] = z
                return z

            def rhs(t, y, p=p):
                return f(t, y, z_of(t, y), p)

            with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
                try:
                    result = solve_ivp(
                        rhs,
                        t_span,
                        start.y0[b],
                        method=options.integrator,
                        t_eval=times,
                        rtol=options.rtol,
                        atol=options.atol,
                        dense_output=False,
                    )
                except (FloatingPointError, np.linalg.LinAlgError) as error:
                    raise ConvergenceError(
                        f"reference: the underlying ODE of '{compiled.name}' failed for sample {b}: {error}; "
                        "the algebraic variables may not be determined along the solution"
                    ) from None
            if result.status != 0:
                raise ConvergenceError(f"reference: solve_ivp failed for sample {b}: {result.message}")
            Y = result.y.T
            guess[0] = start.z0[b].copy()
            Z = np.array([z_of(t, y) for t, y in zip(times, Y, strict=True)]).reshape(len(times), m)
            values[b] = np.concatenate([Y, Z], axis=1)
            for key in ("nfev", "njev", "nlu"):
                stats[key] += int(getattr(result, key))
        wall = time.perf_counter() - began
        return make_solution(self, compiled, start, options, times, values, wall, stats)
