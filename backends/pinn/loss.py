"""The Radau-PINN loss: the Radau IIA stage residual that Newton zeroes, squared and weighted.

For N training inputs y_n with predictions ``Y_i, y_{n+1}, Z_i, z_{n+1}``
(:func:`daemodel.collocation.stage_residual` gives F, G, F_end, G_end, S)::

    L_f = 1/(N (s+1)) sum_samples (sum_i |F_i|^2 + |F_end|^2)
    L_g = 1/(N (s+1)) sum_samples (sum_i |G_i|^2 + |G_end|^2)
    L_s = 1/N         sum_samples |S|^2
    loss = W_f L_f + W_g L_g + W_s L_s = |r|^2

The residual vector ``r`` (per sample, weights folded in) and its Jacobian with respect to
the predictions (:meth:`RadauLoss.jacobian`, from the model's Jacobian) give the Newton
corrections that Levenberg-Marquardt fits; Adam and L-BFGS minimise ``|r|^2``.  At the
classical Radau IIA solution (Newton's stage values, ``y_{n+1} = Y_s``, ``z_{n+1} = Z_s``)
every residual is zero.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from daemodel.collocation import model_jacobian, stage_residual
from daemodel.compiling.codegen import casadi_jacobian
from daemodel.errors import DaemodelError

TERMS = ("L_f", "L_g", "L_s")
# The kernel's Newton correction is used where each of its two solves (the square stage rows; the
# end rows' normal equations) leaves a residual below this, relative to the sizes that bound its
# rounding (measured: 5e-21 to 2e-16 on the ten trajectory models of the PINN benchmark); a failed solve, or
# a worse one (a singular or near-singular stage matrix), is redone by torch's dense lstsq.
OPTIMALITY_BOUND = 1e-13


@dataclass(frozen=True)
class Residuals:
    """Unweighted residuals of a batch of N samples.

    Attributes
    ----------
    F : Tensor, shape (N, s+1, n)
        Stage rows, then the end row (y_{n+1} with b).
    G : Tensor, shape (N, s+1, m)
        Constraints at the stages, then at (y_{n+1}, z_{n+1}).
    S : Tensor, shape (N, m)
        ``z_{n+1} - Z_s``.
    scale_f, scale_s : Tensor or None, shapes (N, 1, n) and (N, m)
        ``max(1, |y_n|)`` and ``max(1, |z_{n+1}|)``: the size of the variable each F and S row is
        measured in, for :meth:`max_abs` (None: 1).
    measured : float or None
        :meth:`max_abs`, where whoever made these residuals computed it (the kernel, in numpy).
    squares : tuple of float or None
        The sums of squares of F, G and S, likewise (for :meth:`terms`).
    """

    F: torch.Tensor
    G: torch.Tensor
    S: torch.Tensor
    scale_f: torch.Tensor | None = None
    scale_s: torch.Tensor | None = None
    measured: float | None = None
    squares: tuple | None = None

    def terms(self) -> dict[str, float]:
        """The loss terms L_f, L_g, L_s (means as in the paper)."""
        N, rows = self.F.shape[0], self.F.shape[1]
        if self.squares is None:
            with torch.no_grad():
                squares = [float((a**2).sum()) for a in (self.F, self.G, self.S)]
        else:
            squares = self.squares
        return {"L_f": squares[0] / (N * rows), "L_g": squares[1] / (N * rows), "L_s": squares[2] / N}

    def largest(self, names=None) -> tuple[float, str]:
        """The largest component as :meth:`max_abs` measures it, and where it is: which equation
        (a stage or end-value row of a state's F, a constraint, a z_end - Z_s row), and the
        sample when there are several.  ``names``: (states, constraints, algebraics)."""
        with torch.no_grad():
            F = self.F if self.scale_f is None else self.F / self.scale_f
            S = self.S if self.scale_s is None else self.S / self.scale_s
            best = (0.0, "")
            for kind, r in (("F", F), ("G", self.G), ("S", S)):
                if not r.numel():
                    continue
                flat = int(r.abs().argmax())
                value = float(r.abs().flatten()[flat])
                if value <= best[0] and best[1]:
                    continue
                index = [int(i) for i in np.unravel_index(flat, tuple(r.shape))]
                column = index[-1]
                if names is not None:
                    label = names[{"F": 0, "G": 1, "S": 2}[kind]][column]
                else:
                    label = f"#{column}"
                stages = self.F.shape[1] - 1
                if kind == "S":
                    where = f"z_end - Z_s of '{label}'"
                else:
                    row = "the end value" if index[1] == stages else f"stage {index[1] + 1}"
                    where = f"the equation of '{label}' at {row}" if kind == "F" else f"constraint '{label}' at {row}"
                if self.F.shape[0] > 1:
                    where += f", sample {index[0]}"
                best = (value, where)
            return best

    def max_abs(self) -> float:
        """The largest residual component, each F and S row in units of its variable's size
        ``max(1, |value|)`` (G rows as they are): the stopping criterion.  Two networks predict
        ``z_{n+1}`` and ``Z_s``, so S cannot fall below the rounding of z itself: 3.6e-12 for the
        squeezer's accelerations of 3e4, where an absolute 1e-12 was out of reach."""
        return self._largest_measured if self.measured is None else self.measured

    @functools.cached_property
    def _largest_measured(self) -> float:  # computed once: LM asks at every step
        with torch.no_grad():
            F = self.F if self.scale_f is None else self.F / self.scale_f
            S = self.S if self.scale_s is None else self.S / self.scale_s
            return max((float(r.abs().max()) if r.numel() else 0.0) for r in (F, self.G, S))


class CasadiKernel:
    """The residuals of :class:`RadauLoss` for one sample, and their Jacobian with respect to the
    predictions, as casadi-compiled functions of one packed vector (the kernels radau's casadi
    engine uses for a trajectory): a call costs microseconds where the torch functions, written
    for batches, cost a millisecond of per-operation dispatch on a small system.

    Both take ``[t_n, h, y_n (n), u (U), p (k)]`` with ``u = [Y (s, n) row-major, y_end (n),
    Z (s, m) row-major, z_end (m)]`` (:meth:`RadauLoss.jacobian`'s layout); ``residual`` returns
    ``[F (s+1, n), G (s+1, m), S (m)]`` flat, ``system`` that followed by the Jacobian dr/du
    (R, U) row by row, and ``correction`` r, the Newton correction e, its solves' accuracy
    (:data:`OPTIMALITY_BOUND`) and ``max |e| / (1 + |u|)`` (how far it moves the values, for the
    trainer's rounding test).

    The correction uses the structure of dr/du (:func:`correction_blocks`): the stage rows are
    square in the stage values (radau's Newton matrix), so the stage values take their full
    Newton increment, by a sparse QR; the end values then fit the end rows (``F_end``, ``G_end``,
    ``S``, row weights W) by least squares, on the normal equations of that small block (the
    identity in y_end and z_end, and g at the end: well conditioned).  Where every residual can
    vanish this is the least-squares solution of all rows; elsewhere it differs from it, and it is
    radau's own Newton step in the stages.  dr/du is sparse (5% nonzero for the squeezer): a
    correction costs 30 us for heat by lines and 52 us for the squeezer, against 150-250 us for
    torch's dense ``lstsq`` alone.
    """

    def __init__(self, compiled, tableau):
        self.compiled, self.tableau = compiled, tableau
        self.s, self.n, self.m = tableau.stages, len(compiled.states), len(compiled.algebraics)
        self._functions = None  # built on first use: batches (surrogates) never need them

    def _built(self):
        if self._functions is None:
            from daemodel.backends.radau.compiled import Buffered

            compiled, tableau = self.compiled, self.tableau
            made = compiled.cached(("casadi-pinn", tableau.stages), lambda: _casadi_loss_functions(compiled, tableau))
            self._functions = (*(Buffered(function) for function in made[:2]), Buffered(made[2], inputs=2))
        return self._functions

    def residual(self, packed: np.ndarray) -> np.ndarray:
        return self._built()[0](packed)

    def system(self, packed: np.ndarray) -> np.ndarray:
        return self._built()[1](packed)

    def correction(self, packed: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """The residuals r (R,), the Newton correction e (U,) for row weights ``weights`` (R,), its
        solves' accuracy and how far it moves the values (the class's ``correction``)."""
        function = self._built()[2]
        function.inputs[1][:] = weights
        return function(packed)

    def pack(self, t_n, h, y_n, p, out) -> np.ndarray:
        """The kernels' argument for predictions ``out``: an :class:`Outputs`, or the flat values u (1, U)."""
        parts = (out, p) if isinstance(out, torch.Tensor) else (out.Y, out.y_end, out.Z, out.z_end, p)
        return np.concatenate([[float(t_n), float(h)], y_n.numpy().ravel(), *(a.numpy().ravel() for a in parts)])


def _casadi_loss_functions(compiled, tableau):
    """casadi functions of :class:`CasadiKernel` (cached on the compiled model, per s), built on
    radau's casadi engine's own stage residual (the equations Newton zeroes there): its stage
    rows, and the end rows and ``S`` that the PINN adds."""
    import casadi
    from daemodel.backends.radau.compiled import casadi_functions

    radau_residual = compiled.cached(("casadi-radau", tableau.stages), lambda: casadi_functions(compiled, tableau))[1]
    dae = compiled.casadi_dae()
    t, p = dae["t"], dae["p"]
    s, n, m = tableau.stages, dae["x"].numel(), dae["z"].numel()
    D = n + m
    g = casadi.Function("g", [t, dae["x"], dae["z"], p], [dae["alg"]])
    h, y_n, u = casadi.SX.sym("h"), casadi.SX.sym("y_n", n), casadi.SX.sym("u", (s + 1) * D)
    Y = [u[i * n : (i + 1) * n] for i in range(s)]
    y_end = u[s * n : (s + 1) * n]
    first = (s + 1) * n
    Z = [u[first + i * m : first + (i + 1) * m] for i in range(s)]
    z_end = u[first + s * m :]
    W = casadi.vertcat(*(casadi.vertcat(Y[i], Z[i]) for i in range(s)))  # stage by stage, as radau packs it
    out = radau_residual(casadi.vertcat(t, h, y_n, W, p))
    R, stage_f = out[: s * D], out[s * D :]
    F = [R[i * D : i * D + n] for i in range(s)]
    G = [R[i * D + n : (i + 1) * D] for i in range(s)]
    quadrature = sum((float(tableau.b[j]) * stage_f[j * n : (j + 1) * n] for j in range(s)), casadi.SX.zeros(n))
    F.append(y_end - y_n - h * quadrature)
    G.append(g(t + h, y_end, z_end, p))
    r = casadi.vertcat(*F, *G, z_end - Z[-1])
    packed = casadi.vertcat(t, h, y_n, u, p)
    sparse = casadi_jacobian(r, u)  # (dense rows apart)
    rows = casadi.reshape(casadi.densify(sparse).T, -1, 1)  # column-major of J^T: J row by row
    # the Newton correction: the stage rows are square (radau's Newton matrix), so the stage values
    # take their full Newton increment; the end values then fit their rows (F_end, G_end, S: the
    # identity in y_end and z_end, and g at the end) by least squares, on their normal equations
    X, weights = casadi.MX.sym("packed", packed.numel()), casadi.MX.sym("weights", r.numel())
    r_x, J_x = casadi.Function("pinn_sparse", [packed], [r, sparse])(X)
    R, U = sparse.shape
    stage_rows, end_rows, stage_cols, end_cols = correction_blocks(s, n, m)
    A, r_s = J_x[stage_rows, stage_cols], r_x[stage_rows]
    stages = casadi.solve(A, r_s, "qr")
    C = weights[end_rows] * J_x[end_rows, end_cols]
    r_e = weights[end_rows] * (r_x[end_rows] - casadi.mtimes(J_x[end_rows, stage_cols], stages))
    ends = casadi.solve(casadi.mtimes(C.T, C), casadi.mtimes(C.T, r_e), "qr")
    e = casadi.vertcat(stages, ends)[np.argsort(stage_cols + end_cols).tolist()]
    # each solve's residual relative to the sizes that bound its rounding (the stage rows' and the
    # end rows' normal equations)
    solved = casadi.norm_inf(casadi.mtimes(A, stages) - r_s) / (
        len(stage_rows) * casadi.mmax(casadi.fabs(A)) * casadi.norm_inf(stages) + casadi.norm_inf(r_s) + 1e-300
    )
    fitted = casadi.norm_inf(casadi.mtimes(C.T, r_e - casadi.mtimes(C, ends))) / (
        len(end_rows) * casadi.mmax(casadi.fabs(C)) * (casadi.norm_inf(r_e) + casadi.norm_inf(casadi.mtimes(C, ends)))
        + 1e-300
    )
    optimality = casadi.fmax(solved, fitted)
    u_x = X[2 + n : 2 + n + U]
    rounding = casadi.mmax(casadi.fabs(e) / (1 + casadi.fabs(u_x)))  # how far e moves u, relative to 1 + |u|
    return (
        casadi.Function("pinn_residual", [packed], [r]),
        casadi.Function("pinn_system", [packed], [casadi.vertcat(r, rows)]),
        casadi.Function("pinn_correction", [X, weights], [casadi.vertcat(r_x, e, optimality, rounding)]),
    )


def correction_blocks(s: int, n: int, m: int) -> tuple:
    """Rows and columns of :meth:`RadauLoss.jacobian` (``[F (s+1, n), G (s+1, m), S (m)]`` by
    ``[Y (s, n), y_end, Z (s, m), z_end]``) in the Newton correction's two blocks: the stage rows
    and stage values (square: radau's Newton matrix), the end rows and end values."""
    stage_rows = list(range(s * n)) + [(s + 1) * n + i for i in range(s * m)]
    end_rows = [s * n + i for i in range(n)] + [(s + 1) * n + s * m + i for i in range(m)]
    end_rows += [(s + 1) * (n + m) + i for i in range(m)]
    stage_cols = list(range(s * n)) + [(s + 1) * n + i for i in range(s * m)]
    end_cols = [s * n + i for i in range(n)] + [(s + 1) * n + s * m + i for i in range(m)]
    return stage_rows, end_rows, stage_cols, end_cols


class RadauLoss:
    """Residuals of one segment ``[t_n, t_n + h]`` for a network's predictions.

    Parameters
    ----------
    functions : TorchFunctions
        The compiled, batched f and g.
    tableau : RadauIIA
    config : PINNConfig
        Supplies the weights W_f, W_g, W_s.
    dtype, device
    kernel : CasadiKernel, optional
        Evaluates one sample's residuals and Jacobian where no gradient is wanted (LM, the
        checks); batches and autograd (Adam, L-BFGS) use ``functions``.
    """

    def __init__(self, functions, tableau, config, dtype, device, kernel: CasadiKernel | None = None):
        self.functions = functions
        self.A, self.b, self.c = tableau.to_torch(dtype=dtype, device=device)
        self.stages = tableau.stages
        self.weights = (config.weight_f, config.weight_g, config.weight_s)
        self.kernel = kernel
        self._kernel_weights = None  # the row weights of one sample, as the kernel takes them

    def _kernel_applies(self, y_n, out, p=None) -> bool:
        """One sample, no gradient wanted: the casadi kernel (made for float64 on the CPU)."""
        if self.kernel is None or y_n.shape[0] != 1:
            return False
        inputs = (y_n, p, out.Y, out.y_end, out.Z, out.z_end)
        return not (torch.is_grad_enabled() and any(a is not None and a.requires_grad for a in inputs))

    def residuals(self, t_n: float, h: float, y_n, p, out) -> Residuals:
        """Residuals at inputs ``y_n`` (N, n), parameters ``p`` (N, k), predictions ``out``."""
        if self._kernel_applies(y_n, out, p):
            packed = self.kernel.pack(t_n, h, y_n, p, out)
            return self._unpacked(self.kernel.residual(packed), packed)
        res = stage_residual(
            self.functions, self.A, self.b, self.c, t_n, h, y_n, out.Y, out.Z, p, y_end=out.y_end, z_end=out.z_end
        )
        F = torch.cat([res.F, res.F_end[:, None, :]], dim=1)
        G = torch.cat([res.G, res.G_end[:, None, :]], dim=1)
        return self._measured(F, G, res.S, y_n, out.z_end)

    def _unpacked(self, r: np.ndarray, packed: np.ndarray) -> Residuals:
        """One sample's :class:`Residuals` from the kernel's flat ``[F, G, S]`` at its argument
        ``packed`` (:meth:`CasadiKernel.pack`), taken apart in numpy (a torch operation costs
        microseconds, as much as the kernel's call on a small model)."""
        s, n, m = self.kernel.s, self.kernel.n, self.kernel.m
        first, U = (s + 1) * n, (s + 1) * (n + m)
        y_n, z_end = packed[2 : 2 + n], packed[2 + n + U - m : 2 + n + U]
        F, G, S = r[:first].reshape(1, s + 1, n), r[first:U].reshape(1, s + 1, m), r[U:].reshape(1, m)
        scale_f, scale_s = np.maximum(np.abs(y_n), 1.0).reshape(1, 1, n), np.maximum(np.abs(z_end), 1.0).reshape(1, m)
        measured = max(float(np.abs(a).max()) if a.size else 0.0 for a in (F / scale_f, G, S / scale_s))
        squares = tuple(float(a @ a) for a in (r[:first], r[first:U], r[U:]))
        tensors = (torch.from_numpy(a) for a in (F, G, S, scale_f, scale_s))
        return Residuals(*tensors, measured=measured, squares=squares)

    def _measured(self, F, G, S, y_n, z_end) -> Residuals:
        with torch.no_grad():
            scale_f = y_n.detach().abs().clamp(min=1.0)[:, None, :]
            scale_s = z_end.detach().abs().clamp(min=1.0) if z_end is not None else None
        return Residuals(F=F, G=G, S=S, scale_f=scale_f, scale_s=scale_s)

    def jacobian(self, t_n: float, h: float, y_n, p, out) -> torch.Tensor:
        """d(vector)/du, shape (N, R, U), of :meth:`vector` (one sample: ``total = N``) with
        respect to the predictions ``u = [Y (s, n) row-major, y_end (n), Z (s, m) row-major,
        z_end (m)]``, assembled from the model's Jacobian at the s stages and the end point::

            dF_i/dY_j = delta_ij I - h a_ij f_y(j),   dF_i/dZ_j = -h a_ij f_z(j)   (end row: b_j, + I at y_end)
            dG_i/d(Y_i, Z_i) = (g_y, g_z)(i),          dG_end/d(y_end, z_end) = (g_y, g_z)(end)
            dS/dz_end = I,                             dS/dZ_s = -I
        """
        s, N = self.stages, y_n.shape[0]
        n, m = y_n.shape[1], out.Z.shape[-1]
        D = n + m
        dtype, device = y_n.dtype, y_n.device
        if self._kernel_applies(y_n, out, p):
            R, U = (s + 1) * D + m, (s + 1) * D
            values = self.kernel.system(self.kernel.pack(t_n, h, y_n, p, out))
            return torch.from_numpy(values[R:]).reshape(1, R, U) * self._row_weights(N, n, m, dtype, device)[:, None]
        times = torch.cat([t_n + self.c * h, torch.full((1,), t_n + h, dtype=dtype, device=device)])
        points_y = torch.cat([out.Y, out.y_end[:, None, :]], dim=1)  # (N, s+1, n)
        points_z = torch.cat([out.Z, out.z_end[:, None, :]], dim=1)
        J = model_jacobian(self.functions, times, points_y, points_z, None if p is None else p[:, None, :])
        f_y, f_z, g_y, g_z = J[..., :n, :n], J[..., :n, n:], J[..., n:, :n], J[..., n:, n:]
        Ab = torch.cat([self.A, self.b[None, :]])  # (s+1, s): the stage rows, then the end row
        sn, sm = s * n, s * m
        R, U = (s + 1) * D + m, (s + 1) * D
        jac = y_n.new_zeros(N, R, U)
        F = jac[:, : (s + 1) * n].view(N, s + 1, n, U)
        F[..., :sn].view(N, s + 1, n, s, n).copy_(-h * torch.einsum("ij,bjpq->bipjq", Ab, f_y[:, :s]))
        F[..., sn + n : sn + n + sm].view(N, s + 1, n, s, m).copy_(-h * torch.einsum("ij,bjpq->bipjq", Ab, f_z[:, :s]))
        eye_n, eye_m = torch.eye(n, dtype=dtype, device=device), torch.eye(m, dtype=dtype, device=device)
        for i in range(s):
            F[:, i, :, i * n : (i + 1) * n] += eye_n
        F[:, s, :, sn : sn + n] += eye_n  # y_end
        G = jac[:, (s + 1) * n : (s + 1) * D].view(N, s + 1, m, U)
        for i in range(s):
            G[:, i, :, i * n : (i + 1) * n] = g_y[:, i]
            G[:, i, :, sn + n + i * m : sn + n + (i + 1) * m] = g_z[:, i]
        G[:, s, :, sn : sn + n] = g_y[:, s]
        G[:, s, :, sn + n + sm :] = g_z[:, s]
        S = jac[:, (s + 1) * D :]
        S[:, :, sn + n + sm :] = eye_m
        S[:, :, sn + n + (s - 1) * m : sn + n + sm] = -eye_m
        return jac * self._row_weights(N, n, m, dtype, device)[:, None]

    def kernel_applies(self, y_n, u, p) -> bool:
        """Whether one sample's residuals at the values ``u`` (flat, or any tensor they are made
        from) go to the casadi kernel: :meth:`residuals_and_correction` takes them."""
        return self.kernel is not None and y_n.shape[0] == 1 and not (torch.is_grad_enabled() and u.requires_grad)

    def residuals_and_correction(self, t_n: float, h: float, y_n, p, u) -> tuple:
        """One sample's :meth:`residuals` and Newton correction e (1, U) of :meth:`vector` at the
        stage and end values ``u`` (1, U) (:meth:`jacobian`'s layout, as ``RadauNetwork.values``
        gives them), by one call of the casadi kernel (where :meth:`kernel_applies`; e as
        :class:`CasadiKernel` solves it); e is None where a solve failed or is not accurate to
        rounding (r not finite, the stage matrix singular or nearly): the caller solves
        ``lstsq`` then.  Returns ``(residuals, e, moved)``, moved the largest
        ``|e_i| / (1 + |u_i|)`` (None with e)."""
        if self._kernel_weights is None:
            n, m = y_n.shape[1], self.kernel.m
            self._kernel_weights = self._row_weights(1, n, m, torch.float64, "cpu").numpy()
        packed = self.kernel.pack(t_n, h, y_n, p, u)
        R = len(self._kernel_weights)
        try:
            values = self.kernel.correction(packed, self._kernel_weights)
        except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
            raise
        except RuntimeError:  # a zero pivot in a sparse QR
            return self._unpacked(self.kernel.residual(packed), packed), None, None
        residuals = self._unpacked(values[:R], packed)
        if not values[-2] <= OPTIMALITY_BOUND:
            return residuals, None, None
        return residuals, torch.from_numpy(values[None, R:-2]), float(values[-1])

    def _row_weights(self, N: int, n: int, m: int, dtype, device) -> torch.Tensor:
        """The weight of each row of :meth:`vector` (one sample of N)."""
        s = self.stages
        W_f, W_g, W_s = self.weights
        return torch.cat(
            [
                torch.full(((s + 1) * n,), math.sqrt(W_f / (N * (s + 1))), dtype=dtype, device=device),
                torch.full(((s + 1) * m,), math.sqrt(W_g / (N * (s + 1))), dtype=dtype, device=device),
                torch.full((m,), math.sqrt(W_s / N), dtype=dtype, device=device),
            ]
        )

    def vector(self, residuals: Residuals, total: int) -> torch.Tensor:
        """Weighted residual vector, shape (N, R), with ``|r|^2`` = the loss over ``total`` samples."""
        W_f, W_g, W_s = self.weights
        rows = self.stages + 1
        N = residuals.F.shape[0]
        return torch.cat(
            [
                math.sqrt(W_f / (total * rows)) * residuals.F.reshape(N, -1),
                math.sqrt(W_g / (total * rows)) * residuals.G.reshape(N, -1),
                math.sqrt(W_s / total) * residuals.S,
            ],
            dim=1,
        )
