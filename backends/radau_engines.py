"""The two engines of ``method="radau"``: who evaluates residuals and Jacobians and factors matrices.

The algorithm (step control, error estimate, Newton strategy) is written once, in
:mod:`daemodel.backends.radau`, on the arrays of an engine's ``xp`` (numpy or torch, whose
functions share numpy's names).  An engine supplies only the numerical kernels:

- :class:`TorchEngine`: the compiler's batched torch functions (any batch, any device, float32
  or float64), a Jacobian from the compiler's sparse symbolic derivatives scattered into dense
  matrices (forward-mode autograd where a derivative leaves the emitters), batched dense LU.
- :class:`CasadiEngine`: one trajectory on CPU in float64, with casadi-compiled residual,
  right-hand side and sparse Jacobian (casadi's AD), dense LAPACK LU for small systems and
  SuperLU for large sparse ones; no torch code generation and no per-operation dispatch.  On
  dense systems a Newton iteration is one casadi call: the residual, then the increment through
  the blocks' inverses (computed from their LU once per factorisation), which halves the
  iteration's cost on small systems, where Python and numpy calls dominate.

Linear algebra follows RADAU5 (Hairer & Wanner, Solving ODEs II, IV.8): with one Jacobian ``J``
per step, the Newton matrix of the s stages, ``(h A)^-1 (x) M - I (x) J`` with ``M = diag(I, 0)``,
is block-diagonalised by ``A^-1 = T Lambda T^-1`` into one real system ``(gamma / h) M - J`` per
real eigenvalue and one complex system ``((alpha + i beta) / h) M - J`` per complex pair, each of
size n + m (:class:`StageTransform`): for s = 3, one real and one complex LU of size n + m
instead of one real LU of size 3(n + m), about five times less work.
"""

from __future__ import annotations

import math
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from daemodel.backends.radau_compiled import (
    inverse_function,
    inverse_size,
    refresh_function,
    step_function,
    transformed_increment,
)

from daemodel.collocation import stage_residual

# casadi engine: factor the (n+m)-sized systems densely (LAPACK) up to this size, or above it when
# more than DENSE_FILL of the Jacobian is nonzero; sparse (SuperLU) otherwise.  Measured on this
# project's CPU: at 100 unknowns a dense LU of a 3 %-full matrix is ~0.1 ms, as SuperLU's overhead.
DENSE_MAX_SIZE, DENSE_FILL = 100, 0.2
# T Lambda T^-1 must reproduce A^-1 to this relative accuracy (float64 eigenvectors of A^-1).
TRANSFORM_CHECK = 1e-12


@dataclass(frozen=True)
class StageTransform:
    """``A^-1 = T Lambda T^-1`` with ``Lambda`` real block-diagonal, and the shifts of the blocks.

    Attributes
    ----------
    T, T_inv, T_inv_A_inv : ndarray (s, s)
    blocks : tuple of (k, eigenvalue)
        Real eigenvalue ``gamma``: stage k of the transformed system alone.  Complex
        ``alpha + i beta`` (beta > 0): stages k, k+1 as one complex system.
    gamma0 : float
        The error estimate's ``gamma0`` (:func:`~daemodel.backends.radau.embedded_weights`); its
        matrix is ``(1 / (h gamma0)) M - J``, the real block itself when s is odd.
    """

    T: np.ndarray
    T_inv: np.ndarray
    T_inv_A_inv: np.ndarray
    blocks: tuple
    gamma0: float

    @classmethod
    def of(cls, A: np.ndarray, gamma0: float) -> StageTransform:
        A_inv = np.linalg.inv(A)
        eig, vectors = np.linalg.eig(A_inv)
        columns, blocks, diagonal = [], [], []
        for lam, v in sorted(zip(eig, vectors.T, strict=True), key=lambda pair: (pair[0].real, pair[0].imag)):
            if abs(lam.imag) < 1e-12:
                blocks.append((len(columns), complex(lam.real)))
                columns.append(v.real / np.linalg.norm(v.real))
                diagonal.append(np.array([[lam.real]]))
            elif lam.imag > 0:  # its conjugate gives the same pair
                blocks.append((len(columns), complex(lam)))
                columns += [v.real, -v.imag]  # A^-1 [vr, -vi] = [vr, -vi] [[alpha, -beta], [beta, alpha]]
                diagonal.append(np.array([[lam.real, -lam.imag], [lam.imag, lam.real]]))
        T = np.array(columns).T
        T_inv = np.linalg.inv(T)
        Lam = np.zeros_like(A_inv)
        k = 0
        for d in diagonal:
            Lam[k : k + len(d), k : k + len(d)] = d
            k += len(d)
        if np.abs(T @ Lam @ T_inv - A_inv).max() > TRANSFORM_CHECK * np.abs(A_inv).max():
            raise ArithmeticError("radau: the eigen-decomposition of A^-1 is inaccurate")  # daemodel's own bug
        return cls(T=T, T_inv=T_inv, T_inv_A_inv=T_inv @ A_inv, blocks=tuple(blocks), gamma0=gamma0)

    def shifts(self, h: float) -> tuple:
        """The shifts ``sigma`` of every ``sigma M - J`` to factor for step ``h``: the blocks',
        then the error estimate's (the real block's when s is odd)."""
        out = [lam / h for _, lam in self.blocks]
        error = complex(1.0 / (h * self.gamma0))
        if not any(abs(sigma - error) <= 1e-12 * abs(error) for sigma in out):
            out.append(error)
        return tuple(out)


