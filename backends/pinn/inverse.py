"""The Radau-PINN's inverse mode: the segment networks and unknown parameters trained together on
the Radau stage residual and a data misfit (the engine behind ``dm.fit(..., method="pinn")``).

The joint problem.  One network per segment of the grid (:mod:`.segments`), chained: segment k's
networks take the previous segment's predicted end value as their input and as their ``y_n``, so
continuity holds exactly, by construction (the rollout the certificate checks), not as a penalty.
The parameters to estimate are a torch leaf ``q`` in a space that keeps their bounds
(:class:`~.inverse_inputs.Transform`).  The residual is the Radau stage residual of every segment
(:func:`daemodel.collocation.stage_residual`, the rows Newton zeroes, with ``p`` the trainable
parameters) and the misfit is each datum minus the segment's collocation polynomial through its
start and its predicted stages (:func:`daemodel.collocation.lagrange_matrix`: what the Solution's
dense output evaluates), divided by the spread of that output's data.

How it trains.  First the networks are trained at the starting parameter values, segment after
segment, by the forward mode (:func:`.segments.train_segments`): every network sits on the Radau
solution at ``start``.  Then Gauss-Newton on the networks and the parameters together, with the
Radau residual as an equality constraint (the limit of an infinite residual weight): each step
linearises the residual R and the misfit d in the networks' output biases ``b`` (which move the
outputs one for one, so this is Newton on the stage values, as the forward mode's finish) and in
``q``; ``db = -R_b^+ (R + R_q dq)`` keeps the linearised residual zero, and ``dq`` minimises the
linearised misfit along it (Levenberg-Marquardt on q, Nielsen's damping).  After each step Newton
on ``b`` alone brings R back to ``config.tol`` before the misfit is compared, so the misfit that
decides is the one of networks on the Radau solution.  The hidden layers keep the weights the
forward training gave them; they still act, since every segment's input moves with the
segments before it.

Initial values.  y0 is known and fixed.  z0 follows the parameters: the compiler's algebraic
solve at t0 at every new value, with dz0/dq from its determining equations (implicit
differentiation).  A z-free constraint level (index 2 or 3) that involves a fitted parameter is
refused (:class:`~daemodel.errors.FittedConstraintError`): y0 would satisfy it at one value only.

Cost.  The Jacobians are dense (every residual and datum against every output bias of every
segment: (S (s+1) D)^2 entries for S segments and D variables) and come from reverse-mode
autodiff through the chained rollout; fine for the tens of segments and few variables of a
parameter fit (0.1-0.3 s per Jacobian at 400 unknowns), not for hundreds of segments of a large
model.

Why not a weighted sum ``w |R|^2 + |d|^2`` under Adam then L-BFGS (the usual PINN inverse loss):
with noisy data its minimiser lies off the Radau solution by O(noise / w), which the certificate
then reports as distance; and it is slow.  Measured on ``y' = -k y, 0 = z - c y^2`` (h = 0.1,
noise-free data at 50 times, start k = 3, c = 1, w = 1e4, one thread): Adam at 1e-3 for 3000
iterations took 42 s and left k and c 3e-2 and 0.12 from the truth; L-BFGS after it, 24 s more,
reached the Radau-at-h estimate (6e-8 and 1.1e-6 from the truth) with the networks' residual
still at 1e-8.  This Gauss-Newton reaches the same estimate with the residual at 4e-16 in 1.5 s
(9 iterations, the forward training at the start values and torch's first use included).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from daemodel.backends.pinn.config import DEFAULT_TOL
from daemodel.backends.pinn.inverse_inputs import Transform, check_constraints, check_inputs

from daemodel.errors import InvalidOptionError, ShapeError, TrainingError

# Gauss-Newton iterations (accepted or rejected steps) when ``max_iterations`` is not given: the
# problems measured converge in 5-15.
DEFAULT_MAX_ITERATIONS = 100
# Newton steps on the networks' outputs alone after each Gauss-Newton step (from the linearised
# step's prediction Newton converges quadratically: two or three reach rounding).
RESTORE_STEPS = 10
# Stop when a step changes no transformed parameter by more than this, relative to 1 + |q|.
PARAMETER_TOL = 1e-10
# ... or when the misfit's relative decrease over an accepted step is below this (its rounding).
MISFIT_RTOL = 1e-14
# LM on q: the first damping relative to the largest diagonal entry of A^T A (Madsen, Nielsen &
# Tingleff's value for a start far from the minimum: from 1e-6, the first steps were rejected,
# 12 -> 9 iterations on the decay fit of the tests, 39 -> 17 on the pendulum's m and lam), and the
# damping beyond which no step decreases the misfit (as the forward mode's LM_MAX_DAMPING).
LM_TAU = 1e-3
LM_MAX_DAMPING = 1e16
# An output whose data do not vary (one datum, or a constant) is scaled by max(1, |mean|) instead.
SPREAD_FLOOR = 1e-12
# Relative singular values of the residual's Jacobian below this are rank deficiency (its rows
# for the end values repeat the last stage's: Radau IIA is stiffly accurate).
RANK_RTOL = 1e-12


@dataclass(frozen=True)
class InverseFit:
    """The result of :func:`fit_inverse`.

    Attributes
    ----------
    names : tuple of str
        The estimated parameters.
    parameters : ndarray, shape (len(names),)
        Their estimates.
    solution : Solution
        The trained networks' answer at the estimates, method ``"pinn"``, on the grid and the
        data times, with the certificate's status (``"success"`` or ``"flagged: ..."``).
    certificate : Certificate
        Its distance from the Radau solution at the same h and the estimated parameters
        (:mod:`.certificate`).
    iterations : int
        Gauss-Newton iterations of the joint training (accepted and rejected steps).
    converged : bool
        Whether the joint training met its stopping test (else it ran out of iterations or of
        damping, and the solution's status says so).
    train_time : float
        Seconds of training: the forward networks at the start values and the joint training.
    loss : dict
        The final ``misfit`` (half the sum of the scaled squared misfits), ``max_residual`` (the
        largest Radau residual component) and ``data_points``.
    history : tuple of float
        The misfit after every accepted step (the first: at the start values).
    """

    names: tuple
    parameters: np.ndarray
    solution: object
    certificate: object
    iterations: int
    converged: bool
    train_time: float
    loss: dict
    history: tuple


class _Problem:
    """The joint problem as functions of the networks' output biases and the transformed parameters."""

    def __init__(
        self, compiled, config, grid, networks, state, indices, transform, times, columns, values, scales=None
    ):
        from daemodel.collocation import lagrange_matrix
        from daemodel.dense import step_owners
        from daemodel.tableau import radau_iia

        self.compiled, self.config, self.grid, self.networks = compiled, config, grid, networks
        self.n, self.m = len(compiled.states), len(compiled.algebraics)
        self.functions = compiled.torch_functions(dtype=torch.float64, device=config.device)
        tableau = radau_iia(config.stages)
        self.A, self.b, self.c = tableau.to_torch(dtype=torch.float64, device=config.device)
        self.steps = [(float(grid[k]), float(grid[k + 1] - grid[k])) for k in range(len(grid) - 1)]
        self.y0 = torch.tensor(np.array(state.y0[:1], dtype=float))
        self.p_fixed = np.array(state.p[0], dtype=float)
        self.indices, self.transform = indices, transform
        # the data, as (segment, Lagrange weights on start and stages, column, value, scale) rows
        observed = np.argwhere(np.isfinite(values))  # (rows, 2): time index, output
        spread = (
            np.array([_spread(values[:, j]) for j in range(values.shape[1])])
            if scales is None
            else np.asarray(scales, dtype=float)
        )
        starts = np.asarray(grid[:-1], dtype=float)
        segment, theta = step_owners(starts, np.diff(grid), times)
        self.data_segment = segment[observed[:, 0]]
        weights = lagrange_matrix(np.concatenate([[0.0], np.asarray(tableau.c, dtype=float)]), theta)
        self.data_weights = torch.as_tensor(weights[observed[:, 0]], dtype=torch.float64)  # (rows, s+1)
        self.data_column = torch.as_tensor(np.asarray(columns)[observed[:, 1]])
        self.data_value = torch.as_tensor(values[observed[:, 0], observed[:, 1]], dtype=torch.float64)
        self.data_scale = torch.as_tensor(spread[observed[:, 1]], dtype=torch.float64)
        self.frozen = [{k: v.detach() for k, v in net.named_parameters() if k != "b_out"} for net in networks]
        self.used = [net.used().bool()[:, None, :] for net in networks]  # as b_out, (K, 1, out)
        self.z0 = None  # set by at_parameters

    # ---- the initial algebraic values follow the parameters ----------------------------------------
    def at_parameters(self, q: torch.Tensor, z_guess: np.ndarray) -> None:
        """z0 at the parameters of ``q`` (the compiler's algebraic solve) and dz0/dq (implicit
        differentiation of its determining equations H(t0, y0, z0, p) = 0)."""
        from daemodel.compiling.initial_states import algebraic_values

        p = self.parameters(q).detach().numpy()[None]
        y0 = self.y0.numpy()
        if self.m == 0:
            self.z0, self.z0_q, self.q_at = torch.zeros(1, 0, dtype=torch.float64), None, q.detach().clone()
            return
        t0 = float(self.grid[0])
        z0 = algebraic_values(self.compiled, t0, y0, p, np.asarray(z_guess, dtype=float).reshape(1, -1))
        determining = [c.determining for c in self.compiled.constraints]
        Hp = self.compiled.numeric.batch_jacobian(determining, self.compiled.parameters)(t0, y0, z0, p)[0]
        Hz = self.compiled.numeric.batch_jacobian(determining, self.compiled.algebraics)(t0, y0, z0, p)[0]
        dz_dp = -np.linalg.solve(Hz, Hp[:, self.indices])  # (m, fitted)
        with torch.enable_grad():
            qq = q.detach().clone().requires_grad_()
            dp_dq = torch.autograd.functional.jacobian(lambda x: self.parameters(x)[torch.as_tensor(self.indices)], qq)
        self.z0 = torch.as_tensor(z0, dtype=torch.float64)
        self.z0_q = torch.as_tensor(dz_dp, dtype=torch.float64) @ dp_dq.detach()
        self.q_at = q.detach().clone()

    def parameters(self, q: torch.Tensor) -> torch.Tensor:
        """The full parameter vector (k,) with the fitted entries from ``q``."""
        p = torch.as_tensor(self.p_fixed, dtype=torch.float64).clone()
        return p.index_put((torch.as_tensor(self.indices),), self.transform.to_parameters(q))

    # ---- the rollout ------------------------------------------------------------------------------------
    def biases(self) -> list:
        return [net.b_out.detach()[self.used[k]] for k, net in enumerate(self.networks)]

    def set_biases(self, flat: torch.Tensor) -> None:
        with torch.no_grad():
            for k, part in enumerate(self.split(flat)):
                self.networks[k].b_out[self.used[k]] = part

    def split(self, flat: torch.Tensor) -> list:
        sizes = [int(u.sum()) for u in self.used]
        return list(torch.split(flat, sizes))

    def rollout(self, flat_b: torch.Tensor, q: torch.Tensor, keep: bool = False):
        """The Radau residual R (every segment's rows, chained), the scaled misfit d (one row per
        datum) and, with ``keep``, the grid values (1, S + 1, n+m) and each segment's Outputs."""
        p = self.parameters(q)
        z0 = self.z0 if self.z0_q is None else self.z0 + (self.z0_q @ (q - self.q_at))[None]
        y_n, z_n = self.y0, z0
        residuals, starts, predictions = [], [], []
        nodes = []  # per segment (1, s+1, n+m): start, stages with the end values last
        for k, (b_k, (t, h)) in enumerate(zip(self.split(flat_b), self.steps, strict=True)):
            net = self.networks[k]
            bias = torch.zeros_like(net.b_out).index_put((self.used[k],), b_k)
            raw = net(y_n, params={**self.frozen[k], "b_out": bias})
            out = net.split(raw, y_n, h)
            res = _stage_rows(self, t, h, y_n, out, p)
            residuals.append(res)
            stages = torch.cat(
                [
                    torch.cat([out.Y[:, :-1], out.y_end[:, None]], dim=1),
                    torch.cat([out.Z[:, :-1], out.z_end[:, None]], dim=1),
                ],
                dim=2,
            )
            nodes.append(torch.cat([torch.cat([y_n, z_n], dim=1)[:, None], stages], dim=1))
            if keep:
                starts.append(torch.cat([y_n, z_n], dim=1))
                predictions.append(out)
            y_n, z_n = out.y_end, out.z_end
        R = torch.cat(residuals)
        nodes = torch.cat(nodes)  # (S, s+1, n+m)
        # each datum: its segment's polynomial through the start and the stages, in its own column
        model = (self.data_weights * nodes[self.data_segment, :, self.data_column]).sum(-1)
        d = (model - self.data_value) / self.data_scale
        if not keep:
            return R, d
        starts.append(torch.cat([y_n, z_n], dim=1))
        return R, d, torch.stack(starts, dim=1), predictions


def _stage_rows(problem, t, h, y_n, out, p):
    """Segment residual rows F, G, F_end, G_end, S flattened (the forward mode's loss terms)."""
    from daemodel.collocation import stage_residual

    res = stage_residual(
        problem.functions, problem.A, problem.b, problem.c, t, h, y_n, out.Y, out.Z, p[None], out.y_end, out.z_end
    )
    parts = [res.F, res.G, res.F_end, res.G_end, res.S]
    return torch.cat([a.reshape(-1) for a in parts if a is not None])


def _spread(column: np.ndarray) -> float:
    finite = column[np.isfinite(column)]
    if finite.size == 0:
        return 1.0
    spread = float(np.std(finite))
    return (
        spread
        if spread > SPREAD_FLOOR * max(1.0, float(np.abs(finite).max()))
        else max(1.0, float(np.abs(finite).mean()))
    )


def fit_inverse(
    compiled,
    t_span,
    times,
    data,
    names,
    start,
    bounds,
    state,
    config,
    *,
    max_iterations: int | None = None,
    progress: bool | None = None,
    scales=None,
) -> InverseFit:
    """Estimate the parameters ``names`` from ``data`` by training the Radau-PINN's segment
    networks and the parameters together (see the module docstring).

    Parameters
    ----------
    compiled : CompiledDAE
        Of index at most 2 (an index-3 model is reduced to 2, as the forward mode does).
    t_span : (float, float)
    times : ndarray, shape (T,)
        Data times, ascending, inside ``t_span``.
    data : dict str -> ndarray, shape (T,)
        Observed values of states or algebraic variables by name, NaN where missing.
    names : tuple of str
        The parameters to estimate; every other parameter keeps its value in ``state.p[0]``.
    start : ndarray, shape (len(names),)
        Starting values, strictly inside ``bounds``.
    bounds : (low, high)
        Arrays (or numbers) of shape (len(names),); -inf and inf for none.
    state : InitialStates
        One trajectory's known initial states (y0, z0, p).  z0 follows the parameters (the
        compiler's algebraic solve at t0); a z-free constraint that depends on a fitted parameter
        is refused (:class:`FittedConstraintError`).
    config : PINNConfig
        The grid (``h``, ``stages``), the networks, and ``tol``: the largest Radau residual
        component the trained networks keep (default :data:`.config.DEFAULT_TOL` when None).
    max_iterations : int, optional
        Cap on the joint Gauss-Newton iterations (default :data:`DEFAULT_MAX_ITERATIONS`); a fit
        that reaches it is returned with a flagged status.
    progress : bool, optional
        A progress bar over the iterations (default: when stderr is a terminal).
    scales : sequence of float, optional
        Each data series' scale (its noise level), in the order of ``data``: its misfits are divided
        by it.  Default: the spread (standard deviation) of its data.

    Returns
    -------
    InverseFit

    Raises
    ------
    ShapeError, TimeSpanError, InvalidOptionError
        For inconsistent data, times, names, start or bounds.
    FittedConstraintError
        When a z-free constraint level depends on a fitted parameter.
    TrainingError
        When the networks cannot be brought back onto the Radau solution after a step (Newton
        on their outputs does not converge) at the start values.
    """
    from daemodel.backends.grids import fixed_grid
    from daemodel.backends.pinn.segments import MAX_INDEX, train_segments
    from daemodel.backends.progress import show_progress
    from daemodel.backends.torch_setup import torch_threads

    from daemodel.compiling.initial_states import InitialStates, algebraic_values

    if config.dtype != "float64" or config.device != "cpu":
        raise InvalidOptionError(
            f"the inverse mode runs in float64 on the CPU (its Gauss-Newton solves dense least-squares problems); "
            f"got dtype {config.dtype!r} on {config.device!r}: use PINNConfig(dtype='float64', device='cpu')"
        )
    if state.size != 1:
        raise ShapeError(f"fit_inverse fits one trajectory; state holds {state.size} samples")
    if max_iterations is None:
        max_iterations = DEFAULT_MAX_ITERATIONS
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidOptionError(f"max_iterations must be a positive integer; got {max_iterations!r}")
    if compiled.index > MAX_INDEX:
        compiled = compiled.reduced(MAX_INDEX)
    times, columns, values, indices, start, low, high = check_inputs(
        compiled, t_span, times, data, names, start, bounds
    )
    names = tuple(names)
    check_constraints(compiled, names)
    tol = config.tol if config.tol is not None else DEFAULT_TOL
    transform = Transform(low=low, high=high)
    grid = fixed_grid(t_span, config.h)
    began = time.perf_counter()
    with torch_threads(1, 0):
        p_start = np.array(state.p[:1], dtype=float)
        p_start[0, indices] = start
        # the networks on the Radau solution at the start values: the forward mode, segment by segment
        z_start = algebraic_values(compiled, float(grid[0]), state.y0[:1], p_start, state.z0[:1])
        networks, _ = train_segments(compiled, config, grid, state.y0[:1], z_start, p_start, [], False, "pinn")
        problem = _Problem(compiled, config, grid, networks, state, indices, transform, times, columns, values, scales)
        bar = _Bar(max_iterations, show_progress(progress))
        try:
            q, flat_b, iterations, converged, history, why = _gauss_newton(
                problem, transform.to_q(start), z_start, tol, max_iterations, bar
            )
        finally:
            bar.close()
        problem.set_biases(flat_b)
        problem.at_parameters(q, problem.z0.numpy())
        trained = time.perf_counter()
        with torch.no_grad():
            R, d, grid_values, predictions = problem.rollout(torch.cat(problem.biases()), q, keep=True)
        p_final = problem.parameters(q).numpy()[None]
        result_state = InitialStates(y0=np.array(state.y0[:1]), z0=problem.z0.numpy().copy(), p=p_final, batched=False)
        solution, certificate = _solution(
            problem,
            result_state,
            grid,
            grid_values.numpy(),
            predictions,
            times,
            converged,
            why,
            iterations,
            trained - began,
            R,
            d,
        )
    estimates = p_final[0, indices].copy()
    return InverseFit(
        names=names,
        parameters=estimates,
        solution=solution,
        certificate=certificate,
        iterations=iterations,
        converged=converged,
        train_time=trained - began,
        loss={
            "misfit": 0.5 * float((d * d).sum()),
            "max_residual": float(R.abs().max()),
            "data_points": int(d.numel()),
        },
        history=tuple(history),
    )


class _Bar:
    """A tqdm bar over the joint iterations whose postfix shows the misfit and the estimates."""

    def __init__(self, total: int, enabled: bool):
        from daemodel.backends.progress import progress_bar

        self.bar = progress_bar(total, "pinn fit", "it") if enabled else None

    def report(self, misfit: float, residual: float, p: np.ndarray) -> None:
        if self.bar is not None:
            shown = " ".join(f"{v:.6g}" for v in p)
            self.bar.set_postfix_str(f"misfit={misfit:.3e} R={residual:.1e} p={shown}")
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _jacobians(problem, flat_b, q):
    """R, d and their Jacobians in (b, q): one reverse pass per row, vectorised."""
    from torch.func import jacrev

    def both(fb, qq):
        R, d = problem.rollout(fb, qq)
        return torch.cat([R, d]), (R, d)

    (J_b, J_q), (R, d) = jacrev(both, argnums=(0, 1), has_aux=True)(flat_b, q)
    r = R.numel()
    return R, d, J_b[:r], J_q[:r], J_b[r:], J_q[r:]


def _restore(problem, flat_b, q, tol, solve=None):
    """Newton on the networks' output biases at fixed ``q`` until every residual is at most ``tol``:
    (biases, R, d, converged).  ``solve``: the pseudo-inverse of the residual's Jacobian at the
    linearisation point, used while it contracts the residual (a chord iteration: after a
    Gauss-Newton step the residual is of the step's square, and a fresh Jacobian costs as much as
    the rest of the iteration); once it stops contracting, Newton with a fresh Jacobian, for at most
    :data:`RESTORE_STEPS` steps in all.  A residual below :data:`STAGNATION_SIZE` that Newton no
    longer decreases is at its rounding floor."""
    from torch.func import jacrev

    previous, fresh = math.inf, solve is None
    for _ in range(RESTORE_STEPS):
        R, d = problem.rollout(flat_b, q)
        size = float(R.abs().max())
        if not math.isfinite(size):
            return flat_b, R, d, False
        if size <= tol:
            return flat_b, R, d, True
        if fresh and previous <= size <= STAGNATION_SIZE:  # Newton no longer decreases it: its rounding floor
            return flat_b, R, d, True
        if not fresh and size > RESTORE_CONTRACTION * previous:
            solve = None
        if solve is None:
            solve, fresh = _PseudoInverse(jacrev(lambda fb: problem.rollout(fb, q)[0])(flat_b)), True
        previous = size
        flat_b = flat_b + solve(-R[:, None])[:, 0]
    R, d = problem.rollout(flat_b, q)
    return flat_b, R, d, float(R.abs().max()) <= tol


# A residual that stopped shrinking below this (absolute) is at its rounding floor.
STAGNATION_SIZE = 1e-10
# A chord step must cut the residual at least this much, else the Jacobian is refreshed.
RESTORE_CONTRACTION = 0.1


class _PseudoInverse:
    """The minimum-norm least-squares solve by the SVD of J (the residual rows are rank deficient:
    the end rows repeat the last stage's), factored once for several right-hand sides."""

    def __init__(self, J: torch.Tensor):
        U, S, Vh = torch.linalg.svd(J, full_matrices=False)
        keep = S > RANK_RTOL * S[0]
        self.U, self.S, self.V = U[:, keep], S[keep], Vh[keep].T

    def __call__(self, rhs: torch.Tensor) -> torch.Tensor:
        return self.V @ ((self.U.T @ rhs) / self.S[:, None])


def _gauss_newton(problem, q0: np.ndarray, z_start: np.ndarray, tol: float, max_iterations: int, bar):
    """The joint training (see the module docstring): (q, output biases, iterations, converged,
    misfit history, why it did not converge)."""
    q = torch.as_tensor(q0, dtype=torch.float64)
    problem.at_parameters(q, z_start)
    flat_b = torch.cat(problem.biases())
    flat_b, R, d, ok = _restore(problem, flat_b, q, tol)
    if not ok:
        raise TrainingError(
            f"pinn fit: the networks trained at the start values keep a Radau residual of {float(R.abs().max()):.3g} "
            f"above tol = {tol:g}; shorten h or raise the forward mode's iterations"
        )
    misfit = 0.5 * float((d * d).sum())
    history, mu, nu, why = [misfit], None, 2.0, f"it ran out of iterations ({max_iterations})"
    iterations = 0
    while iterations < max_iterations:
        R, d, J_b, J_q, D_b, D_q = _jacobians(problem, flat_b, q)
        # db = db0 + X dq keeps the linearised residual zero; the misfit along it is r + A dq
        solve = _PseudoInverse(J_b)
        solved = solve(-torch.cat([R[:, None], J_q], dim=1))
        db0, X = solved[:, 0], solved[:, 1:]
        r, A = d + D_b @ db0, D_b @ X + D_q
        g, H = A.T @ r, A.T @ A
        if mu is None:
            mu = LM_TAU * float(H.diagonal().max())
        while iterations < max_iterations:
            iterations += 1
            dq = torch.linalg.solve(H + mu * torch.eye(len(q), dtype=H.dtype), -g)
            q_new = q + dq
            problem.at_parameters(q_new, problem.z0.numpy())
            b_new, R_new, d_new, ok = _restore(problem, flat_b + db0 + X @ dq, q_new, tol, solve)
            new = 0.5 * float((d_new * d_new).sum()) if ok else math.inf
            predicted = float(-(g @ dq) - 0.5 * dq @ H @ dq)
            if new < misfit:  # accepted: Nielsen's update of the damping
                rho = (misfit - new) / predicted if predicted > 0 else 0.0
                mu, nu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), 2.0
                small = float((dq.abs() / (1 + q_new.abs())).max()) <= PARAMETER_TOL
                stalled = misfit - new <= MISFIT_RTOL * misfit
                q, flat_b, misfit = q_new, b_new, new
                history.append(misfit)
                bar.report(misfit, float(R_new.abs().max()), problem.parameters(q).numpy()[problem.indices])
                if small or stalled:
                    return q, flat_b, iterations, True, history, ""
                break
            mu, nu = mu * nu, 2 * nu
            problem.at_parameters(q, problem.z0.numpy())
            bar.report(misfit, float(R.abs().max()), problem.parameters(q).numpy()[problem.indices])
            step = float((dq.abs() / (1 + q.abs())).max())
            if step <= PARAMETER_TOL:  # no step decreases the misfit: at its minimum, to rounding
                return q, flat_b, iterations, True, history, ""
            if mu > LM_MAX_DAMPING * max(float(H.diagonal().max()), 1e-300):
                return q, flat_b, iterations, False, history, "no step decreases the misfit (the damping ran out)"
    return q, flat_b, iterations, False, history, why


