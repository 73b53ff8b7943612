"""Radau IIA in torch: Newton on the compiled, batched stage residual.

Each step solves ``F = 0, G = 0`` of :func:`daemodel.collocation.stage_residual` (the
equations the Radau-PINN minimises) for the stage values of every sample at once, with a
simplified Newton method: one Jacobian ``[f_y f_z; g_y g_z]`` at the step's start (forward-mode
autograd through the generated code), one batched LU of the ``s(n+m)`` stage matrix, reused
across iterations and, while Newton contracts fast, across steps.

Fixed step (``h=...``) reproduces the Radau IIA collocation solution on the grid
``t0 + k h``.  Adaptive mode (``rtol``, ``atol``) estimates the local error with an embedded
formula of order s (Hairer & Wanner, Solving ODEs II, IV.8, generalised to s stages): with
``gamma0`` the real eigenvalue of A (s odd) and ``bhat`` of order s including the start point,

    (M - h gamma0 J) err = [gamma0 h f(y_n) + h sum_i (bhat_i - b_i) f(Y_i) ; 0]

where ``M = diag(I, 0)``.  As in RADAU5, the error of an algebraic variable determined through
an index-k constraint is multiplied by ``h^(k-1)`` before the norm (its stage values are only
accurate to order s - k + 2).  A batch shares the step sequence (the worst sample decides).

Fixed step computes the same estimate after every step, with the Jacobian Newton already used,
in units of the solution's size ``1 + max |u|`` so far, reports its maximum as
``stats["max_local_error_estimate"]`` and refuses a step whose estimate exceeds
:data:`LOCAL_ERROR_BOUND` (:class:`~daemodel.errors.LocalErrorBoundError`): Newton converges on
a step across a singularity as readily as on a good one, and only the estimate tells them apart.

Adaptive mode stops Newton on the contraction rate of the last step, as RADAU5 does, but a step
declared converged after a single iteration is checked with one more increment (one LU solve):
trusting that rate alone accepted unconverged stages, 100 x rtol errors on the pendulum and finite
garbage on a switching f such as sign(x).

Every loop is bounded: ``max_steps`` bounds the fixed grid (checked before it is built) and, in
adaptive mode, every step attempt, accepted, rejected or failed in Newton
(:class:`~daemodel.errors.StepLimitError`).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    LOCAL_ERROR_BOUND,
    AbstractBackend,
    ProgressWatch,
    check_dtype,
    check_number,
    check_stages,
    check_tolerances,
    fixed_grid,
    fixed_step_sweep,
    make_solution,
    output_times,
    torch_device,
)

from daemodel.collocation import stage_residual
from daemodel.errors import ConvergenceError, InvalidOptionError, LocalErrorBoundError, StepLimitError
from daemodel.tableau import radau_iia

# Fixed step: Newton stops when the scaled increment is below this many eps of the dtype.
FIXED_NEWTON_TOL_EPS = 10
# Tolerances of adaptive mode when neither h nor rtol/atol is given.
DEFAULT_RTOL, DEFAULT_ATOL = 1e-6, 1e-8
# float32 carries ~7 digits: asking for more from it is an error, not a silent loss.
FLOAT32_MIN_RTOL = 1e-5
# Step-size controller (RADAU5's values): safety factor, and bounds on h_new / h.
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 8.0
# Keep h (and the LU) when the controller asks for a change within this band (RADAU5's QUOT1/2).
KEEP_H_BAND = (1.0, 1.2)
# Reuse the Jacobian for the next step when Newton contracted at least this fast (RADAU5's THET).
REUSE_THETA = 1e-3
# Above this contraction rate, Newton switches to per-stage Jacobians at the current iterate.
REFRESH_THETA = 0.05
# Fixed step: increments that stop shrinking (contraction above STAGNATION_THETA) while within
# STAGNATION_FACTOR of newton_tol have reached the rounding floor of the residual.
STAGNATION_THETA, STAGNATION_FACTOR = 0.5, 100.0
# Newton is declared diverging when an increment is not at least this much smaller than the last.
DIVERGENCE_THETA = 0.99
# Adaptive mode: default budget of step attempts (accepted, rejected, or failed in Newton).  An
# attempt costs 2-6 ms on one (shared) CPU core, so a runaway (a chattering switch, an endless
# t_span) fails within 10-30 s; the pendulum on [0, 10] takes ~370 attempts at rtol = 1e-6.
DEFAULT_MAX_ADAPTIVE_STEPS = 5_000
# Fixed step: default bound on the grid's step count, checked before the grid is built (the count
# is known up front, so no runaway is possible; daemodel.compare's finest sweep takes 20,480 steps).
DEFAULT_MAX_FIXED_STEPS = 100_000


@dataclass(frozen=True, kw_only=True)
class RadauOptions:
    """Options of ``method="radau"``.

    Attributes
    ----------
    stages : int
        Radau IIA stages s (order 2s-1 for y; s for an index-2 algebraic variable).
    h : float, optional
        Fixed step size.  Exclusive with ``rtol``/``atol``.
    rtol, atol : float, optional
        Adaptive mode's tolerances (default 1e-6, 1e-8 when ``h`` is not given).
    h0 : float, optional
        First step of adaptive mode (default: estimated from f at t0).
    t_eval : array, optional
        Output times (collocation-polynomial dense output); default: the step grid.
    newton_tol : float, optional
        Newton's tolerance on scaled increments; default ``10 * eps`` of the dtype for a fixed
        step (the collocation solution to rounding), ``max(10 eps / rtol, min(0.03, sqrt(rtol)))``
        relative to the error tolerance in adaptive mode (RADAU5's rule).
    max_newton_iterations : int
    max_steps : int, optional
        Fixed step: most steps of the grid, refused before it is built
        (:class:`~daemodel.errors.ResourceLimitError`); default 100,000.  Adaptive mode: most step
        attempts, accepted, rejected or failed in Newton alike
        (:class:`~daemodel.errors.StepLimitError`); default 5,000, a runaway's 10-30 s.
    reuse_jacobian : bool
        Keep the Jacobian (and the LU while h is unchanged) for the next step when Newton
        contracted fast; otherwise a fresh one every step.
    dtype : "float64" or "float32"
    device : str
        A torch device ("cpu", "cuda", "cuda:1", ...).
    """

    stages: int = 3
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    h0: float | None = None
    t_eval: object = None
    newton_tol: float | None = None
    max_newton_iterations: int = 10
    max_steps: int | None = None
    reuse_jacobian: bool = True
    dtype: str = "float64"
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_stages(self.stages)
        for name in ("h", "rtol", "atol", "h0", "newton_tol"):
            check_number(name, getattr(self, name), allow_none=True)
        check_number("max_newton_iterations", self.max_newton_iterations, integer=True)
        object.__setattr__(self, "dtype", check_dtype(self.dtype))
        if self.h is not None and (self.rtol is not None or self.atol is not None or self.h0 is not None):
            raise InvalidOptionError("h fixes the step size; rtol/atol/h0 select adaptive steps: give one or the other")
        if self.max_steps is None:
            object.__setattr__(
                self, "max_steps", DEFAULT_MAX_ADAPTIVE_STEPS if self.adaptive else DEFAULT_MAX_FIXED_STEPS
            )
        check_number("max_steps", self.max_steps, integer=True)
        if self.adaptive:
            object.__setattr__(self, "rtol", DEFAULT_RTOL if self.rtol is None else self.rtol)
            object.__setattr__(self, "atol", DEFAULT_ATOL if self.atol is None else self.atol)
            if self.dtype == "float32" and self.rtol < FLOAT32_MIN_RTOL:
                raise InvalidOptionError(
                    f"rtol = {self.rtol:g} is below what float32 can deliver (>= {FLOAT32_MIN_RTOL:g}); "
                    "use dtype='float64'"
                )
            check_tolerances(self.rtol, self.atol)
        eps = float(np.finfo(self.dtype).eps)
        if self.newton_tol is not None and self.newton_tol < 10 * eps:
            raise InvalidOptionError(
                f"newton_tol = {self.newton_tol:g} is below 10 eps of {self.dtype} ({10 * eps:.1e}); "
                "Newton cannot reach it" + (": use dtype='float64'" if self.dtype == "float32" else "")
            )
        if not isinstance(self.reuse_jacobian, bool):
            raise InvalidOptionError(f"reuse_jacobian must be True or False; got {self.reuse_jacobian!r}")
        device = torch_device(self.device)  # InvalidOptionError for a device torch cannot use here
        if not isinstance(self.device, str):
            object.__setattr__(self, "device", str(device))

    @property
    def adaptive(self) -> bool:
        return self.h is None


class RadauBackend(AbstractBackend):
    """``method="radau"``: batched Radau IIA with Newton, fixed or adaptive steps."""

    name = "radau"
    Options = RadauOptions
    # index 3 would need h^-2-conditioned Newton matrices; solve() reduces it to index 2
    max_index = 2

    def work_precision(self, t_span, points):
        return fixed_step_sweep(t_span, points)

    def solve(self, compiled, t_span, start, options: RadauOptions):
        import torch

        device = torch_device(options.device)
        stepper = _Stepper(compiled, start, options, getattr(torch, options.dtype), device)
        began = time.perf_counter()
        times, values = stepper.integrate(t_span)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        wall = time.perf_counter() - began
        return make_solution(self, compiled, start, options, times, values, wall, stepper.stats)


def embedded_weights(tableau) -> tuple[float, np.ndarray]:
    """``(gamma0, bhat - b)`` of the order-s error estimate.

    ``gamma0`` is A's real eigenvalue (s odd, as in RADAU5 and Hairer-Wanner's RADAU); for even
    s, A has no real eigenvalue and ``det(A)^(1/s)`` (the geometric mean of their moduli) is used.
    ``bhat`` solves ``gamma0 * 0^(k-1) + sum_i bhat_i c_i^(k-1) = 1/k`` for k = 1..s.
    """
    s, c = tableau.stages, tableau.c
    eig = np.linalg.eigvals(tableau.A)
    real = eig[np.abs(eig.imag) < 1e-12].real
    gamma0 = float(real.max()) if real.size else float(abs(np.linalg.det(tableau.A)) ** (1 / s))
    V = np.vander(c, s, increasing=True).T  # V[k, i] = c_i^k
    rhs = 1.0 / np.arange(1, s + 1)
    rhs[0] -= gamma0
    return gamma0, np.linalg.solve(V, rhs) - tableau.b


class _Stepper:
    """State of one integration: tableau, functions, LU, counters."""

    def __init__(self, compiled, start, options: RadauOptions, dtype, device):
        import torch

        self.torch = torch
        self.compiled, self.options = compiled, options
        self.dtype, self.device = dtype, device
        self.tf = compiled.torch_functions(dtype=dtype, device=device)
        self.tableau = radau_iia(options.stages)
        self.A, self.b, self.c = self.tableau.to_torch(dtype, device)
        gamma0, e = embedded_weights(self.tableau)
        self.gamma0, self.e = gamma0, torch.tensor(e, dtype=dtype, device=device)
        self.s, self.n, self.m = options.stages, len(compiled.states), len(compiled.algebraics)
        self.B = start.size

        def tensor(a):
            return torch.tensor(a, dtype=dtype, device=device)

        self.y, self.z, self.p = tensor(start.y0), tensor(start.z0), tensor(start.p)
        # index of the constraint that determines each algebraic variable: its error weight is h^(k-1)
        self.z_index = tensor([compiled.constraints[j].index for j in compiled.determined_by])
        # constraints (rows of g) of index 2, whose rows of z's iteration matrix are g_y f_z
        self.z_rows_index2 = torch.tensor([c.index == 2 for c in compiled.constraints], device=device)
        self._det_sign, self._det_time = None, compiled.t0  # the last fresh Jacobian's sign of det
        eps = float(np.finfo(options.dtype).eps)
        if options.adaptive:
            self.rtol, self.atol = options.rtol, options.atol
            self.newton_tol = options.newton_tol or max(10 * eps / self.rtol, min(0.03, self.rtol**0.5))
        else:
            # fixed step: converge to rounding, increments measured against 1 + |w|
            self.rtol, self.atol = 1.0, 1.0
            self.newton_tol = options.newton_tol or FIXED_NEWTON_TOL_EPS * eps
        self.stats = {
            "mode": "adaptive" if options.adaptive else "fixed",
            "stages": self.s,
            "order": self.tableau.order,
            "dtype": options.dtype,
            "device": str(device),
            "batch": self.B,
            "steps": 0,
            "attempts": 0,
            "rejected_steps": 0,
            "newton_iterations": 0,
            "max_newton_iterations": 0,
            "newton_failures": 0,
            "newton_refreshes": 0,
            "jacobian_evaluations": 0,
            "lu_decompositions": 0,
            "residual_evaluations": 0,
            "h_min": math.inf,
            "h_max": 0.0,
        }
        if not options.adaptive:
            # worst step, sample and variable, in units of 1 + max|u| (see check_local_error)
            self.stats["max_local_error_estimate"] = 0.0
        self._jac = None  # (J, t, h-independent) at the last refresh
        self._lu = None  # (LU, pivots, h)
        self._step_jac = None  # the Jacobian of the last Newton matrix, (B, s, D, D): reused by the estimate
        # the error-estimate matrix is M + J diag(rows): rows -h gamma0 for y, 1 for z (M = diag(I, 0))
        self._error_M = torch.diag(torch.cat([torch.ones(self.n), torch.zeros(self.m)])).to(dtype=dtype, device=device)
        self._error_rows = None  # (h, rows (D, 1), index weights h^(k-1) (D,)) for the last h
        self._no_g = torch.zeros((self.B, self.m), dtype=dtype, device=device)  # the constraint rows' right side
        self._f_start = None  # f at the start of the next step (the last stage's f of this one)
        self._scale = None  # fixed step: 1 + max |u| over the steps' start values so far, (B, n+m)
        self._outputs = None  # ([t], [u (B, n+m)], [(t, h, u_start, U)]) of the accepted steps
        self._eta = torch.ones(self.B, dtype=dtype, device=device)  # Newton's contraction estimate
        self._previous = None  # (h, u_start, U) of the last accepted step, for the start guess

    # ---- pieces -------------------------------------------------------------------------
    def jacobian(self, t, y, z):
        """``[f_y f_z; g_y g_z]`` at ``(t, y, z)``: the compiled symbolic Jacobian, else forward-mode AD.

        ``t`` has shape () or (s,), ``y (B, n)`` or ``(B, s, n)``, likewise ``z``; the result has
        shape ``(B, n+m, n+m)`` or ``(B, s, n+m, n+m)``.
        """
        torch = self.torch
        import torch.autograd.forward_ad as fwAD

        n, m = self.n, self.m
        D = n + m
        lead = y.shape[:-1]
        eye = torch.eye(D, dtype=self.dtype, device=self.device)
        t = torch.as_tensor(t, dtype=self.dtype, device=self.device)
        p = self.p.reshape(self.B, *([1] * (len(lead) - 1)), -1)
        if self.tf.jacobian is not None:  # the compiler's symbolic Jacobian
            self.stats["jacobian_evaluations"] += 1
            return self.tf.jacobian(t, y, z, p).reshape(*lead, D, D)
        t, p = t[..., None], p[..., None, :]  # a new axis for the D directions

        def directions(x, columns):
            shape = (*lead, D, x.shape[-1])
            return x[..., None, :].expand(shape).clone(), columns.expand(shape).clone()

        with warnings.catch_warnings(), fwAD.dual_level():
            # torch's forward-AD decompositions still call torch.jit.script on first use
            warnings.filterwarnings("ignore", message=".*torch.jit.script.*deprecated", category=DeprecationWarning)
            yd = fwAD.make_dual(*directions(y, eye[:, :n]))
            zd = fwAD.make_dual(*directions(z, eye[:, n:]))
            columns = []
            for fn, size in ((self.tf.f, n), (self.tf.g, m)):
                tangent = fwAD.unpack_dual(fn(t, yd, zd, p)).tangent
                columns.append(y.new_zeros((*lead, D, size)) if tangent is None else tangent)
        self.stats["jacobian_evaluations"] += 1
        return torch.cat(columns, dim=-1).transpose(-1, -2).contiguous()

    def newton_matrix(self, J, h):
        """The Newton matrix of the stage equations, shape (B, s(n+m), s(n+m)).

        ``J`` is one Jacobian for every stage, ``(B, D, D)`` (simplified Newton), or one per
        stage, ``(B, s, D, D)`` (full Newton).
        """
        torch = self.torch
        s, n, m, B = self.s, self.n, self.m, self.B
        D = n + m
        if J.ndim == 3:
            J = J[:, None].expand(B, s, D, D)
        # unknowns [Y_1..Y_s, Z_1..Z_s]; rows [F_1..F_s, G_1..G_s]
        M = J.new_zeros((B, s * D, s * D))
        for i in range(s):
            rows_F, rows_G = slice(i * n, (i + 1) * n), slice(s * n + i * m, s * n + (i + 1) * m)
            for j in range(s):
                cols_Y, cols_Z = slice(j * n, (j + 1) * n), slice(s * n + j * m, s * n + (j + 1) * m)
                # dF_i/dY_j = delta_ij I - h a_ij f_y(stage j);  dF_i/dZ_j = -h a_ij f_z(stage j)
                M[:, rows_F, cols_Y] = (-h * float(self.tableau.A[i, j])) * J[:, j, :n, :n]
                M[:, rows_F, cols_Z] = (-h * float(self.tableau.A[i, j])) * J[:, j, :n, n:]
            # dG_i/dY_i = g_y(stage i);  dG_i/dZ_i = g_z(stage i)
            M[:, rows_G, i * n : (i + 1) * n] = J[:, i, n:, :n]
            M[:, rows_G, s * n + i * m : s * n + (i + 1) * m] = J[:, i, n:, n:]
        M[:, : s * n, : s * n] += torch.eye(s * n, dtype=self.dtype, device=self.device)
        return M

    def factor(self, matrix, t, h, what):
        LU, pivots, info = self.torch.linalg.lu_factor_ex(matrix)
        self.stats["lu_decompositions"] += 1
        self.check_singular(info, t, h, what)
        return LU, pivots

    def weights(self, h, y_ref):
        """Error scale of each of the n + m components, shape (B, n+m)."""
        torch = self.torch
        scale = self.atol + self.rtol * y_ref.abs()
        index_weight = torch.as_tensor(h, dtype=self.dtype, device=self.device) ** (self.z_index - 1)
        return torch.cat([scale[:, : self.n], scale[:, self.n :] / index_weight], dim=-1)

    def split(self, W):
        s, n, m, B = self.s, self.n, self.m, self.B
        return W[:, : s * n].reshape(B, s, n), W[:, s * n :].reshape(B, s, m)

    def residual(self, t, h, W):
        Y, Z = self.split(W)
        r = stage_residual(self.tf, self.A, self.b, self.c, t, h, self.y, Y, Z, self.p)
        self.stats["residual_evaluations"] += 1
        return self.torch.cat([r.F.reshape(self.B, -1), r.G.reshape(self.B, -1)], dim=-1), r

    def start_guess(self, h):
        """Stage values extrapolated from the last step's collocation polynomial (or constant)."""
        torch = self.torch
        u = torch.cat([self.y, self.z], dim=-1)
        if self._previous is None:
            U = u[:, None, :].expand(self.B, self.s, self.n + self.m)
        else:
            h_old, u_old, U_old = self._previous
            nodes = np.concatenate([[0.0], self.tableau.c])
            tau = 1.0 + self.tableau.c * h / h_old
            L = torch.tensor(_lagrange(nodes, tau), dtype=self.dtype, device=self.device)  # (s, s+1)
            U = torch.einsum("ij,bjk->bik", L, torch.cat([u_old[:, None, :], U_old], dim=1))
        return torch.cat([U[..., : self.n].reshape(self.B, -1), U[..., self.n :].reshape(self.B, -1)], dim=-1)

    # ---- one step -----------------------------------------------------------------------
    def newton(self, t, h, LU, pivots, W):
        """Solve the stage equations from the guess ``W``; ``(W, stage residual, theta)`` or None."""
        torch = self.torch
        u_ref = torch.cat([self.y, self.z], dim=-1).abs()
        w = self.weights(h, u_ref)
        # the stage unknowns are ordered [Y_1..Y_s, Z_1..Z_s]
        scale = torch.cat([w[:, : self.n].repeat(1, self.s), w[:, self.n :].repeat(1, self.s)], dim=-1)
        if self.options.adaptive:
            # RADAU5: trust the last step's contraction rate, so one iteration may suffice
            eta = torch.clamp(self._eta, min=float(np.finfo(self.options.dtype).eps)) ** 0.8
        else:
            # the fixed-step solution must be the collocation solution: no early trust
            eta = torch.ones_like(self._eta)
        previous = None
        theta = torch.zeros(self.B, dtype=self.dtype, device=self.device)
        active = torch.ones(self.B, dtype=torch.bool, device=self.device)  # samples still iterating
        for k in range(1, self.options.max_newton_iterations + 1):
            R, r = self.residual(t, h, W)
            dW = torch.linalg.lu_solve(LU, pivots, -R[..., None])[..., 0] * active[:, None]
            W = W + dW
            norm = torch.sqrt(torch.mean((dW / scale) ** 2, dim=-1))
            finite = torch.isfinite(norm)  # a NaN or inf anywhere in R or dW ends up here
            if not bool(finite.all()):
                sample = int(torch.nonzero(~finite)[0])
                return None, k, f"non-finite values: {self.non_finite(r, dW, sample, t, h)}", sample
            if previous is not None:
                theta = torch.where(active, norm / torch.clamp(previous, min=1e-300), theta)
                diverging = active & (theta >= DIVERGENCE_THETA)
                if bool(diverging.any()):
                    worst = int(torch.nonzero(diverging)[0])
                    return None, k, f"diverging (contraction {float(theta[worst]):.2f})", worst
                eta = torch.where(active, theta / (1 - theta), eta)
                if float((theta * active).max()) > REFRESH_THETA and k < self.options.max_newton_iterations:
                    # slow contraction: full Newton, with each stage's Jacobian at the current iterate
                    Y, Z = self.split(W)
                    stage_J = self.jacobian(t + self.c * h, Y, Z)
                    LU, pivots = self.factor(self.newton_matrix(stage_J, h), t, h, "Newton matrix")
                    self._step_jac = stage_J
                    self.stats["newton_refreshes"] += 1
                    self._jac = None  # the next step starts from a fresh Jacobian too
            previous = norm
            if self.options.adaptive:
                done = eta * norm <= self.newton_tol
            else:
                # the last increment itself is below tol, or rounding stops the iteration near it
                done = (norm <= self.newton_tol) | (
                    (theta >= STAGNATION_THETA) & (norm <= STAGNATION_FACTOR * self.newton_tol)
                )
            active = active & ~done
            if not bool(active.any()) and self.options.adaptive:
                # the error estimate needs f at the final stage values
                R, r = self.residual(t, h, W)
                if k == 1 and k < self.options.max_newton_iterations:
                    # converged on the last step's contraction alone: check that the next increment is
                    # small too (a non-smooth f, e.g. sign(x), can make one iteration look converged)
                    after = torch.linalg.lu_solve(LU, pivots, -R[..., None])[..., 0]
                    active = torch.sqrt(torch.mean((after / scale) ** 2, dim=-1)) > self.newton_tol
            if not bool(active.any()):
                self._eta = eta
                self.stats["newton_iterations"] += k
                self.stats["max_newton_iterations"] = max(self.stats["max_newton_iterations"], k)
                return (W, r, float(theta.max())), k, None, None
        return None, k, f"not converged in {k} iterations", int(torch.nonzero(active)[0])

    def non_finite(self, r, dW, sample, t, h) -> str:
        """Where a sample's first non-finite value arose: ``f`` or ``g`` at a stage, else an increment of a variable."""
        torch = self.torch
        compiled = self.compiled
        for values, names, what in (
            (r.stage_f, compiled.state_names, "the right-hand side of {}'"),
            (r.G, compiled.constraint_names, "constraint '{}'"),
        ):
            bad = torch.nonzero(~torch.isfinite(values[sample]))
            if len(bad):
                stage, k = (int(i) for i in bad[0])
                when = t + float(self.tableau.c[stage]) * h
                return f"{what.format(names[k])} at stage {stage + 1} (t = {when:.6g})"
        Y, Z = self.split(dW)
        for values, names in ((Y, compiled.state_names), (Z, compiled.algebraic_names)):
            bad = torch.nonzero(~torch.isfinite(values[sample]))
            if len(bad):
                stage, k = (int(i) for i in bad[0])
                return f"the Newton increment of '{names[k]}' at stage {stage + 1}"
        return "the Newton increment"

    def error_rows(self, h):
        """``(rows (D, 1), index weights (D,))`` of step size ``h``, kept while h is unchanged."""
        if self._error_rows is None or self._error_rows[0] != h:
            torch = self.torch
            D = self.n + self.m
            rows = torch.full((D, 1), -h * self.gamma0, dtype=self.dtype, device=self.device)
            rows[self.n :] = 1.0
            index_weight = torch.ones(D, dtype=self.dtype, device=self.device)
            index_weight[self.n :] = torch.as_tensor(h, dtype=self.dtype, device=self.device) ** (self.z_index - 1)
            self._error_rows = (h, rows, index_weight)
        return self._error_rows[1], self._error_rows[2]

    def local_error(self, h, J, f0, stage_f):
        """The embedded local error estimate of the step (see the module docstring), shape (B, n+m).

        ``J`` (B, D, D) is the Jacobian of the error matrix ``M - h gamma0 J``, ``f0`` (B, n) is
        ``f`` at the step's start, ``stage_f`` (B, s, n) at its stages.  Returns the estimate, the
        solve's ``info`` (> 0 where the matrix is singular) and what :meth:`refiltered` needs.
        """
        torch = self.torch
        E = torch.addcmul(self._error_M, J, self.error_rows(h)[0])
        quadrature = torch.matmul(self.e, stage_f)  # sum_i (bhat_i - b_i) f(Y_i), (B, n)
        # the constraint rows carry no local error: each step's Newton enforces g at its stages,
        # and its leftover |g(y_n)| (Newton's tolerance) must not block ever smaller steps
        rhs = torch.cat([(quadrature + self.gamma0 * f0) * h, self._no_g], dim=-1)
        err, info = torch.linalg.solve_ex(E, rhs[..., None])
        self.stats["lu_decompositions"] += 1
        return err[..., 0], info, (E, quadrature)

    def refiltered(self, t, h, err, matrices):
        """The estimate with the stiff filter applied once more (Hairer-Wanner's first or rejected step)."""
        torch = self.torch
        E, quadrature = matrices
        f1 = self.tf.f(t, self.y + err[:, : self.n], self.z + err[:, self.n :], self.p)
        rhs = torch.cat([(quadrature + self.gamma0 * f1) * h, self._no_g], dim=-1)
        return torch.linalg.solve_ex(E, rhs[..., None])[0][..., 0]

    def error_norm(self, t, h, r, W, first):
        """RADAU5-style scaled local error of the step, worst sample (adaptive mode)."""
        torch = self.torch
        J = self.jacobian(t, self.y, self.z)
        f0 = self.tf.f(t, self.y, self.z, self.p)
        err, info, matrices = self.local_error(h, J, f0, r.stage_f)
        self.check_singular(info, t, h, "error-estimate matrix")
        Y, Z = self.split(W)
        u_new = torch.cat([Y[:, -1], Z[:, -1]], dim=-1)
        u_old = torch.cat([self.y, self.z], dim=-1)
        w = self.weights(h, torch.maximum(u_old.abs(), u_new.abs()))
        norm = torch.sqrt(torch.mean((err / w) ** 2, dim=-1))
        if first and bool((norm >= 1).any()):
            err = self.refiltered(t, h, err, matrices)
            norm = torch.sqrt(torch.mean((err / w) ** 2, dim=-1))
        if not bool(torch.isfinite(norm).all()):
            return math.inf
        return float(norm.max())

    def check_local_error(self, step, t, h, r):
        """Fixed step: the step's local error estimate in units of the solution's size; raise beyond the bound.

        The unit is ``1 + max |u|`` over the steps' start values so far (an algebraic variable of
        index k: that over ``h^(k-1)``), so a step across a singularity cannot excuse its error by
        its own huge result, nor an oscillation be judged where it crosses zero.  It reuses the
        Jacobian of the step's Newton matrix (its first stage) and takes ``f`` at the step's start
        from the last step's final stage (Radau IIA is stiffly accurate: ``c_s = 1``).
        """
        torch = self.torch
        u = torch.cat([self.y, self.z], dim=-1).abs().add_(1.0)
        self._scale = u if self._scale is None else torch.maximum(self._scale, u)
        if self._f_start is None:
            self._f_start = self.tf.f(t, self.y, self.z, self.p)
        err, info, matrices = self.local_error(h, self._step_jac[:, 0], self._f_start, r.stage_f)
        index_weight = self.error_rows(h)[1]
        ratio = err.abs().mul_(index_weight).div_(self._scale)
        worst = float(ratio.max())
        if worst > LOCAL_ERROR_BOUND:  # the stiff filter once more before judging (Hairer-Wanner)
            ratio = self.refiltered(t, h, err, matrices).abs().mul_(index_weight).div_(self._scale)
            worst = float(ratio.max())
        self._f_start = r.stage_f[:, -1]
        if worst <= LOCAL_ERROR_BOUND:  # the usual case: False for NaN too
            self.stats["max_local_error_estimate"] = max(self.stats["max_local_error_estimate"], worst)
            return
        self.stats["max_local_error_estimate"] = math.inf if math.isnan(worst) else worst
        self.check_singular(info, t, h, "error-estimate matrix")
        ratio = torch.nan_to_num(ratio, nan=math.inf)
        sample, k = divmod(int(torch.argmax(ratio.reshape(-1))), self.n + self.m)
        name = (*self.compiled.state_names, *self.compiled.algebraic_names)[k]
        index = int(self.z_index[k - self.n]) if k >= self.n else 1
        size = f"1 + max|{name}|" if index == 1 else f"(1 + max|{name}|) / h^{index - 1}"
        value = float(ratio.reshape(-1)[sample * (self.n + self.m) + k])
        raise LocalErrorBoundError(
            f"radau: step {step} from t = {t:.6g} with h = {h:.3g}: the local error estimate of '{name}' "
            f"(sample {sample}) is {value:.3g} times the solution's size {size} so far, beyond "
            f"LOCAL_ERROR_BOUND = {LOCAL_ERROR_BOUND:g}: the step has no correct digit (the solution may be "
            "singular, switch or change too fast there); take a smaller h, or the adaptive mode (rtol=...)"
        )

    def check_singular(self, info, t, h, what):
        """Raise :class:`ConvergenceError` where ``info`` (of an LU) reports a singular matrix."""
        torch = self.torch
        if bool((info > 0).any()):  # non-finite entries surface in Newton's increments instead
            sample = int(torch.nonzero(info > 0)[0])
            raise ConvergenceError(
                f"radau: the {what} is singular for sample {sample} at t = {t:.6g} with h = {h:.3g}; the "
                "constraints may not determine the algebraic variables there (g_y f_z singular)"
            )

    # ---- the loop -----------------------------------------------------------------------
    def integrate(self, t_span):
        """Values at the output times: ``(times (T,), values (B, T, n+m))``."""
        torch = self.torch
        options = self.options
        t0 = t_span[0]
        grid = None if options.adaptive else fixed_grid(t_span, options.h, max_steps=options.max_steps)
        t_out = output_times(options.t_eval, t_span, grid)
        u0 = torch.cat([self.y, self.z], dim=-1)
        self._outputs = ([t0], [u0], [])
        if options.adaptive:
            self.adaptive_steps(t_span)
        else:
            self.fixed_steps(grid)
        out_t, out_u, steps = self._outputs
        if options.t_eval is not None:
            return self.dense_output(t_out, u0, t0, steps)
        values = torch.stack(out_u, dim=1)  # (B, T, n+m)
        return np.asarray(out_t, dtype=float), values.detach().cpu().double().numpy()

    def fixed_steps(self, grid):
        """Step along ``grid``, checking each step's local error estimate."""
        for step in range(1, len(grid)):
            t, h = float(grid[step - 1]), float(grid[step] - grid[step - 1])
            if abs(h - self.options.h) <= 1e-12 * self.options.h:
                h = self.options.h  # not its rounded copy: the LU and the estimate's weights are kept per h
            self.stats["attempts"] += 1
            result, _, why, sample = self.attempt(t, h)
            if result is None:
                self.stats["newton_failures"] += 1
                raise ConvergenceError(
                    f"radau: Newton failed in step {step} from t = {t:.6g} with h = {h:.3g} ({why}, "
                    f"sample {sample}); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
                )
            W, r, theta = result
            self.check_local_error(step, t, h, r)
            self.accept(t, h, W, theta, float(grid[step]))

    def adaptive_steps(self, t_span):
        """RADAU5's step-size controller; every attempt counts against ``max_steps``."""
        options = self.options
        t0, t1 = t_span
        t = t0
        h = options.h0 or self.initial_step(t_span)
        first, rejected_last = True, False
        half = (t0, 0)  # (t, accepted steps) when half the budget was spent: the recent rate of progress
        watch = ProgressWatch(t0, h, extra=0)  # extra: the accepted steps when the window began
        while t < t1 and not math.isclose(t, t1, rel_tol=1e-13, abs_tol=1e-13 * abs(t1 - t0)):
            attempts = self.stats["attempts"]
            if attempts >= options.max_steps:
                raise self.budget_error(t, h, t1, half, options.max_steps - options.max_steps // 2)
            if attempts == options.max_steps // 2:
                half = (t, self.stats["steps"])
            needed = watch.hopeless(attempts, t, h, t1, options.max_steps, extra=self.stats["steps"])
            if needed is not None:
                t_w, count_w, _, accepted_w = watch.start
                raise self.budget_error(t, h, t1, (t_w, accepted_w), attempts - count_w, projected=needed)
            self.stats["attempts"] += 1
            if h < 1e-14 * max(1.0, abs(t)):
                h = self._shrink(h, t, "the error estimate kept shrinking the step", None, 1.0)
            h = min(h, t1 - t)
            if (t1 - t) - h < 1e-10 * h:
                h = t1 - t
            result, iterations, why, sample = self.attempt(t, h)
            if result is None:
                self.stats["newton_failures"] += 1
                self._lu = None
                h = self._shrink(h, t, why, sample, 0.5)
                first = True
                continue
            W, r, theta = result
            err = self.error_norm(t, h, r, W, first or rejected_last)
            factor = min(
                SAFETY,
                SAFETY * (2 * options.max_newton_iterations + 1) / (2 * options.max_newton_iterations + iterations),
            )
            quot = factor * max(err, 1e-10) ** (-1.0 / (self.s + 1))
            if err > 1:
                self.stats["rejected_steps"] += 1
                h = self._shrink(h, t, f"error estimate {err:.2g} > 1", None, max(MIN_FACTOR, min(quot, 0.9)))
                rejected_last = True
                self._lu = None
                continue
            t_next = t1 if math.isclose(t + h, t1, rel_tol=1e-13) else t + h
            self.accept(t, h, W, theta, t_next)
            t = t_next
            new_h = h * min(MAX_FACTOR, max(MIN_FACTOR, quot)) if not rejected_last else h * min(1.0, quot)
            if KEEP_H_BAND[0] <= new_h / h <= KEEP_H_BAND[1]:
                new_h = h
            h = new_h
            first = rejected_last = False

    def attempt(self, t, h):
        """Newton on the step from ``t`` with ``h``, retried once with a fresh Jacobian if a reused one fails."""
        W0 = self.start_guess(h)
        J = self.current_jacobian(t, h, W0)
        LU, pivots = self.current_lu(J, t, h)
        self._step_jac = J
        result, iterations, why, sample = self.newton(t, h, LU, pivots, W0)
        if result is None and self._jac is not None and self._jac[1] != t:
            # the reused Jacobian is stale: refresh it and try again
            self._jac = self._lu = None
            J = self.current_jacobian(t, h, W0)
            LU, pivots = self.current_lu(J, t, h)
            self._step_jac = J
            result, iterations, why, sample = self.newton(t, h, LU, pivots, W0)
        return result, iterations, why, sample

    def accept(self, t, h, W, theta, t_next):
        """Take the step: record its output, move the state to ``t_next``, decide on the Jacobian's reuse."""
        torch = self.torch
        out_t, out_u, steps = self._outputs
        Y, Z = self.split(W)
        u_start = torch.cat([self.y, self.z], dim=-1)
        U = torch.cat([Y, Z], dim=-1)
        if self.options.t_eval is not None:
            steps.append((t, h, u_start, U))
        else:
            out_t.append(t_next)
            out_u.append(U[:, -1])
        self._previous = (h, u_start, U)
        self.y, self.z = Y[:, -1].clone(), Z[:, -1].clone()
        self.stats["steps"] += 1
        self.stats["h_min"] = min(self.stats["h_min"], h)
        self.stats["h_max"] = max(self.stats["h_max"], h)
        if not self.options.reuse_jacobian or theta > REUSE_THETA:
            self._jac = None  # slow contraction (or no reuse asked for): a fresh Jacobian next step

    def budget_error(self, t, h, t1, half, recent, projected=None) -> StepLimitError:
        """max_steps ran out (or, ``projected``, cannot suffice): say where, and why it likely did
        (chattering, or a span too long); ``half`` is (t, accepted steps) ``recent`` attempts ago."""
        budget, accepted = self.options.max_steps, self.stats["steps"]
        failed = self.stats["rejected_steps"] + self.stats["newton_failures"]
        recent_accepted = accepted - half[1]
        progress = t - half[0]
        if recent_accepted < recent / 2:
            reason = (
                f"{recent - recent_accepted} of the last {recent} attempts were rejected or failed in Newton, "
                f"and they advanced t by {progress:.3g} of the {t1 - half[0]:.3g} left: the right-hand side is "
                "likely discontinuous near "
                f"t = {t:.6g} (sign(x), abs(x), min/max or a Piecewise that switches), and steps across the "
                "switch need h -> 0 (chattering); stop the integration at the switch and restart from there, "
                "or smooth the switch"
            )
        else:
            rate = progress / max(recent, 1)
            if projected is not None:
                more = f"about {projected:.3g} more"
            else:
                more = f"about {(t1 - t) / rate:.3g} more" if rate > 0 else "endlessly many"
            reason = (
                f"the steps are accepted, but at the last {recent} attempts' rate ({rate:.3g} per attempt) the "
                f"rest of t_span needs {more} attempts: t_span is too long for max_steps at this tolerance; "
                "raise max_steps, loosen rtol/atol or shorten t_span"
            )
        if projected is None:
            head = f"radau: max_steps = {budget} reached at t = {t:.6g}"
        else:
            head = (
                f"radau: max_steps = {budget} cannot suffice (about {projected:.3g} more attempts projected, "
                f"{budget - self.stats['attempts']} left), stopped early at t = {t:.6g}"
            )
        return StepLimitError(
            f"{head} (h = {h:.3g}) before t1 = {t1:g}, after {accepted} accepted steps and {failed} rejected or "
            f"failed attempts: {reason}"
        )

    def current_jacobian(self, t, h, W0):
        """Each stage's Jacobian at the starting guess (kept while Newton contracts fast)."""
        if self._jac is None:
            Y0, Z0 = self.split(W0)
            self._jac = (self.jacobian(t + self.c * h, Y0, Z0), t)
            self._lu = None
            self.check_determined(self._jac[0], t, h)
        return self._jac[0]

    def check_determined(self, J, t, h):
        """Refuse a step across a point where the constraints stop determining z.

        The iteration matrix of the algebraic variables (row by row ``g_z`` for an index-1 and
        ``g_y f_z`` for an index-2 constraint, as at compile time) must stay nonsingular; its
        determinant changing sign between two fresh Jacobians (the stages of one step, or this
        step and the last fresh one) means it passed through zero, where z is undetermined and
        may blow up (``q' = (0.7 - t) z, 0 = q - sin t``).  Index-2 z is measured against
        ``(atol + rtol |z|) / h``, so the error estimate alone would step over it.
        """
        if not self.m:
            return
        n = self.n
        rows = J[..., n:, n:].clone()  # g_z, (B, s, m, m)
        two = self.z_rows_index2
        if two.any():
            gyfz = J[..., n:, :n] @ J[..., :n, n:]
            rows[..., two, :] = gyfz[..., two, :]
        sign = torch_sign_det(rows)  # (B, s)
        signs = sign if self._det_sign is None else self.torch.cat([self._det_sign[:, None], sign], dim=1)
        flips = (signs[:, 1:] * signs[:, :-1] < 0).any(dim=1)
        if bool(flips.any()):
            sample = int(self.torch.nonzero(flips)[0])
            names = ", ".join(f"'{c.name}'" for c in self.compiled.constraints)
            raise ConvergenceError(
                f"radau: the constraints ({names}) stop determining the algebraic variables between t = "
                f"{self._det_time:.6g} and {t + h:.6g} (sample {sample}): the determinant of their iteration matrix "
                "(g_z, or g_y f_z at index 2) changes sign, so it passes through zero, where z is not determined "
                "and may blow up; end t_span before that time or reformulate the constraints"
            )
        self._det_sign, self._det_time = sign[:, -1], t

    def current_lu(self, J, t, h):
        if self._lu is None or self._lu[2] != h:
            LU, pivots = self.factor(self.newton_matrix(J, h), t, h, "Newton matrix")
            self._lu = (LU, pivots, h)
        return self._lu[0], self._lu[1]

    def _shrink(self, h, t, why, sample, factor):
        new = h * factor
        if new < 1e-14 * max(1.0, abs(t)):
            who = f", sample {sample}" if sample is not None else ""
            raise ConvergenceError(
                f"radau: step size underflow at t = {t:.6g} (h = {new:.3g}; last failure: {why}{who}); the "
                "solution may blow up or leave the domain of f there"
            )
        return new

    def initial_step(self, t_span) -> float:
        """``0.01 |u0| / |f(u0)|`` in the error norm, capped by the interval (Hairer-Wanner's first guess)."""
        torch = self.torch
        t0, t1 = t_span
        f0 = self.tf.f(t0, self.y, self.z, self.p)
        sc = self.atol + self.rtol * self.y.abs()
        d0 = float(torch.sqrt(torch.mean((self.y / sc) ** 2, dim=-1)).max())
        d1 = float(torch.sqrt(torch.mean((f0 / sc) ** 2, dim=-1)).max()) if self.n else 0.0
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        return min(h0, t1 - t0)

    def dense_output(self, t_out, u0, t0, steps):
        """Values at ``t_out`` from each step's collocation polynomial through (t_n, u_n), (t_n + c_i h, U_i)."""
        torch = self.torch
        nodes = np.concatenate([[0.0], self.tableau.c])
        rows = []
        k = 0
        for time_point in t_out:
            if time_point <= t0:
                rows.append(u0)
                continue
            while k < len(steps) - 1 and time_point > steps[k][0] + steps[k][1] * (1 + 1e-13):
                k += 1
            t_n, h, u_start, U = steps[k]
            L = torch.tensor(_lagrange(nodes, np.array([(time_point - t_n) / h])), dtype=self.dtype, device=self.device)
            rows.append(torch.einsum("j,bjk->bk", L[0], torch.cat([u_start[:, None, :], U], dim=1)))
        values = torch.stack(rows, dim=1)
        return np.asarray(t_out, dtype=float), values.detach().cpu().double().numpy()


def torch_sign_det(matrices):
    """Sign of the determinant of each matrix in a stack (+1, -1, or 0), from an LU factorisation."""
    import torch

    sign, _ = torch.linalg.slogdet(matrices)
    return sign


def _lagrange(nodes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``L[i, j]``: the j-th Lagrange basis polynomial on ``nodes`` at ``points[i]``."""
    L = np.ones((len(points), len(nodes)))
    for j, xj in enumerate(nodes):
        for m, xm in enumerate(nodes):
            if m != j:
                L[:, j] *= (points - xm) / (xj - xm)
    return L