@dataclass
class Factors:
    """The factored systems of one Jacobian and step: ``lu`` by shift, and which samples are singular."""

    h: float
    shifts: tuple
    lu: dict
    singular: object
    error_shift: complex
    complete: bool = True  # False: the error estimate's system alone
    inverse: object = None  # casadi engine, dense: the blocks' inverses packed for its fused Newton step


@dataclass
class StageFactors:
    """The factored full Newton matrix of per-stage Jacobians (no Kronecker structure)."""

    lu: object
    singular: object


@dataclass
class Residual:
    """One evaluation of the stage equations: ``R (B, s, n+m)`` = [F, G] per stage, and f and g at the stages."""

    R: object
    stage_f: object
    G: object


class AbstractEngine(ABC):
    """Numerical kernels of ``method="radau"`` on one backend of arrays (see the module docstring).

    ``y (B, n)``, ``z (B, m)``, stage values ``W (B, s, n+m)``; ``t`` and ``h`` are floats.
    """

    name: str
    xp: object

    def __init__(self, compiled, start, tableau, transform: StageTransform):
        self.compiled, self.tableau, self.transform = compiled, tableau, transform
        self.s, self.n, self.m = tableau.stages, len(compiled.states), len(compiled.algebraics)
        self.D = self.n + self.m
        self.index2_rows = np.array([c.index == 2 for c in compiled.constraints], dtype=bool)
        self._T = None  # T, T^-1, T^-1 A^-1 as this engine's arrays, made on first use

    @abstractmethod
    def asarray(self, values):
        """An array of this engine (its dtype and device) from numpy values."""

    @abstractmethod
    def f(self, t: float, y, z):
        """``f(t, y, z)``, shape (B, n)."""

    @abstractmethod
    def residual(self, t: float, h: float, y, W) -> Residual:
        """The stage equations of :func:`daemodel.collocation.stage_residual`."""

    @abstractmethod
    def jacobian(self, t: float, y, z):
        """``[f_y f_z; g_y g_z]`` at one point per sample (an engine-specific matrix)."""

    @abstractmethod
    def stage_jacobians(self, t: float, h: float, W):
        """The Jacobian at each stage of ``W`` (for full Newton)."""

    @abstractmethod
    def z_matrix_sign(self, J):
        """Sign of det of the algebraic variables' iteration matrix (rows ``g_z`` at index 1,
        ``g_y f_z`` at index 2), shape (B,)."""

    @abstractmethod
    def _factor_shift(self, J, sigma: complex):
        """Factor ``sigma M - J``: ``(lu, singular (B,))``."""

    @abstractmethod
    def solve(self, lu, rhs):
        """Solve one factored ``sigma M - J`` system, ``rhs (B, n+m)`` real or complex."""

    @abstractmethod
    def factor_stages(self, stage_J, h: float) -> StageFactors:
        """Factor the full Newton matrix of the stage equations with per-stage Jacobians."""

    @abstractmethod
    def solve_stages(self, factors: StageFactors, R):
        """Solve the full Newton system ``N dW = -R``, ``R (B, s, n+m)``."""

    @abstractmethod
    def first(self, mask) -> int:
        """Index of the first True of a (B,) mask."""

    def refresh(self, t: float, y, z, h: float):
        """A fresh Jacobian at ``(t, y, z)``: ``(J, factors for step h or None, z_matrix_sign or None)``;
        an engine that computes the factors or the sign along with J returns them (else None)."""
        return self.jacobian(t, y, z), None, None

    def make_compiled_step(self, iterations: int, e: np.ndarray) -> bool:
        """Whether this engine runs an adaptive attempt in one compiled call (see
        :meth:`CasadiEngine.make_compiled_step`); by default it does not."""
        return False

    def newton_increment(self, factors, R):
        """``dW`` solving the Newton system ``N dW = -R`` (``R (B, s, n+m)``), through the
        transformed systems of ``factors`` or the full matrix of :class:`StageFactors`."""
        if isinstance(factors, StageFactors):
            return self.solve_stages(factors, R)
        xp, n, h, tr = self.xp, self.n, factors.h, self.transform
        T, T_inv, T_inv_A_inv = self._transform_arrays()
        # (h A)^-1 on the F rows, -1 on the G rows: the system becomes ((h A)^-1 (x) M - I (x) J) dU = rhs
        rhs = xp.concatenate([(T_inv_A_inv @ R[..., :n]) * (-1.0 / h), T_inv @ R[..., n:]], axis=-1)
        parts = []
        for (k, lam), shift in zip(tr.blocks, factors.shifts, strict=False):
            lu = factors.lu[shift]
            if lam.imag == 0:
                parts.append(self.solve(lu, rhs[:, k]))
            else:
                w = self.solve(lu, rhs[:, k] + 1j * rhs[:, k + 1])
                parts += [w.real, w.imag]
        return T @ xp.stack(parts, axis=1)

    def newton_step(self, factors, t: float, h: float, y, W) -> tuple:
        """The stage residual at ``W`` and Newton's increment from it: ``(Residual, dW)``."""
        r = self.residual(t, h, y, W)
        return r, self.newton_increment(factors, r.R)

    def error_solve(self, factors: Factors, rhs):
        """Solve ``((1 / (h gamma0)) M - J) err = rhs`` (the error estimate's matrix)."""
        return self.solve(factors.lu[factors.error_shift], rhs).real

    def _transform_arrays(self):
        if self._T is None:
            tr = self.transform
            self._T = tuple(self.asarray(a) for a in (tr.T, tr.T_inv, tr.T_inv_A_inv))
        return self._T

    def factor(self, J, h: float, error_only: bool = False) -> Factors:
        """Factor ``sigma M - J`` for every shift of :meth:`StageTransform.shifts`, or (``error_only``)
        for the error estimate's alone."""
        shifts = self.transform.shifts(h)
        target = 1.0 / (h * self.transform.gamma0)
        error = min(shifts, key=lambda sigma: abs(sigma - target))
        lu, singular = self._factor_shifts(J, (error,) if error_only else shifts)
        return Factors(h=h, shifts=shifts, lu=lu, singular=singular, error_shift=error, complete=not error_only)

    def _factor_shifts(self, J, shifts) -> tuple:
        """``sigma M - J`` factored for each of ``shifts``: ``({sigma: factors}, singular (B,))``."""
        lu, singular = {}, None
        for sigma in shifts:
            lu[sigma], bad = self._factor_shift(J, sigma)
            singular = bad if singular is None else singular | bad
        return lu, singular


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

        with warnings.catch_warnings(), fwAD.dual_level():
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
        return (LU, pivots), info > 0

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
        return StageFactors(lu=(LU, pivots), singular=info > 0)

    def solve_stages(self, factors, R):
        LU, pivots = factors.lu
        B, s, D = R.shape
        return self.torch.linalg.lu_solve(LU, pivots, -R.reshape(B, s * D, 1)).reshape(B, s, D)

    def first(self, mask):
        return int(self.torch.nonzero(mask)[0])