def _solution(problem, state, grid, values, predictions, times, converged, why, iterations, train_time, R, d):
    """The Solution at the estimates (grid and data times, the networks' collocation polynomials as
    its dense output) and its certificate."""
    from daemodel.backends.base import DEFAULT_ESTIMATE_BOUND, make_solution
    from daemodel.backends.pinn.backend import certified_status, estimate_status
    from daemodel.backends.pinn.certificate import certify

    from daemodel.dense import CollocationPolynomials

    compiled, config = problem.compiled, problem.config
    began = time.perf_counter()
    stacked = tuple(
        torch.stack([getattr(out, name).detach() for out in predictions]) for name in ("Y", "Z", "y_end", "z_end")
    )  # each (S, 1, ...)
    certificate = certify(compiled, config, grid, problem.networks, [], values, state.p, predictions=stacked)
    Y, Z = (a.numpy() for a in stacked[:2])
    stages = np.concatenate([Y, Z], axis=3).transpose(1, 0, 2, 3)  # (1, S, s, n+m)
    stages[:, :, -1] = values[:, 1:]  # the end values at c_s = 1, as the forward mode's dense output
    dense = CollocationPolynomials(
        c=np.asarray(problem.c.numpy(), dtype=float),
        starts=np.asarray(grid[:-1], dtype=float),
        lengths=np.diff(grid),
        nodes=np.concatenate([values[:, :-1, None], stages], axis=2),
    )
    out_times = np.union1d(grid, times)
    out_values = dense(out_times)
    status = certified_status(compiled, config, grid, [], certificate, False)
    # never better than radau's at the same h and stages: flagged where its own estimate is (a fit keeps
    # its estimates where radau's forward solve would raise LocalErrorBoundError; the status says so)
    estimated = estimate_status(compiled, grid, certificate, DEFAULT_ESTIMATE_BOUND, False)
    if estimated != "success":
        status = estimated if status == "success" else f"{status}; {estimated.removeprefix('flagged: ')}"
    if not converged:
        reason = f"the joint training did not converge: {why}; raise max_iterations or start closer"
        status = f"flagged: {reason}" + ("" if status == "success" else "; " + status.removeprefix("flagged: "))
    names = (*compiled.state_names, *compiled.algebraic_names)
    stats = {
        "mode": "inverse",
        "segments": len(grid) - 1,
        "iterations": iterations,
        "converged": converged,
        "training_seconds": train_time,
        "misfit": 0.5 * float((d * d).sum()),
        "final_max_residual": float(R.abs().max()),
        "certificate": certificate.summary(names),
    }
    settings = {**dataclasses.asdict(config), "executor": "local"}
    return (
        make_solution(
            "pinn",
            compiled,
            state,
            None,
            out_times,
            out_values,
            time.perf_counter() - began,
            stats,
            settings=settings,
            status=status,
            setup_time=train_time,
            dense=dense,
        ),
        certificate,
    )
