"""What an engine of ``method="radau"`` supplies, and the records it returns.

The algorithm (step control, error estimate, Newton strategy) is written once, in the modules of
:mod:`daemodel.backends.radau`, on the arrays of an engine's ``xp`` (numpy or torch, whose
functions share numpy's names).  An engine supplies only the numerical kernels: residuals,
Jacobians, factorisations and solves of the transformed systems (:mod:`.transform`).  Two engines
implement it: :class:`~.torch_engine.TorchEngine` (batches, float32, GPUs) and
:class:`~.casadi_engine.CasadiEngine` (one trajectory in float64 on the CPU, compiled).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from daemodel.backends.radau.transform import StageTransform


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

    def release(self) -> None:
        """Drop the factored systems (a stale Jacobian's, replaced while a caller still holds these): the
        band kernel's buffers go back to its spares before the fresh factors are made (.band.BandKernel)."""
        self.lu, self.inverse = {}, None


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


def factors_bytes(factors) -> int:
    """The bytes the factorisation ``factors`` holds (:class:`Factors` or :class:`StageFactors`): every
    array of its factored systems (LAPACK's LU and pivots, dense inverses, the band kernel's packed
    buffers, the static factors' packed array) counted once, however many views of it there are, and
    SuperLU's factors by the entries it stores (``nnz``: a value and an int32 row index each) and its
    column pointers and permutations.  ``stats["factor_bytes"]`` reports the largest over a solve."""
    seen = {}

    def add(item, complex_: bool) -> None:
        if isinstance(item, np.ndarray):
            while isinstance(item.base, np.ndarray):  # (a view: its owner's bytes, once)
                item = item.base
            seen[id(item)] = item.nbytes
        elif isinstance(item, (tuple, list)):
            for part in item:
                add(part, complex_)
        elif hasattr(item, "untyped_storage"):  # (a torch tensor: its storage, once)
            seen[item.untyped_storage().data_ptr()] = item.untyped_storage().nbytes()
        elif hasattr(item, "packed"):  # (.band.BandLU: its kernel's buffer)
            add(item.packed, complex_)
        elif hasattr(item, "lu"):  # (.linalg.OrderedLU: SuperLU's factors in the band order)
            add(item.lu, complex_)
        elif hasattr(item, "perm_c"):  # (scipy's SuperLU)
            seen[id(item)] = item.nnz * ((16 if complex_ else 8) + 4) + 3 * 4 * item.shape[0]

    if isinstance(factors, StageFactors):
        add(factors.lu, False)
    else:
        for shift, lu in factors.lu.items():
            add(lu, bool(complex(shift).imag))
        add(factors.inverse, False)
    return sum(seen.values())


class AbstractEngine(ABC):
    """Numerical kernels of ``method="radau"`` on one backend of arrays (see the module docstring).

    ``y (B, n)``, ``z (B, m)``, stage values ``W (B, s, n+m)``; ``t`` and ``h`` are floats.
    """

    name: str
    xp: object
    jit = False  # (the casadi engine's steps in machine code: see CasadiEngine)
    increment = None  # (numpy, one sample: the transformed systems' increment in buffers, .transform.IncrementBuffers)

    def __init__(self, compiled, start, tableau, transform: StageTransform):
        self.compiled, self.tableau, self.transform = compiled, tableau, transform
        self.s, self.n, self.m = tableau.stages, len(compiled.states), len(compiled.algebraics)
        self.D = self.n + self.m
        self.index2_rows = np.array([c.index == 2 for c in compiled.constraints], dtype=bool)
        self._T = None  # T, T^-1, T^-1 A^-1 as this engine's arrays, made on first use
        # (t0, t1, y, z, atol, rtol) -> (h, f at the start): the first step of adaptive steps in one call, made in
        # the setup where an engine has it (the casadi engine's: .start); None: the controller computes it
        self.first_step = None

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

    def make_compiled_step(self, iterations: int, e: np.ndarray, jit: bool = False) -> bool:
        """Whether this engine runs an adaptive attempt in one compiled call (see
        :meth:`CasadiEngine.make_compiled_step`); by default it does not."""
        return False

    def make_newton_step(self) -> None:
        """Build, in the setup, what the general path's Newton step compiles (see
        :meth:`CasadiEngine.make_newton_step`); by default nothing."""
        return None

    def make_compiled_run(self, iterations: int):
        """Many attempts of the RADAU5 controller in one call (see :meth:`CasadiEngine.make_compiled_run`),
        or None: by default there is none."""
        return None

    def newton_increment(self, factors, R, over: bool = False):
        """``dW`` solving the Newton system ``N dW = -R`` (``R (B, s, n+m)``), through the
        transformed systems of ``factors`` or the full matrix of :class:`StageFactors`.  A residual
        that overflowed gives a non-finite increment, which Newton's loop counts as a failure of the
        attempt (shorter h): numpy's warnings about it would only repeat that to the user.  ``over``: R is
        the engine's residual buffer (:meth:`newton_step`'s), which the increment may be written over."""
        with np.errstate(invalid="ignore", over="ignore"):
            return self._newton_increment(factors, R, over)

    def _newton_increment(self, factors, R, over=False):
        if isinstance(factors, StageFactors):
            return self.solve_stages(factors, R)
        if self.increment is not None:  # (the same operations, in buffers made once)
            return self.increment(factors, R, self.solve, self._transform_arrays(), over)
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

    def stage_values(self, t: float, h: float, y, W) -> Residual:
        """f at the stages of ``W`` (the error estimate's, once Newton has converged): a :class:`Residual`
        whose ``stage_f`` is :meth:`residual`'s; an engine may leave ``R`` and ``G`` out (None)."""
        return self.residual(t, h, y, W)

    def newton_step(self, factors, t: float, h: float, y, W) -> tuple:
        """The stage residual at ``W`` and Newton's increment from it: ``(Residual, dW)``; on numpy, one sample,
        the increment may be written over the residual's ``R`` and ``G`` (:class:`.transform.IncrementBuffers`)."""
        r = self.residual(t, h, y, W)
        return r, self.newton_increment(factors, r.R, over=True)

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
        error = self.transform.error_shift(shifts)
        lu, singular = self._factor_shifts(J, (error,) if error_only else shifts)
        return Factors(h=h, shifts=shifts, lu=lu, singular=singular, error_shift=error, complete=not error_only)

    def _factor_shifts(self, J, shifts) -> tuple:
        """``sigma M - J`` factored for each of ``shifts``: ``({sigma: factors}, singular (B,))``."""
        lu, singular = {}, None
        for sigma in shifts:
            lu[sigma], bad = self._factor_shift(J, sigma)
            singular = bad if singular is None else singular | bad
        return lu, singular