class CasadiEngine(AbstractEngine):
    """One trajectory in float64 on casadi-compiled functions and scipy's LU (see the module docstring)."""

    name = "casadi"

    def __init__(self, compiled, start, tableau, transform):
        super().__init__(compiled, start, tableau, transform)
        self.xp = np
        self.B = 1
        self.p = np.asarray(start.p, dtype=float)[0]
        functions = compiled.cached(("casadi-radau", self.s), lambda: _casadi_functions(compiled, tableau))
        self._f, self._residual, self._jac, self._stage_jac = (_Buffered(fn) for fn in functions[:4])
        self.rows, self.cols = functions[4:]
        D = self.D
        self._stage_layout = None  # the full Newton matrix's CSC layout (sparse factor_stages), made on first use
        self.dense = D <= DENSE_MAX_SIZE or len(self.rows) > DENSE_FILL * D * D
        self._step = None  # dense: the fused Newton step (see newton_step), and the factors it is bound to
        self._identity = None  # dense: real and complex identities, the right-hand sides of the inverses
        if self.dense:
            self._identity = (np.eye(D), np.eye(D, dtype=complex))
            step = compiled.cached(("casadi-radau-step", self.s), lambda: _step_function(functions[1], self))
            self._step = [_Buffered(step, inputs=2), None]
        else:
            self._sparse_layout()
        self._compiled = None  # dense: the compiled adaptive step and the factors bound to it (make_compiled_step)
        self._inverses = None  # dense: the compiled inverses of the shifted systems (_compiled_factor)
        self._refresh = None  # dense: Jacobian, inverses and iteration matrix in one call (refresh)
        self._functions = functions

    def make_compiled_step(self, iterations: int, e: np.ndarray) -> bool:
        """Build (or fetch, cached per model, s and ``iterations``) the compiled adaptive step (``e``:
        the error estimate's ``bhat - b``); False
        where the systems are sparse and the step runs on the general path."""
        if not self.dense:
            return False
        compiled, functions = self.compiled, self._functions
        weights = np.array(compiled.algebraic_index, dtype=float)
        step = compiled.cached(
            ("casadi-radau-compiled-step", self.s, iterations),
            lambda: step_function(functions[0], functions[1], self, iterations, e, weights),
        )
        self._compiled = [_Buffered(step, inputs=2), None]
        return True

    def _sparse_layout(self):
        """The CSC pattern of ``sigma M - J`` (J's entries and M's diagonal), and where each goes."""
        n, D = self.n, self.D
        keys_J = self.cols * D + self.rows  # CSC order: by column, then row
        keys_M = np.arange(n) * D + np.arange(n)
        keys = np.unique(np.concatenate([keys_J, keys_M]))
        indptr = np.searchsorted(keys // D, np.arange(D + 1))
        self._csc = (keys % D, indptr, len(keys))
        self._pos_J, self._pos_M = np.searchsorted(keys, keys_J), np.searchsorted(keys, keys_M)

    def asarray(self, values):
        return np.array(values, dtype=float)

    def factor(self, J, h: float, error_only: bool = False) -> Factors:
        if self.dense and not error_only:
            factors = self._compiled_factor(J, h)
            if factors is not None:
                return factors
        factors = super().factor(J, h, error_only)
        if self.dense and factors.complete and not factors.singular.any():
            # the blocks' inverses, column-major as casadi reads them, complex ones as (Re, Im)
            packed = []
            for _, lam in self.transform.blocks:
                inverse = factors.lu[lam / h][1]
                packed += [inverse.real.ravel("F")] + ([inverse.imag.ravel("F")] if lam.imag else [])
            packed.append(factors.lu[factors.error_shift][1].real.ravel("F"))  # the error estimate's (compiled step)
            factors.inverse = np.concatenate(packed)
        return factors

    def _compiled_factor(self, J, h: float, build_only: bool = False) -> Factors | None:
        """The inverses of every shift in one casadi call (:func:`~daemodel.backends.radau_compiled.inverse_function`),
        or None where one is singular or not finite (scipy's LAPACK then factors, and names it)."""
        if self._inverses is None:
            build = lambda: inverse_function(self.rows, self.cols, self)  # noqa: E731
            self._inverses = _Buffered(self.compiled.cached(("casadi-radau-inverses", self.s), build))
        if build_only:
            return None
        try:
            packed = self._inverses(np.concatenate([[h], J]))
        except RuntimeError:
            return None
        return self._packed_factors(packed, h)

    def _packed_factors(self, packed: np.ndarray, h: float) -> Factors | None:
        """:class:`Factors` of the packed inverses of the compiled factorisation; None where one is not finite."""
        if not np.isfinite(packed.sum()):
            return None
        shifts = self.transform.shifts(h)
        target = 1.0 / (h * self.transform.gamma0)
        error = min(shifts, key=lambda sigma: abs(sigma - target))
        lu = _PackedInverses(packed, self.transform.blocks, shifts, error, self.D)
        return Factors(h=h, shifts=shifts, lu=lu, singular=np.array([False]), error_shift=error, inverse=packed)

    def refresh(self, t: float, y, z, h: float):
        """A fresh Jacobian, the systems of step ``h`` factored and the sign of the algebraic variables'
        iteration matrix, in one casadi call on dense systems (:func:`.radau_compiled.refresh_function`)."""
        if not self.dense:
            return super().refresh(t, y, z, h)
        if self._refresh is None:
            self._compiled_factor(None, h, build_only=True)
            build = lambda: refresh_function(self._jac.function, self._inverses.function, self.rows, self.cols, self)  # noqa: E731
            self._refresh = _Buffered(self.compiled.cached(("casadi-radau-refresh", self.s), build))
        try:
            out = self._refresh(np.concatenate([[t], y[0], z[0], self.p, [h]]))
        except RuntimeError:  # a singular system: the general path factors it and names it
            return super().refresh(t, y, z, h)
        nnz, m = len(self.rows), self.m
        J = out[:nnz]
        sign = np.array([_small_sign_det(out[nnz : nnz + m * m], m)])
        return J, self._packed_factors(out[nnz + m * m :], h), sign

    def compiled_step(self, factors: Factors, scalars, previous: np.ndarray, f0: np.ndarray) -> np.ndarray:
        """One adaptive attempt in one call (:mod:`daemodel.backends.radau_compiled`): ``scalars`` in the
        order of its ``SCALARS``, ``previous`` ((s+1) D) the last step's start value and stages, ``f0``
        (n) f at the step's start; returns its packed output."""
        step, bound = self._compiled
        if bound is not factors:
            step.inputs[1][:] = factors.inverse
            self._compiled[1] = factors
        return step(np.concatenate([scalars, previous, f0, self.p]))

    def _factor_shifts(self, values, shifts):
        """Dense systems: the inverse of each ``sigma M - J`` (LAPACK), which the fused Newton step
        applies as a matrix product; sparse ones: SuperLU's factors."""
        if not self.dense:
            return super()._factor_shifts(values, shifts)
        minus_J = -self._dense(values)
        diagonal = slice(0, self.n * (self.D + 1), self.D + 1)  # M's diagonal in the flattened matrix
        lu, singular = {}, False
        for sigma in shifts:
            matrix = minus_J.copy() if sigma.imag == 0 else minus_J.astype(complex)
            matrix.ravel()[diagonal] += sigma.real if sigma.imag == 0 else sigma
            lu[sigma] = _dense_inverse(matrix, self._identity[sigma.imag != 0])
            singular = singular or lu[sigma][0] == "singular"
        return lu, np.array([singular])

    def newton_step(self, factors, t, h, y, W):
        """One casadi call for the residual and the transformed systems' increment (by their inverses)
        on dense systems; the residual and LU solves apart otherwise (full Newton, sparse systems)."""
        if not isinstance(factors, Factors) or factors.inverse is None:
            return super().newton_step(factors, t, h, y, W)
        step, bound = self._step
        if bound is not factors:
            step.inputs[1][:] = factors.inverse
            self._step[1] = factors
        s, n, D = self.s, self.n, self.D
        out = step(np.concatenate([[t, h], y[0], W.ravel(), self.p]))
        R = out[: s * D].reshape(1, s, D)
        stage_f = out[s * D : s * D + s * n].reshape(1, s, n)
        return Residual(R=R, stage_f=stage_f, G=R[..., n:]), out[s * D + s * n :].reshape(1, s, D)

    def f(self, t, y, z):
        return self._f(np.concatenate([[t], y[0], z[0], self.p]))[None]

    def residual(self, t, h, y, W):
        s, n, D = self.s, self.n, self.D
        out = self._residual(np.concatenate([[t, h], y[0], W.ravel(), self.p]))
        R = out[: s * D].reshape(1, s, D)
        return Residual(R=R, stage_f=out[s * D :].reshape(1, s, n), G=R[..., n:])

    def jacobian(self, t, y, z):
        return self._jac(np.concatenate([[t], y[0], z[0], self.p]))

    def stage_jacobians(self, t, h, W):
        values = self._stage_jac(np.concatenate([[t, h], W.ravel(), self.p]))
        return list(values.reshape(self.s, -1))

    def _dense(self, values) -> np.ndarray:
        J = np.zeros((self.D, self.D))
        J[self.rows, self.cols] = values
        return J

    def _csr(self, values):
        import scipy.sparse as sparse

        return sparse.csr_matrix((values, (self.rows, self.cols)), shape=(self.D, self.D))

    def z_matrix_sign(self, values):
        if isinstance(values, list):  # the stages' Jacobians: (1, s)
            return np.array([[self.z_matrix_sign(v)[0] for v in values]])
        n = self.n
        if self.dense:
            J = self._dense(values)
            rows = J[n:, n:].copy()
            if self.index2_rows.any():
                rows[self.index2_rows] = (J[n:, :n] @ J[:n, n:])[self.index2_rows]
            return np.array([_dense_sign_det(rows)])
        if self.m <= DENSE_MAX_SIZE:  # a small z block of a large system: dense blocks of J suffice
            g_rows = self.rows >= n
            G = np.zeros((self.m, self.D))
            G[self.rows[g_rows] - n, self.cols[g_rows]] = values[g_rows]
            rows = G[:, n:].copy()
            if self.index2_rows.any():
                f_z = (self.rows < n) & (self.cols >= n)
                F = np.zeros((n, self.m))
                F[self.rows[f_z], self.cols[f_z] - n] = values[f_z]
                rows[self.index2_rows] = (G[:, :n] @ F)[self.index2_rows]
            return np.array([_dense_sign_det(rows)])
        import scipy.sparse as sparse

        J = self._csr(values)
        rows = J[n:, n:]
        if self.index2_rows.any():
            pick = sparse.diags(self.index2_rows.astype(float))
            rows = rows - pick @ rows + pick @ (J[n:, :n] @ J[:n, n:])
        return np.array([_sparse_sign_det(rows.tocsc())])

    def _factor_shift(self, values, sigma):
        """SuperLU's factors of ``sigma M - J`` (dense systems: see :meth:`_factor_shifts`)."""
        import scipy.sparse as sparse

        real = sigma.imag == 0

        indices, indptr, nnz = self._csc
        data = np.zeros(nnz, dtype=float if real else complex)
        data[self._pos_J] = -values
        data[self._pos_M] += sigma.real if real else sigma
        return _sparse_lu(sparse.csc_matrix((data, indices, indptr), shape=(self.D, self.D)))

    def solve(self, lu, rhs):
        kind = lu[0]
        if kind == "inverse":
            return (lu[1] @ rhs[0])[None]
        if kind == "dense":
            LU, piv, getrs = lu[1:]
            if not np.iscomplexobj(LU) and np.iscomplexobj(rhs):
                return (getrs(LU, piv, rhs[0].real)[0] + 1j * getrs(LU, piv, rhs[0].imag)[0])[None]
            return getrs(LU, piv, rhs[0])[0][None]
        if kind == "singular":
            return np.full_like(rhs, np.nan)
        return lu[1].solve(rhs[0])[None]

    def factor_stages(self, stage_J, h):
        s, n, D = self.s, self.n, self.D
        A = self.tableau.A
        if self.dense:
            # rows [F_i; G_i] and unknowns [Y_j; Z_j] stage by stage (see TorchEngine.factor_stages)
            Js = np.stack([self._dense(v) for v in stage_J])  # (s, D, D)
            N = np.zeros((s, D, s, D))
            N[:, :n] = (-h * A[:, None, :, None]) * Js[None, :, :n, :].transpose(0, 2, 1, 3)
            for i in range(s):
                N[i, n:, i, :] = Js[i, n:, :]
                N[i, :n, i, :n] += np.eye(n)
            lu, singular = _dense_lu(N.reshape(s * D, s * D))
            return StageFactors(lu=lu, singular=singular)
        import scipy.sparse as sparse

        if self._stage_layout is None:
            self._stage_layout = self._full_newton_layout()
        top, bottom, positions, (indices, indptr, nnz) = self._stage_layout
        V = np.stack(stage_J)  # (s, nnz of J)
        values = np.concatenate(
            [((-h) * A[:, :, None] * V[None, :, top]).ravel(), V[:, bottom].ravel(), np.ones(s * n)]
        )
        data = np.bincount(positions, weights=values, minlength=nnz)  # sums the identity into J's diagonal
        lu, singular = _sparse_lu(sparse.csc_matrix((data, indices, indptr), shape=(s * D, s * D)))
        return StageFactors(lu=lu, singular=singular)

    def _full_newton_layout(self):
        """Where each entry of the full Newton matrix goes in its CSC data, computed once.

        Entries, in the order :meth:`factor_stages` lays out their values: ``-h a_ij J_j`` on the F rows
        of every block (i, j), ``J_i`` on the G rows of the diagonal blocks, the identity of the F rows.
        """
        s, n, D = self.s, self.n, self.D
        top, bottom = np.flatnonzero(self.rows < n), np.flatnonzero(self.rows >= n)
        i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
        rows = [
            (i[:, :, None] * D + self.rows[None, None, top]).ravel(),
            (np.arange(s)[:, None] * D + self.rows[None, bottom]).ravel(),
            (np.arange(s)[:, None] * D + np.arange(n)[None, :]).ravel(),
        ]
        cols = [
            (j[:, :, None] * D + self.cols[None, None, top]).ravel(),
            (np.arange(s)[:, None] * D + self.cols[None, bottom]).ravel(),
            rows[2],
        ]
        keys_all = np.concatenate(cols) * (s * D) + np.concatenate(rows)  # CSC order: column, then row
        keys = np.unique(keys_all)
        indptr = np.searchsorted(keys // (s * D), np.arange(s * D + 1))
        return top, bottom, np.searchsorted(keys, keys_all), (keys % (s * D), indptr, len(keys))

    def solve_stages(self, factors, R):
        s, D = self.s, self.D
        return self.solve(factors.lu, -R.reshape(1, s * D)).reshape(1, s, D)

    def first(self, mask):
        return int(np.flatnonzero(mask)[0])


class _PackedInverses(dict):
    """``{shift: ("inverse", matrix)}`` read from the packed inverses of the compiled factorisation
    when first asked for (the compiled step reads the packed array itself; the general path's LU
    solves need the matrices)."""

    def __init__(self, packed, blocks, shifts, error_shift, D):
        super().__init__()
        self._where, offset = {}, 0
        for (_, lam), sigma in zip(blocks, shifts, strict=False):
            self._where[sigma] = (offset, bool(lam.imag))
            offset += (2 if lam.imag else 1) * D * D
        self._where.setdefault(error_shift, (offset, False))
        self._packed, self._D = packed, D

    def __missing__(self, sigma):
        offset, complex_ = self._where[sigma]
        D2, D = self._D * self._D, self._D
        matrix = self._packed[offset : offset + D2].reshape(D, D, order="F")
        if complex_:
            matrix = matrix + 1j * self._packed[offset + D2 : offset + 2 * D2].reshape(D, D, order="F")
        self[sigma] = ("inverse", matrix)
        return self[sigma]


class _Buffered:
    """A casadi function of one dense vector, evaluated on bound numpy buffers (casadi's
    FunctionBuffer: ~3 us a call, against ~40-100 us through argument conversion)."""

    def __init__(self, function, inputs: int = 1):
        # inputs after the first stay bound between calls: write them through ``inputs[k][:]``
        self.inputs = [np.zeros(function.nnz_in(k)) for k in range(inputs)]
        self._inputs = self.inputs[0]
        self._outputs = np.zeros(function.nnz_out(0))
        self._buffer, self._evaluate = function.buffer()
        for k, values in enumerate(self.inputs):
            self._buffer.set_arg(k, memoryview(values))
        self._buffer.set_res(0, memoryview(self._outputs))
        self.name = function.name()
        self.function = function

    def __call__(self, values: np.ndarray) -> np.ndarray:
        self._inputs[:] = values
        self._evaluate()
        if self._buffer.ret() != 0:
            raise RuntimeError(f"casadi function {self.name} failed (return code {self._buffer.ret()})")
        return self._outputs.copy()


def _casadi_functions(compiled, tableau):
    """casadi functions of the casadi engine (cached on the compiled model, per s).

    Each takes one packed vector and returns one (a call costs ~20 us per argument): ``f`` of
    ``[t, y, z, p]``; the stage residual (the equations of
    :func:`daemodel.collocation.stage_residual`) of ``[t, h, y_n, W, p]``, ``W`` stage by stage
    ``[Y_i, Z_i]``, returning ``[R (stage by stage [F_i, G_i]), f at the stages]``; the Jacobian's
    nonzeros at ``[t, y, z, p]`` and at every stage of ``[t, h, W, p]``; its pattern (rows, cols).
    """
    import casadi

    dae = compiled.casadi_dae()
    t, x, z, p = dae["t"], dae["x"], dae["z"], dae["p"]
    s, n, D = tableau.stages, x.numel(), x.numel() + z.numel()
    f = casadi.Function("f", [t, x, z, p], [dae["ode"]])
    g = casadi.Function("g", [t, x, z, p], [dae["alg"]])
    jac = casadi.jacobian(casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(x, z))
    jac = casadi.Function("jacobian", [t, x, z, p], [jac.nz[:]]), jac.sparsity().get_triplet()
    h, y_n, W = casadi.SX.sym("h"), casadi.SX.sym("y_n", n), casadi.SX.sym("W", s * D)
    A, c = tableau.A, tableau.c
    times = [t + float(c[i]) * h for i in range(s)]
    Y = [W[i * D : i * D + n] for i in range(s)]
    Z = [W[i * D + n : (i + 1) * D] for i in range(s)]
    stage_f = [f(times[i], Y[i], Z[i], p) for i in range(s)]
    rows = []
    for i in range(s):
        quadrature = sum((float(A[i, j]) * stage_f[j] for j in range(s)), casadi.SX.zeros(n))
        rows += [Y[i] - y_n - h * quadrature, g(times[i], Y[i], Z[i], p)]
    return (
        casadi.Function("f", [casadi.vertcat(t, x, z, p)], [dae["ode"]]),
        casadi.Function("residual", [casadi.vertcat(t, h, y_n, W, p)], [casadi.vertcat(*rows, *stage_f)]),
        casadi.Function("jacobian", [casadi.vertcat(t, x, z, p)], [jac[0](t, x, z, p)]),
        casadi.Function(
            "stage_jacobians",
            [casadi.vertcat(t, h, W, p)],
            [casadi.vertcat(*(jac[0](times[i], Y[i], Z[i], p) for i in range(s)))],
        ),
        np.asarray(jac[1][0], dtype=np.int64),
        np.asarray(jac[1][1], dtype=np.int64),
    )


def _step_function(residual, engine):
    """casadi function of the fused Newton step (:meth:`CasadiEngine.newton_step`).

    Inputs: the residual's packed ``[t, h, y_n, W, p]`` and the packed inverses of
    :meth:`CasadiEngine.factor`; output ``[R, f at the stages, dW]``: the increment through the
    transformed systems, exactly as :meth:`AbstractEngine.newton_increment` computes it with LU
    solves.  Matrix products are MX (dense kernels), the residual the SX function inside.
    """
    import casadi

    s, n, D, tr = engine.s, engine.n, engine.D, engine.transform
    x = casadi.MX.sym("x", residual.nnz_in(0))
    inverse = casadi.MX.sym("inverse", inverse_size(tr, D))
    out = residual(x)
    R = casadi.reshape(out[: s * D], D, s)  # column i: stage i's [F_i; G_i]
    dW = transformed_increment(casadi, R, x[1], inverse, tr, n, D)  # column i: stage i's increment
    return casadi.Function("newton_step", [x, inverse], [casadi.vertcat(out, casadi.vec(dW))])


def _dense_inverse(matrix: np.ndarray, identity: np.ndarray) -> tuple:
    """``("inverse", matrix^-1)`` by LAPACK (``gesv`` on ``identity``, of the matrix's dtype), or
    ``("singular",)`` when it is singular or the inverse overflows."""
    from scipy.linalg import lapack

    gesv = lapack.zgesv if np.iscomplexobj(matrix) else lapack.dgesv
    _, _, inverse, info = gesv(matrix, identity)
    # (the sum is not finite when any entry is not, or when the entries are near overflow: singular enough)
    return ("inverse", inverse) if info == 0 and np.isfinite(inverse.sum()) else ("singular",)


def _dense_lu(matrix: np.ndarray):
    """LAPACK's LU of a dense square matrix: ``(("dense", LU, pivots, getrs), singular (1,))``."""
    from scipy.linalg import lapack

    getrf, getrs = (lapack.zgetrf, lapack.zgetrs) if np.iscomplexobj(matrix) else (lapack.dgetrf, lapack.dgetrs)
    LU, piv, info = getrf(matrix, overwrite_a=True)
    return ("dense", LU, piv, getrs), np.array([info > 0 or not np.isfinite(LU).all()])


def _sparse_lu(matrix):
    """SuperLU's factors of a sparse CSC matrix: ``(("sparse", lu), singular (1,))``."""
    import scipy.sparse.linalg as splinalg

    try:
        return ("sparse", splinalg.splu(matrix)), np.array([False])
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        return ("singular",), np.array([True])


def _small_sign_det(values: np.ndarray, m: int) -> float:
    """Sign of the determinant of the (m, m) matrix of ``values`` (column-major): by its formula up to
    m = 3 (a few Python operations, where a LAPACK call costs 7 us), else :func:`_dense_sign_det`."""
    if m == 1:
        det = values[0]
    elif m == 2:
        det = values[0] * values[3] - values[1] * values[2]
    elif m == 3:
        a, b, c, d, e, f, g, h, i = values.tolist()  # columns (a, b, c), (d, e, f), (g, h, i)
        det = a * (e * i - f * h) - d * (b * i - c * h) + g * (b * f - c * e)
    else:
        return _dense_sign_det(values.reshape(m, m, order="F"))
    return float(np.sign(det)) if math.isfinite(det) else 0.0


def _dense_sign_det(matrix: np.ndarray) -> float:
    """Sign of the determinant of a dense square matrix (0 when singular or not finite), from LAPACK's LU
    (numpy's slogdet costs 10 us of overhead on the few-element matrices of a step)."""
    from scipy.linalg import lapack

    if matrix.shape[0] == 0:
        return 1.0
    LU, piv, info = lapack.dgetrf(matrix)
    diagonal = LU.diagonal()
    if info > 0 or not np.isfinite(diagonal).all():
        return 0.0
    swaps = int(np.count_nonzero(piv != np.arange(len(piv))))
    return float(np.prod(np.sign(diagonal))) * (-1.0 if swaps % 2 else 1.0)


def _sparse_sign_det(matrix) -> float:
    """Sign of the determinant of a sparse square matrix (0 when singular), from SuperLU's factors."""
    import scipy.sparse.linalg as splinalg

    if matrix.shape[0] == 0:
        return 1.0
    try:
        lu = splinalg.splu(matrix)
    except RuntimeError:
        return 0.0
    sign = float(np.prod(np.sign(lu.U.diagonal())))
    return sign * _permutation_sign(lu.perm_r) * _permutation_sign(lu.perm_c)


def _permutation_sign(perm: np.ndarray) -> float:
    """+1 or -1: the parity of a permutation, from its cycles."""
    seen = np.zeros(len(perm), dtype=bool)
    transpositions = 0
    for start in range(len(perm)):
        length = 0
        k = start
        while not seen[k]:
            seen[k] = True
            k = perm[k]
            length += 1
        transpositions += max(length - 1, 0)
    return -1.0 if transpositions % 2 else 1.0
