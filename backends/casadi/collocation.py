"""``method="casadi-collocation"``: casadi's collocation integrator, Radau IIA with ``stages``
points and one finite element per step ``h``, applied to the system as compiled (index 2 is fine:
its root finder solves the same stage equations as ``method="radau"``), checked step by step.

Trust: casadi-collocation is fixed-step, so nothing inside it notices a step over a singularity
that lands on a finite root of the stage equations.  Every step is therefore checked after the
solve: it is repeated from the same start with one more collocation point (Radau IIA of order
2s+1, one mapped casadi call for all steps and samples), and the difference estimates the step's
local error.  An estimate above :data:`LOCAL_ERROR_BOUND` times the variable's scale raises
:class:`~daemodel.errors.LocalErrorBoundError`.  A step that returned its start value although f
is not zero there (casadi's root finder gave up and returned its last iterate) is named too.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    DEFAULT_ESTIMATE_BOUND,
    LOCAL_ERROR_BOUND,
    AbstractBackend,
    estimate_status,
    make_solution,
)
from daemodel.backends.casadi.plumbing import (
    QUIET,
    cached_integrator,
    dae_of,
    first_non_finite,
    integrator_stats,
    last_lines,
    last_number,
    normalised_dae,
    run_samples,
)
from daemodel.backends.checks import check_output_memory, check_stages, set_number
from daemodel.backends.grids import SWEEP_FIRST_STEPS, fixed_grid, fixed_step_sweep, output_times
from daemodel.backends.progress import captured_output

from daemodel.dense import AbstractDenseOutput, CollocationPolynomials, step_owners
from daemodel.errors import ConvergenceError, LocalErrorBoundError
from daemodel.tableau import radau_iia

# Steps of casadi-collocation over the interval when h is not given.
DEFAULT_STEPS = 100
# casadi-collocation's root finder: absolute residual tolerance per unit of the solution's size
# 1 + max|u0| (casadi's default 1e-12 assumes unit size; the squeezing mechanism's w ~ 1e4-4e5
# leaves residuals at 1e-11 from rounding alone).
ROOT_ABSTOL = 1e-12
# A casadi-collocation step that returns its start value is steady, not stuck, when its change h |f|
# is below the root finder's abstol or this many units in the last place of the value: rounding in
# f (a constraint met to the last bit, x' = 1e-14 at rest) moves nothing that the values can show.
STEADY_ULPS = 16
# casadi-collocation's dense output: a step's stages solved again must end at the step's own end value
# to this much, relative to 1 + its size (the root finder's tolerance is 1e-12 of it).
DENSE_END_MATCH = 1e-8
# What an adaptive alternative to a fixed step is called in messages.
ADAPTIVE_FIX = 'take a smaller h, or an adaptive method (method="radau" with rtol=..., or method="casadi-idas")'


@dataclass(frozen=True, kw_only=True)
class CollocationOptions:
    """Options of ``method="casadi-collocation"``.

    Attributes
    ----------
    stages : int
        Collocation points per step (casadi's ``interpolation_order``), Radau scheme.
    h : float, optional
        Step size; default: the interval in 100 steps.  Values are reported on the step grid.
    t_eval : array, optional
        Output times instead of the step grid, within the interval.  casadi does not expose its
        collocation polynomials, so the values there are :meth:`Solution.at`'s: cubic Hermite
        states through the step grid with the model's f (O(h^4) on top of the method's error)
        and algebraic values solved from the constraints.
    estimate_bound : float
        A run whose largest local error estimate (a step repeated with one more collocation
        point, in units of the solution's size ``1 + max |u|``) exceeds this is flagged (status
        ``"flagged: ..."`` naming the step, and a :class:`~daemodel.errors.LocalErrorWarning`);
        every step's estimate is in ``stats["local_error_estimates"]``.  Default
        :data:`~daemodel.backends.base.DEFAULT_ESTIMATE_BOUND`.
    """

    stages: int = 3
    h: float | None = None
    t_eval: object = None
    estimate_bound: float = DEFAULT_ESTIMATE_BOUND

    def __post_init__(self) -> None:
        check_stages(self.stages)
        set_number(self, "h", allow_none=True)
        set_number(self, "estimate_bound")


def stuck_step(
    compiled, grid, values, slopes, root_abstol: float = ROOT_ABSTOL, stage_increments=None
) -> ConvergenceError | None:
    """The error for the first step that returned its start value exactly although f is not zero
    there: casadi's root finder gave up (f or g turned NaN inside its Newton iteration, with casadi's
    evaluation warnings off) and casadi returned its last iterate instead of failing.

    A step whose whole change ``h |f|`` is within rounding of its start is not stuck but steady
    (a start at rest up to rounding, ``x' = 1e-14``, or a constraint met to the last bit): the
    collocation residual at the start guess is ``h f`` at the stages, so the root finder accepts that
    guess once ``h |f| < root_abstol``; and a change below :data:`STEADY_ULPS` units in the last place
    of ``u`` is not a change that the values can show.  ``stage_increments(sample, k)``: step ``k``'s stage
    increments from its start value, ``h A f`` (s, n) with f at its collocation times there (the root finder's
    first Newton step, without J): within that rounding at every stage, the step's own change is, and its root
    finder stops at the start value (on its residual, or on a Newton step below its ``abstolStep``, 1e-12): x' = 2
    (t - h) from 0 over one step h = 7.4e-7 (h |f| 1.1e-12 at the start, its increments 0.5e-12 at most) and
    x = (t - c)^2 - 3.6e-13 across its crossing (h |f| 1.5e-12, increments 0.2e-12) were named stuck.
    """
    n = len(compiled.states)
    same = np.all(values[:, 1:] == values[:, :-1], axis=2)  # (B, T-1): step k returned u_k
    h = np.diff(grid)[None, :, None]
    rounding = np.maximum(root_abstol, STEADY_ULPS * np.finfo(values.dtype).eps * np.abs(values[:, :-1, :n]))
    moving = np.any(h * np.abs(slopes[:, :-1, :n]) > rounding, axis=2)  # f(t_k, u_k) moves u_k visibly
    for sample, k in np.argwhere(same & moving):  # (each a step that f at its start says moves)
        sample, k = int(sample), int(k)
        if stage_increments is None or np.any(np.abs(stage_increments(sample, k)) > rounding[sample, k]):
            return _stuck(compiled, grid, sample, k)
    return None


def _stuck(compiled, grid, sample: int, k: int) -> ConvergenceError:
    """The error of :func:`stuck_step` for step ``k`` of ``sample``."""
    return ConvergenceError(
        f"casadi-collocation: step {k + 1} from t = {grid[k]:.6g} (h = {grid[k + 1] - grid[k]:.3g}) of sample {sample} "
        f"of '{compiled.name}' returned its start value although f is not zero there: casadi's Newton iteration "
        "gave up (f or g likely turned NaN inside it, e.g. sqrt or log of a negative value) and casadi returned its "
        'last iterate; take a smaller h, or an adaptive method (method="radau" with rtol=..., or method="casadi-idas")'
    )


def _right_hand_sides(dae, grid, values, parameters) -> np.ndarray:
    """``[f, g]`` at every returned point, shape (B, T, n + m): one mapped casadi call per sample."""
    import casadi

    fg = casadi.Function("fg", [dae["t"], dae["x"], dae["z"], dae["p"]], [casadi.vertcat(dae["ode"], dae["alg"])])
    n = dae["x"].shape[0]
    out = np.empty_like(values)
    mapped = fg.map(len(grid))
    for b in range(values.shape[0]):
        with np.errstate(all="ignore"), captured_output():
            result = mapped(
                grid, values[b, :, :n].T, values[b, :, n:].T, np.repeat(parameters[b][:, None], len(grid), 1)
            )
        out[b] = np.asarray(result).T
    return out


class LocalErrorCheck:
    """The a-posteriori local error estimate of every casadi-collocation step.

    Each step from ``u_k`` to ``u_{k+1}`` is repeated from ``u_k`` with ``stages + 1`` Radau
    points (order 2s + 1 against the step's 2s - 1), so ``|u_{k+1} - û_{k+1}|`` estimates the
    step's own local error (asymptotically exactly, for a smooth solution).
    As in RADAU5, an algebraic variable determined through an index-k constraint has its
    estimate multiplied by ``h^(k-1)`` (its values are only accurate to a lower order).  The
    estimate is divided by the variable's scale ``1 + max|u|`` over the sample's trajectory.

    The repeat solves the step on normalised time ``t = tau + h s``, ``s`` in [0, 1], so one
    casadi Function, mapped over all steps of all samples, serves any grid.  Its root finder
    does not raise: a step whose repeat has no solution gets a large or non-finite estimate.
    """

    def __init__(self, compiled, stages: int, dae: dict | None = None, root_abstol: float = ROOT_ABSTOL):
        """``dae``: the system's casadi DAE dict when the caller has built it already; ``root_abstol``:
        the root finder's residual tolerance (see :data:`ROOT_ABSTOL`)."""
        import casadi

        dae = dae if dae is not None else dae_of(compiled)
        self.step = casadi.integrator(
            "collocation_check",
            "collocation",
            normalised_dae(dae),
            0.0,
            1.0,
            {
                "collocation_scheme": "radau",
                "interpolation_order": stages + 1,
                "number_of_finite_elements": 1,
                "rootfinder_options": {"error_on_fail": False, "abstol": root_abstol, **QUIET},
                **QUIET,
            },
        )
        self.compiled = compiled
        self.stages = stages
        self.z_index = np.array(compiled.algebraic_index, dtype=float)

    def __call__(self, grid, values, parameters) -> np.ndarray:
        """Estimates, shape (B, N, n + m), in units of each variable's scale ``1 + max |u|``, for
        ``values`` (B, N + 1, n + m)."""
        B, N = values.shape[0], len(grid) - 1
        n = len(self.compiled.states)
        h = np.diff(grid)
        starts = values[:, :-1].reshape(B * N, -1).T  # (n + m, B N): every step of every sample
        p = np.concatenate(
            [np.repeat(parameters, N, axis=0).T, np.tile(grid[:-1], B)[None, :], np.tile(h, B)[None, :]], axis=0
        )
        with captured_output():
            repeat = self.step.map(B * N)(x0=starts[:n], z0=starts[n:], p=p)
        again = np.concatenate([np.asarray(repeat["xf"]), np.asarray(repeat["zf"])], axis=0).T.reshape(B, N, -1)
        scale = 1.0 + np.max(np.abs(values), axis=1, keepdims=True)
        return np.nan_to_num(np.abs(values[:, 1:] - again) / scale, nan=np.inf)

    def weighted(self, grid, estimates) -> np.ndarray:
        """``estimates`` with an index-k algebraic variable's multiplied by ``h^(k-1)`` (RADAU5's
        units, which :data:`LOCAL_ERROR_BOUND` bounds)."""
        n = len(self.compiled.states)
        out = estimates.copy()
        out[..., n:] *= np.diff(grid)[None, :, None] ** (self.z_index - 1)
        return out

    def status(self, name: str, grid, estimates, bound: float, batched: bool) -> str:
        """ "success", or flagged at the step with the largest estimate beyond ``bound``
        (:func:`~daemodel.backends.base.estimate_status`)."""
        if not estimates.size:
            return "success"
        sample, step, j = np.unravel_index(int(np.argmax(estimates)), estimates.shape)
        variable = (*self.compiled.state_names, *self.compiled.algebraic_names)[j]
        t, h = grid[step], grid[step + 1] - grid[step]
        where = f"step {step + 1} from t = {t:.6g} (h = {h:.3g}), in '{variable}'"
        where += f", sample {sample}" if batched else ""
        return estimate_status(name, float(estimates[sample, step, j]), bound, where)

    def raise_beyond_bound(self, name: str, grid, estimates) -> None:
        """:class:`LocalErrorBoundError` for the earliest step whose estimate exceeds the bound."""
        beyond = estimates > LOCAL_ERROR_BOUND
        if not beyond.any():
            return
        step = int(np.argmax(beyond.any(axis=(0, 2))))
        sample = int(np.argmax(beyond[:, step].any(axis=1)))
        j = int(np.argmax(estimates[sample, step]))
        n = len(self.compiled.states)
        variable = (*self.compiled.state_names, *self.compiled.algebraic_names)[j]
        power = int(self.z_index[j - n]) - 1 if j >= n else 0
        scale = f"1 + max|{variable}|" + (f" over h^{power}" if power else "")
        t, h = grid[step], grid[step + 1] - grid[step]
        raise LocalErrorBoundError(
            f"{name}: step {step + 1} from t = {t:.6g} to {t + h:.6g} (h = {h:.3g}) of sample {sample} of "
            f"'{self.compiled.name}' is not trustworthy: the local error estimate of '{variable}' is "
            f"{estimates[sample, step, j]:.3g} times its scale {scale}, beyond LOCAL_ERROR_BOUND = "
            f"{LOCAL_ERROR_BOUND:g} (a step with {self.stages + 1} collocation points from the same start disagrees): "
            f"the solution may be singular there; {ADAPTIVE_FIX}"
        )


class CollocationStages:
    """The stage values of casadi-collocation's steps, for its dense output.

    casadi keeps its collocation polynomials to itself; they are determined by each step's start and
    length, so they are found again here: the Radau IIA stage equations of the step (the equations
    casadi's root finder solved, ``X_i = u_k + h sum_j a_ij f(t_k + c_j h, X_j, Z_j)``, ``0 = g(t_k + c_i
    h, X_i, Z_i)``), solved by casadi's Newton from the straight line between the step's two ends, in
    one mapped call for all the steps asked for.  Their root is the one casadi found where the end
    value agrees: :meth:`__call__` checks it.
    """

    def __init__(self, compiled, stages: int, dae: dict, root_abstol: float):
        import casadi

        tableau = radau_iia(stages)
        A, self.c = np.asarray(tableau.A, dtype=float), np.asarray(tableau.c, dtype=float)
        n, m = dae["x"].shape[0], dae["z"].shape[0]
        f = casadi.Function("f", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"]])
        g = casadi.Function("g", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["alg"]])
        X, Z = casadi.SX.sym("X", n, stages), casadi.SX.sym("Z", m, stages)
        x0, p = casadi.SX.sym("x0", n), casadi.SX.sym("p", dae["p"].shape[0])
        tau, h = casadi.SX.sym("tau"), casadi.SX.sym("h")
        slopes = [f(tau + self.c[j] * h, X[:, j], Z[:, j], p) for j in range(stages)]
        equations = []
        for i in range(stages):
            equations.append(X[:, i] - x0 - h * sum(A[i, j] * slopes[j] for j in range(stages)))
            equations.append(g(tau + self.c[i] * h, X[:, i], Z[:, i], p))
        unknowns = casadi.vertcat(*[casadi.vertcat(X[:, i], Z[:, i]) for i in range(stages)])
        residual = casadi.Function("stages", [unknowns, casadi.vertcat(x0, p, tau, h)], [casadi.vertcat(*equations)])
        options = {"abstol": root_abstol, "error_on_fail": False, **QUIET}
        self.solve = casadi.rootfinder("collocation_stages", "newton", residual, options)
        self.n, self.stages = n, stages

    def __call__(self, starts, ends, parameters, tau, h) -> np.ndarray:
        """Stage values ``(K, s, n+m)`` of ``K`` steps from ``starts`` (K, n+m) to ``ends`` (K, n+m),
        with ``parameters`` (K, k), start times ``tau`` (K,) and lengths ``h`` (K,).

        Raises
        ------
        ConvergenceError
            Where Newton finds no root, or one whose last stage is not the step's end value (casadi's).
        """
        K, D = starts.shape
        guess = starts[:, None] + self.c[None, :, None] * (ends - starts)[:, None]  # (K, s, n+m)
        inputs = np.concatenate([starts[:, : self.n], parameters, tau[:, None], h[:, None]], axis=1)
        with captured_output():
            found = self.solve.map(K)(guess.reshape(K, -1).T, inputs.T)
        stages = np.asarray(found).T.reshape(K, self.stages, D)
        scale = 1.0 + np.abs(ends).max(axis=1)
        mismatch = np.abs(stages[:, -1] - ends).max(axis=1) / scale
        bad = ~(mismatch <= DENSE_END_MATCH)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ConvergenceError(
                f"casadi-collocation's dense output: the stage equations of the step from t = {tau[k]:.6g} (h = "
                f"{h[k]:.3g}) solved again from its ends give an end value {mismatch[k]:.3g} (relative) away from the "
                "step's own: no polynomial between those outputs; ask for the times with t_eval instead"
            )
        return stages


@dataclass(frozen=True, eq=False)
class CollocationSteps(AbstractDenseOutput):
    """casadi-collocation's dense output: each step's collocation polynomial, its stages found again by
    :class:`CollocationStages` for the steps a query needs (and kept for the next query)."""

    grid: np.ndarray
    values: np.ndarray  # (B, N + 1, n+m)
    parameters: np.ndarray  # (B, k)
    stages: CollocationStages
    _found: dict = dataclasses.field(default_factory=dict)  # step -> (B, s, n+m)

    @property
    def description(self) -> str:
        return f"each step's collocation polynomial (degree {self.stages.stages}), its stages solved again"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        B = len(self.values)
        lengths = np.diff(self.grid)
        step, _ = step_owners(self.grid[:-1], lengths, times)
        needed = [k for k in np.unique(step).tolist() if k not in self._found]
        if needed:
            rows = np.array(needed)
            starts = self.values[:, rows].reshape(-1, self.values.shape[2])  # (B * len, n+m), sample-major
            ends = self.values[:, rows + 1].reshape(-1, self.values.shape[2])
            found = self.stages(
                starts,
                ends,
                np.repeat(self.parameters, len(rows), axis=0),
                np.tile(self.grid[rows], B),
                np.tile(lengths[rows], B),
            ).reshape(B, len(rows), self.stages.stages, -1)
            for j, k in enumerate(needed):
                self._found[k] = found[:, j]
        used = np.unique(step)
        nodes = np.stack([np.concatenate([self.values[:, k, None], self._found[k]], axis=1) for k in used], axis=1)
        within = CollocationPolynomials(self.stages.c, self.grid[used], lengths[used], nodes)
        out = within(times)
        on_grid = np.isin(times, self.grid)  # (a grid time: the step's own value, not its re-solved last stage)
        out[:, on_grid] = self.values[:, np.searchsorted(self.grid, times[on_grid])]
        return out


class CollocationBackend(AbstractBackend):
    """``method="casadi-collocation"``: casadi's collocation integrator, Radau scheme, checked step by step.

    ``stats["max_local_error_estimate"]`` is the largest estimate of :class:`LocalErrorCheck`
    over all steps, samples and variables, in units of the variable's scale (the quantity that
    :data:`LOCAL_ERROR_BOUND` bounds).
    """

    name = "casadi-collocation"
    Options = CollocationOptions
    max_index = 2

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return fixed_step_sweep(t_span, points, steps)

    def solve(self, compiled, t_span, start, options: CollocationOptions):
        h = options.h if options.h is not None else (t_span[1] - t_span[0]) / DEFAULT_STEPS
        grid = fixed_grid(t_span, h)
        points = len(grid) + len(output_times(options.t_eval, t_span, ()))  # t_eval validated first
        check_output_memory(self.name, compiled, start.size, points)
        began = time.perf_counter()
        dae = dae_of(compiled)
        # casadi's Newton stops on |residual| < abstol (default 1e-12, for unit-size values): scale it
        # with the solution, or mechanisms with accelerations of 1e4-1e6 never reach it (rounding)
        root_abstol = ROOT_ABSTOL * (1.0 + float(np.abs(np.concatenate([start.y0, start.z0], axis=1)).max(initial=0)))
        plugin_options = {
            "collocation_scheme": "radau",
            "interpolation_order": options.stages,
            "number_of_finite_elements": 1,
            "rootfinder_options": {"abstol": root_abstol, **QUIET},
            **QUIET,
        }
        # built once per model, grid and settings, as radau builds its functions once: sweeps and
        # repeated solves pay the setup once
        integrator = cached_integrator(compiled, "collocation", "own", grid[0], grid[1:], plugin_options)
        check = compiled.cached(
            ("casadi-collocation-check", options.stages, root_abstol),
            lambda: LocalErrorCheck(compiled, options.stages, dae, root_abstol),
        )
        # (the dense output's stage solver: made in the solve, before, where it was a chain of 20 pendulums'
        # first solve's 15 ms of CPU, issue 42)
        stage_solver = compiled.cached(
            ("casadi-collocation-stages", options.stages, root_abstol),
            lambda: CollocationStages(compiled, options.stages, dae, root_abstol),
        )
        setup = time.perf_counter() - began  # building the integrators: reported apart from the solve
        began = time.perf_counter()

        def call(b):
            return integrator(x0=start.y0[b], z0=start.z0[b], p=start.p[b])

        def explain(sample, error, printed):
            return collocation_failure(error, printed, sample=sample, model=compiled.name, grid=grid)

        values = run_samples(call, compiled, start, len(grid) - 1, explain)
        stats = {"batch": start.size, "casadi_calls": start.size, **integrator_stats(integrator)}
        failure = first_non_finite(self.name, compiled, grid, values, ADAPTIVE_FIX)
        if failure is None:  # casadi's root finder returns its last iterate when f turns NaN inside a step
            slopes = _right_hand_sides(dae, grid, values, start.p)
            tableau = radau_iia(options.stages)  # (casadi's collocation: Radau's times)
            A, nodes, n = np.asarray(tableau.A, dtype=float), np.asarray(tableau.c, dtype=float), len(compiled.states)

            def stage_increments(b: int, k: int) -> np.ndarray:  # (h A f at step k's collocation times, its start)
                h = grid[k + 1] - grid[k]
                at_start = np.repeat(values[b : b + 1, k : k + 1], len(nodes), axis=1)
                return h * A @ _right_hand_sides(dae, grid[k] + nodes * h, at_start, start.p[b : b + 1])[0, :, :n]

            failure = first_non_finite(self.name, compiled, grid, slopes, ADAPTIVE_FIX, "f at") or stuck_step(
                compiled, grid, values, slopes, root_abstol, stage_increments
            )
        if failure is not None:
            raise failure
        estimates = check(grid, values, start.p)
        weighted = check.weighted(grid, estimates)
        check.raise_beyond_bound(self.name, grid, weighted)
        stats = {
            "stages": options.stages,
            "steps": len(grid) - 1,
            "max_local_error_estimate": float(weighted.max(initial=0.0)),
            "local_error_estimates": estimates.max(axis=(0, 2), initial=0.0).tolist(),
            **stats,
        }
        status = check.status(self.name, grid, estimates, options.estimate_bound, start.batched)
        settings = {k: v for k, v in dataclasses.asdict(options).items() if k != "t_eval"}
        dense = CollocationSteps(grid, values, np.asarray(start.p, dtype=float), stage_solver)
        times = grid
        if options.t_eval is not None:
            times = output_times(options.t_eval, t_span, grid)
            values = dense(times)
        wall = time.perf_counter() - began
        return make_solution(
            self,
            compiled,
            start,
            options,
            times,
            values,
            wall,
            stats,
            settings,
            status=status,
            setup_time=setup,
            dense=dense,
        )


def collocation_failure(error: str, printed: str, *, sample: int, model: str, grid) -> ConvergenceError:
    """casadi-collocation's failure as one line, from casadi's exception text and what it printed.

    A root-finder failure comes with an input dump that names the step ("Input 0 (t): 0.99",
    "Input 1 (h): 0.03"); anything else quotes casadi's last lines.
    """
    name = CollocationBackend.name
    t, h = last_number(r"Input 0 \(t\): (\S+)", printed), last_number(r"Input 1 \(h\): (\S+)", printed)
    if t is None or h is None or "rootfinder" not in error:
        return ConvergenceError(
            f"{name}: casadi failed for sample {sample} of '{model}': {last_lines(error)}; {ADAPTIVE_FIX}"
        )
    step = int(np.searchsorted(grid, t + 0.5 * h))
    return ConvergenceError(
        f"{name}: casadi's Newton iteration did not solve the collocation equations of step {step} from "
        f"t = {t:.6g} to {t + h:.6g} (h = {h:.3g}) for sample {sample} of '{model}'; the solution may be "
        f"singular there; {ADAPTIVE_FIX}"
    )
