"""The torch engine of ``method="radau"``: batched kernels for any batch, device and float dtype.

The compiler's batched torch functions; a Jacobian from the compiler's sparse symbolic
derivatives scattered into dense matrices (forward-mode autograd over a column colouring where a
derivative leaves the emitters); batched dense LU.
"""

from __future__ import annotations

import threading
import warnings

import numpy as np
from daemodel.backends.radau.engines import AbstractEngine, Residual, StageFactors

from daemodel.collocation import stage_residual

# torch's forward-mode AD levels are the process's, not a thread's: threads' Jacobians by forward AD take turns (two
# radau solves of one large model in two threads raised torch's RuntimeError "Nested forward mode AD is not supported
# at the moment" where their dual levels met); warnings.catch_warnings, around it, is the process's too.
_FORWARD_AD = threading.Lock()


class TorchEngine(AbstractEngine):
    """Batched kernels in torch (see the module docstring)."""

    name = "torch"

    def __init__(self, compiled, start, tableau, transform, dtype, device):
        import torch

        super().__init__(compiled, start, tableau, transform)
        self.xp = self.torch = torch
        self.dtype, self.device = dtype, device
        self.complex_dtype = torch.complex128 if dtype == torch.float64 else torch.complex64
        self.tf = compiled.torch_functions(dtype=dtype, device=device)
        self.A, self.b, self.c = tableau.to_torch(dtype, device)
        self.p = self.asarray(start.p)
        self.B = start.size
        pattern = self.tf.jacobian_pattern
        self._flat = None if pattern is None else torch.as_tensor(pattern[0] * self.D + pattern[1], device=device)
        if pattern is None:  # forward-mode AD over the column colouring
            colour = compiled.column_colouring()
            rows, cols = (torch.as_tensor(a, device=device) for a in compiled.jacobian_pattern())
            seeds = torch.zeros((int(colour.max(initial=0)) + 1, self.D), dtype=dtype, device=device)
            seeds[torch.as_tensor(colour, device=device), torch.arange(self.D, device=device)] = 1.0
            self._colouring = (seeds, rows, cols, torch.as_tensor(colour, device=device)[cols])
        self._diag = torch.arange(self.n, device=device)
        self._stage_buffer = self._stage_eye = None  # the full Newton matrix's buffer (factor_stages)
        self._index2 = torch.as_tensor(self.index2_rows, device=device)

    def asarray(self, values):
        return self.torch.tensor(np.asarray(values), dtype=self.dtype, device=self.device)

    def f(self, t, y, z):
        return self.tf.f(t, y, z, self.p)

    def residual(self, t, h, y, W):
        n = self.n
        r = stage_residual(self.tf, self.A, self.b, self.c, t, h, y, W[..., :n], W[..., n:], self.p)
        return Residual(R=self.torch.cat([r.F, r.G], dim=-1), stage_f=r.stage_f, G=r.G)

    def jacobian(self, t, y, z):
        """``(B, D, D)`` for ``y (B, n)``, ``(B, s, D, D)`` for ``y (B, s, n)`` with ``t (s,)``."""
        torch = self.torch
        D, lead = self.D, y.shape[:-1]
        t = torch.as_tensor(t, dtype=self.dtype, device=self.device)
        p = self.p.reshape(self.B, *([1] * (len(lead) - 1)), -1)
        if self.tf.jacobian is not None:  # the compiler's symbolic Jacobian, its nonzeros only
            values = self.tf.jacobian(t, y, z, p)
            J = values.new_zeros((*lead, D * D))
            J[..., self._flat] = values
            return J.reshape(*lead, D, D)
        return self._forward_ad(t, y, z, p, lead)

    def _forward_ad(self, t, y, z, p, lead):
        """Forward-mode AD through the generated f and g, one direction per colour of the
        compiled column colouring (a few for a sparse system, instead of n + m)."""
        torch = self.torch
        import torch.autograd.forward_ad as fwAD

        n, m, D = self.n, self.m, self.D
        seeds, rows, cols, colours = self._colouring
        C = seeds.shape[0]
        t, p = t[..., None], p[..., None, :]  # a new axis for the C directions

        def directions(x, columns):
            shape = (*lead, C, x.shape[-1])
            return x[..., None, :].expand(shape).clone(), columns.expand(shape).clone()

        with _FORWARD_AD, warnings.catch_warnings(), fwAD.dual_level():
            # torch's forward-AD decompositions still call torch.jit.script on first use
            warnings.filterwarnings("ignore", message=".*torch.jit.script.*deprecated", category=DeprecationWarning)
            yd = fwAD.make_dual(*directions(y, seeds[:, :n]))
            zd = fwAD.make_dual(*directions(z, seeds[:, n:]))
            parts = []
            for fn, size in ((self.tf.f, n), (self.tf.g, m)):
                tangent = fwAD.unpack_dual(fn(t, yd, zd, p)).tangent
                parts.append(y.new_zeros((*lead, C, size)) if tangent is None else tangent)
        compressed = torch.cat(parts, dim=-1)  # (..., C, D): row i of colour c holds J[i, j] for j of colour c
        J = y.new_zeros((*lead, D * D))
        J[..., rows * D + cols] = compressed[..., colours, rows]
        return J.reshape(*lead, D, D)

    def stage_jacobians(self, t, h, W):
        n = self.n
        return self.jacobian(t + self.c * h, W[..., :n], W[..., n:])

    def z_matrix_sign(self, J):
        n = self.n
        rows = J[..., n:, n:].clone()  # g_z, (B, m, m)
        if self.index2_rows.any():
            gyfz = J[..., n:, :n] @ J[..., :n, n:]
            rows[..., self._index2, :] = gyfz[..., self._index2, :]
        return self.torch.linalg.slogdet(rows)[0]

    def _factor_shift(self, J, sigma):
        torch = self.torch
        if sigma.imag == 0:
            matrix = -J
            matrix.diagonal(dim1=-2, dim2=-1)[..., self._diag] += sigma.real
        else:
            matrix = (-J).to(self.complex_dtype)
            matrix.diagonal(dim1=-2, dim2=-1)[..., self._diag] += sigma
        LU, pivots, info = torch.linalg.lu_factor_ex(matrix)
        return (LU, pivots), singular(torch, LU, info)

    def solve(self, lu, rhs):
        LU, pivots = lu
        if LU.is_complex() and not rhs.is_complex():
            rhs = rhs.to(LU.dtype)
        return self.torch.linalg.lu_solve(LU, pivots, rhs[..., None])[..., 0]

    def factor_stages(self, stage_J, h):
        torch = self.torch
        s, n, D, B = self.s, self.n, self.D, self.B
        # rows [F_i; G_i] and unknowns [Y_j; Z_j] stage by stage:
        # dF_i/dU_j = delta_ij [I 0] - h a_ij [f_y f_z](stage j);  dG_i/dU_i = [g_y g_z](stage i)
        # one buffer for every step: the G rows' off-diagonal blocks stay zero, everything else is overwritten
        if self._stage_buffer is None or self._stage_buffer.shape[0] != B:
            self._stage_buffer = stage_J.new_zeros((B, s, D, s, D))
            self._stage_eye = torch.eye(n, dtype=self.dtype, device=self.device)
        N = self._stage_buffer
        torch.mul(
            (-h) * self.A[None, :, None, :, None],
            stage_J[:, None, :, :n, :].permute(0, 1, 3, 2, 4),
            out=N[:, :, :n],
        )
        for i in range(s):
            N[:, i, n:, i, :] = stage_J[:, i, n:, :]
            N[:, i, :n, i, :n] += self._stage_eye
        LU, pivots, info = torch.linalg.lu_factor_ex(N.reshape(B, s * D, s * D))
        return StageFactors(lu=(LU, pivots), singular=singular(torch, LU, info))

    def solve_stages(self, factors, R):
        LU, pivots = factors.lu
        B, s, D = R.shape
        return self.torch.linalg.lu_solve(LU, pivots, -R.reshape(B, s * D, 1)).reshape(B, s, D)

    def first(self, mask):
        return int(self.torch.nonzero(mask)[0])


def singular(torch, LU, info):
    """``(B,)``: where torch's LU is singular or not finite (a nan in the Jacobian: sqrt(-x), which torch gives as
    nan, passed lu_factor_ex's info = 0, and the solve went on to torch's bare RuntimeError "expected scalar type
    Double but found ComplexDouble"; linalg's dense LU counts a factor that is not finite as singular too), so that
    the step names the Jacobian that is not finite (Stepper.check_singular)."""
    return (info > 0) | ~torch.isfinite(LU).flatten(1).all(dim=1)
