"""The simplified Newton increment through RADAU5's transformed systems, on casadi symbols: the
right-hand sides from the stage residual (``T^-1 A^-1`` and ``T^-1``), the systems' packed factors
(:class:`DenseInverses`, the blocks' inverses; :class:`StaticFactors`, sparse LU with a fixed pivot
order) and the increment back through ``T``, for :mod:`.compiled`'s attempt (in machine code on static
factors the transforms are loops of :mod:`.kernel`, :func:`.kernel.transform_calls`); and the packed
inverses read back as matrices for the general path (:class:`PackedInverses`)."""

from __future__ import annotations

from daemodel.backends.radau.kernel import UNROLLED_SOLVE_MAX_ENTRIES, solve_call


def transformed_increment(casadi, R, h, inverse, transform, n: int, D: int, solver=None):
    """``dW`` (D, s) from the stage residual ``R`` (D, s) through the transformed systems, whose
    factors come packed (``solver``: :class:`DenseInverses` by default, the blocks' inverses, or
    :class:`StaticFactors`): the increment :meth:`AbstractEngine.newton_increment` computes with LU solves."""
    solver = solver or DenseInverses(transform, D)
    rhs = casadi.vertcat(
        casadi.mtimes(R[:n, :], casadi.DM(transform.T_inv_A_inv.T)) * (-1.0 / h),
        casadi.mtimes(R[n:, :], casadi.DM(transform.T_inv.T)),
    )
    columns = []
    for index, (k, lam) in enumerate(transform.blocks):
        if lam.imag == 0:
            columns.append(solver.real(casadi, inverse, index, rhs[:, k]))
        else:
            columns += solver.complex(casadi, inverse, index, rhs[:, k], rhs[:, k + 1])
    return casadi.mtimes(casadi.horzcat(*columns), casadi.DM(transform.T.T))


class DenseInverses:
    """The transformed systems' inverses packed column-major: each block's (a complex one as (Re, Im)),
    then the error estimate's system's; applied by matrix products."""

    def __init__(self, transform, D: int):
        self.D, self.offsets = D, []
        offset = 0
        for _, lam in transform.blocks:
            self.offsets.append(offset)
            offset += (2 if lam.imag else 1) * D * D
        self.error_offset, self.size = offset, offset + D * D

    def real(self, casadi, packed, block: int, rhs):
        o, D = self.offsets[block], self.D
        return casadi.mtimes(casadi.reshape(packed[o : o + D * D], D, D), rhs)

    def complex(self, casadi, packed, block: int, re, im):
        o, D = self.offsets[block], self.D
        real = casadi.reshape(packed[o : o + D * D], D, D)
        imag = casadi.reshape(packed[o + D * D : o + 2 * D * D], D, D)
        return [casadi.mtimes(real, re) - casadi.mtimes(imag, im), casadi.mtimes(imag, re) + casadi.mtimes(real, im)]

    def error(self, casadi, packed, rhs):
        o, D = self.error_offset, self.D
        return casadi.mtimes(casadi.reshape(packed[o : o + D * D], D, D), rhs)


class StaticFactors:
    """The transformed systems' sparse LU factors with a fixed pivot order (:class:`.sparse.StaticLU`)
    packed: each block's (real, or complex as (Re, Im) parts), then the error estimate's system's
    where it is no block's (s even), then the factorisation's largest growth and smallest pivot (over
    the systems); applied by triangular solves: straight-line SX, or with ``machine`` above
    :data:`.kernel.UNROLLED_SOLVE_MAX_ENTRIES` entries calls into the loops of :mod:`.kernel` (for
    machine code only: :func:`.kernel.solve_call`; the same bits)."""

    def __init__(self, lu, transform, machine: bool = False):
        self.lu, self.offsets, self.machine, self._solves = lu, [], machine, None
        self.complex_blocks = [bool(lam.imag) for _, lam in transform.blocks]
        offset = 0
        for _, lam in transform.blocks:
            self.offsets.append(offset)
            offset += lu.size(bool(lam.imag))
        if transform.error_block is not None:
            self.error_offset = self.offsets[transform.error_block]
        else:
            self.error_offset, offset = offset, offset + lu.size(False)
        self.checks_offset, self.size = offset, offset + 2

    @property
    def solves(self) -> dict:
        """The real (False) and complex (True) triangular solves as casadi functions of ``[packed factors
        of one system, b]`` (made on first use: the SX ones of a chain of 20 pendulums take 0.2 s)."""
        if self._solves is None:
            if self.machine and self.lu.entries > UNROLLED_SOLVE_MAX_ENTRIES:
                self._solves = {complex_: solve_call(self.lu, complex_) for complex_ in (False, True)}
            else:
                self._solves = {complex_: self.lu.solve_function(complex_) for complex_ in (False, True)}
        return self._solves

    def real(self, casadi, packed, block: int, rhs):
        o = self.offsets[block]
        return self.solves[False](packed[o : o + self.lu.size(False)], rhs)

    def complex(self, casadi, packed, block: int, re, im):
        o = self.offsets[block]
        out = self.solves[True](packed[o : o + self.lu.size(True)], casadi.vertcat(re, im))
        return [out[: self.lu.D], out[self.lu.D :]]

    def stacked(self, casadi, packed, block: int, rhs):
        """Block ``block``'s system solved for ``rhs``, a complex one's real and imaginary parts stacked
        (in and out: the complex solve's own layout, no copies)."""
        complex_ = self.complex_blocks[block]
        o = self.offsets[block]
        return self.solves[complex_](packed[o : o + self.lu.size(complex_)], rhs)

    def error(self, casadi, packed, rhs):
        return self.solves[False](packed[self.error_offset : self.error_offset + self.lu.size(False)], rhs)


def static_factor_function(lu, transform):
    """casadi SX function of the packed :class:`StaticFactors` from ``[h, J's nonzeros]``: each block's
    factors, the error system's where it is no block's, the largest growth and the smallest pivot."""
    import casadi

    x = casadi.SX.sym("x", 1 + len(lu.rows))
    h, J = x[0], x[1:]
    packed, growth, pivot = [], casadi.SX(0), casadi.SX(casadi.inf)
    shifts = [lam for _, lam in transform.blocks]
    shifts += [complex(1.0 / transform.gamma0)] if transform.error_block is None else []
    for lam in shifts:
        values, block_growth, block_pivot = lu.factor_expressions(casadi, h, J, lam, bool(lam.imag))
        packed += values
        growth, pivot = casadi.fmax(growth, block_growth), casadi.fmin(pivot, block_pivot)
    return casadi.Function("static_factors", [x], [casadi.vertcat(*packed, growth, pivot)])


def inverse_size(transform, D: int) -> int:
    """Entries of the packed inverses: the blocks' (a complex one twice), then the error estimate's."""
    return DenseInverses(transform, D).size


class PackedInverses(dict):
    """``{shift: ("inverse", matrix)}`` read from the packed inverses of the compiled factorisation
    when first asked for (the compiled step reads the packed array itself; the general path's LU
    solves need the matrices)."""

    def __init__(self, packed, transform, shifts, D):
        super().__init__()
        self._packed, self._transform, self._shifts, self._D = packed, transform, shifts, D

    def __missing__(self, sigma):
        D, offset = self._D, 0
        for (_, lam), shift in zip(self._transform.blocks, self._shifts, strict=False):
            if shift == sigma:
                break
            offset += (2 if lam.imag else 1) * D * D
        else:
            lam = 0j  # the error estimate's own system (s even): last, real
        D2 = D * D
        matrix = self._packed[offset : offset + D2].reshape(D, D, order="F")
        if lam.imag:
            matrix = matrix + 1j * self._packed[offset + D2 : offset + 2 * D2].reshape(D, D, order="F")
        self[sigma] = ("inverse", matrix)
        return self[sigma]
