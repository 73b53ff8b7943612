"""The algebraic variables solved again from a method's states at its outputs (adaptive radau, where
some have index 2 or more, and its dense output between them).

Collocation's values of an algebraic variable of index 2 are of order s at the step ends where the
states are of order 2s - 1, and adaptive steps weigh their error estimate by h, as RADAU5 does: at
rtol = atol = 1e-10 the car axis's multipliers were 3.8 tolerances off their own hidden constraint
at the step ends (s = 3: 13), the Hessenberg example's y5 10.5, and a circle's z 212 at s = 3, with
status success.  The same variables solved from the determining equations (``g_t + g_y f = 0`` at
index 2) at the returned states carry the states' error only: the car axis's multipliers read 13.58
digits so where the collocation's read 8.30, and the circle's and the Hessenberg example's z were
within 0.15 tolerances of the closed form.  So the outputs take those, and the difference
(the collocation's error, estimated) is reported.

That solve is on every adaptive solve's clock.  Determining equations affine in z (mechanics: always) take one
whole Newton step in one casadi function of the outputs, made in the setup (:class:`AffineStep`): 21 outputs of
a chain of 20 pendulums cost 0.9-1.1 ms on the batched numpy path (thread CPU), as much as half of radau's
solve at loose tolerances, and 0.18-0.28 ms so (benchmarks/affine_resolve.py).  Where the step does not settle,
and for other equations, the numpy path solves.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.compiling.batch_function import made_since
from daemodel.compiling.determinants import householder_sign, odd_permutation
from daemodel.compiling.init import NewtonTolerances, jacobian_entries, residual_settled, solve_algebraic
from daemodel.compiling.initial_states import constraint_checks
from daemodel.compiling.linear import SPARSE_MIN_SIZE
from daemodel.errors import UnsupportedFunctionError

# Newton steps at most from the collocation's values, which lie within a few tolerances of the root:
# determining equations linear in z (mechanics) settle in one, others in a few.
RESOLVE_MAX_ITERATIONS = 20
# Outputs solved at a time: as many as keep their dense z Jacobians (m x m each) within these bytes (a long run of
# a model with tens of algebraic variables would otherwise hold hundreds of megabytes of them at once).
RESOLVE_BYTES = 64 * 2**20
# Samples that one call of the affine step (:class:`AffineStep`) evaluates: a casadi map of the step over each of
# these many, made in the setup; the outputs are cut into the largest first (21 outputs: 16 + 4 + 1), so that no
# sample is evaluated for nothing and Python runs a few times a solve, not once an output.
AFFINE_BATCHES = (32, 16, 8, 4, 2, 1)
# Casadi instructions of the affine step at most (~1 ns each on casadi's virtual machine: 0.1 ms a sample); a
# larger one, and algebraic variables from linear.SPARSE_MIN_SIZE on, take Newton's batched numpy path.
AFFINE_MAX_INSTRUCTIONS = 100_000


def resolves_algebraic(compiled) -> bool:
    """Whether ``compiled`` has algebraic variables of index 2 or more (only those are solved again)."""
    return bool(compiled.algebraics) and max(compiled.algebraic_index) >= 2


@dataclass(frozen=True)
class Resolved:
    """Result of :func:`algebraic_from_states`.

    Attributes
    ----------
    z : ndarray, shape (B, K, m)
        The algebraic variables solved from the states; where Newton failed, the values given.
    converged : ndarray of bool, shape (B, K)
    signs : ndarray, shape (B, K), or None
        ``sign(det H_z)`` at each point (-1 or +1), read off the affine step's QR of ``H_z`` (free of z there:
        the same matrix at the values given and at those returned), NaN where the QR cannot tell
        (:func:`~daemodel.compiling.determinants.householder_sign`); None without the affine step.  The
        branch check's signs (:func:`~daemodel.compiling.initial_states.check_branch`), made here for free.
    """

    z: np.ndarray
    converged: np.ndarray
    signs: np.ndarray | None = None


def algebraic_from_states(compiled, times, Y, Z, P) -> Resolved:
    """The algebraic variables that the states ``Y`` (B, K, n) determine at ``times`` (K,): one Newton solve of
    the determining equations of every algebraic variable, started from ``Z`` (B, K, m), with the parameters
    ``P`` (B, k).  Where they are affine in z (mechanics), first one whole Newton step in casadi
    (:func:`affine_step`), kept where it settles as :func:`~daemodel.compiling.init.solve_algebraic` settles a
    linear first step; the other points (and every point of other equations) go to that batched Newton (the
    one algebraic Newton) from ``Z``.  The caller decides what a point that did not converge means."""
    Y, Z = np.asarray(Y, dtype=float), np.asarray(Z, dtype=float)
    B, K, n = Y.shape
    m = Z.shape[2]
    if not K or not m:
        return Resolved(Z.copy(), np.ones((B, K), dtype=bool))
    settings = tolerances(compiled)
    rows_t, rows_y = np.tile(np.asarray(times, dtype=float), B), Y.reshape(B * K, n)
    rows_p, rows_z = np.repeat(np.asarray(P, dtype=float), K, axis=0), Z.reshape(B * K, m)
    step = affine_step(compiled) if settings.max_iterations >= 1 else None
    signs = None
    if step is None:
        x, converged = _newton(compiled, settings, rows_t, rows_y, rows_z, rows_p)
    else:
        x, converged, signs = step(rows_t, rows_y, rows_z, rows_p, settings)
        rest = np.flatnonzero(~converged)
        if rest.size:  # (a singular H_z, values not finite, rounding above the bound: Newton from the start)
            x[rest], converged[rest] = _newton(
                compiled, settings, rows_t[rest], rows_y[rest], rows_z[rest], rows_p[rest]
            )
    return Resolved(x.reshape(B, K, m), converged.reshape(B, K), None if signs is None else signs.reshape(B, K))


def _newton(compiled, settings, rows_t, rows_y, rows_z, rows_p) -> tuple[np.ndarray, np.ndarray]:
    """``(z, converged)`` of rows of samples by :func:`~daemodel.compiling.init.solve_algebraic` from ``rows_z``
    (kept where it fails), a chunk of at most :data:`RESOLVE_BYTES` of z Jacobians at a time."""
    checks, (R, m) = constraint_checks(compiled), rows_z.shape
    x, converged = rows_z.copy(), np.zeros(R, dtype=bool)
    chunk = max(1, RESOLVE_BYTES // (8 * m * m))
    for a in range(0, R, chunk):
        rows = slice(a, a + chunk)
        t, y, p = rows_t[rows], rows_y[rows], rows_p[rows]
        result = solve_algebraic(
            lambda z, t=t, y=y, p=p: checks.H(t, y, z, p),
            lambda z, t=t, y=y, p=p: checks.Hz(t, y, z, p),
            rows_z[rows],
            settings,
        )
        x[rows], converged[rows] = np.where(result.converged[:, None], result.x, rows_z[rows]), result.converged
    return x, converged


class AffineStep:
    """One whole Newton step on determining equations ``H(t, y, z, p) = 0`` affine in z, from a start ``z0``:
    ``z1 = z0 - H_z^-1 H(z0)``, the residual ``H(z1)`` and ``|H_z| |z1|``, as one casadi function of a sample
    (packed ``(t, y, z0, p)``; ``H_z`` by a sparse Householder QR whose pattern casadi analysed once, at its
    making), mapped over :data:`AFFINE_BATCHES` samples.  Made by :func:`affine_step`.  With ``parity`` (that of
    the QR's two permutations, where its reflections are m long), the function gives the sign of ``det H_z`` too,
    read off that QR (:func:`~daemodel.compiling.determinants.householder_sign`), which the branch check reads at
    every output (97 of radau's 1,400 us at rtol 1e-4 on a chain of 20 pendulums,
    207 of 2,700 on 40, where a second evaluation of ``H_z`` and a dense LU of each took them).

    The numpy path's cost was ~1 ms at 21 outputs of a chain of 20 pendulums (the z Jacobians' block split, their
    dense solves, two evaluations of H and one of H_z, each a call per output on casadi, and solve_algebraic's
    bookkeeping), more than half of radau's whole solve at rtol 1e-4.
    """

    def __init__(self, function, n: int, m: int, parity: int | None = None):
        self._functions = {size: function.map(size, "serial") if size > 1 else function for size in AFFINE_BATCHES}
        self._n, self._m, self._parity = n, m, parity
        self._width, self._outputs = function.nnz_in(0), function.nnz_out(0)  # (3 m, and 1 with the QR's sign)
        self.instructions = function.n_instructions()
        self._local = threading.local()  # (each thread's buffers: a call writes its inputs into them)

    def __call__(self, t, Y, Z, P, settings: NewtonTolerances) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(z1, settled, signs)`` for rows ``t`` (R,), ``Y`` (R, n), ``Z`` (R, m), ``P`` (R, k): the step's end,
        where it settled as :func:`~daemodel.compiling.init.solve_algebraic` settles a linear first step (its
        residual within :func:`~daemodel.compiling.init.residual_settled`'s bound, every value finite), and
        ``sign(det H_z)`` (R,) where the QR tells it (NaN where not; None without ``parity``)."""
        n, m, R = self._n, self._m, len(Y)
        packed = np.empty((R, self._width))
        packed[:, 0], packed[:, 1 : 1 + n], packed[:, 1 + n : 1 + n + m], packed[:, 1 + n + m :] = t, Y, Z, P
        out, at = np.empty((R, self._outputs)), 0
        buffers = getattr(self._local, "buffers", None) or self._buffers()
        for size in AFFINE_BATCHES:
            while R - at >= size:
                inputs, outputs, evaluate = buffers[size]
                inputs[:] = packed[at : at + size]
                evaluate()  # (an SX function on the virtual machine: no call that could fail)
                out[at : at + size] = outputs
                at += size
        z1, r1, scaled = out[:, :m], out[:, m : 2 * m], out[:, 2 * m : 3 * m]
        settled = np.isfinite(out[:, : 3 * m]).all(axis=1)
        settled &= residual_settled(r1, 1 + np.abs(z1).max(axis=1), scaled, settings)
        if self._parity is None:
            return z1, settled, None
        return z1, settled, out[:, 3 * m]

    def _buffers(self) -> dict:
        """This thread's ``{size: (inputs (size, width), outputs (size, 3 m [+ 1]), evaluate)}``, the buffers bound to
        the map over ``size`` samples (made at its first call; kept with the casadi buffer that they back)."""
        buffers, width = {}, self._width
        for size, function in self._functions.items():
            inputs, outputs = np.zeros((size, width)), np.zeros((size, self._outputs))
            buffer, evaluate = function.buffer()
            buffer.set_arg(0, memoryview(inputs.reshape(-1)))
            buffer.set_res(0, memoryview(outputs.reshape(-1)))
            buffers[size] = (inputs, outputs, evaluate)
            buffers.setdefault("kept", []).append(buffer)
        self._local.buffers = buffers
        return buffers


def affine_step(compiled) -> AffineStep | None:
    """The :class:`AffineStep` of ``compiled``'s determining equations, made once per model (in the setup:
    :func:`prepare`; where made later, its seconds count as code made at first use,
    :func:`~daemodel.compiling.batch_function.generating_seconds`); None where they are not affine in z
    (:func:`tolerances`), casadi cannot express them, there are :data:`~daemodel.compiling.linear.SPARSE_MIN_SIZE`
    algebraic variables or more, or the step takes more than :data:`AFFINE_MAX_INSTRUCTIONS` instructions."""

    def build() -> AffineStep | None:
        if not resolves_algebraic(compiled) or not tolerances(compiled).linear:
            return None
        if len(compiled.algebraics) >= SPARSE_MIN_SIZE:
            return None
        began = time.perf_counter()
        try:
            return _make_affine_step(compiled)
        finally:
            made_since(began)

    return compiled.cached("algebraic-from-states-affine-step", build)


def _make_affine_step(compiled) -> AffineStep | None:
    import casadi

    from daemodel.compiling.codegen import CasadiConverter

    numeric = compiled.numeric
    determining = [sp.sympify(c.determining) for c in compiled.constraints]
    rows, cols, entries = jacobian_entries(determining, compiled.algebraics, numeric.calculus)
    if not entries:  # (H_z structurally zero: nothing a step could solve)
        return None
    n, m, k = len(numeric.y), len(numeric.z), len(numeric.p)
    packed = casadi.SX.sym("x", 1 + n + m + k)
    convert = CasadiConverter(
        dict(zip((numeric.t, *numeric.y, *numeric.z, *numeric.p), casadi.vertsplit(packed), strict=True))
    )
    try:
        # (one stack: the subexpressions that H_z's entries share with H made once, by its cse)
        both = convert.stack([*determining, *entries])
    except (UnsupportedFunctionError, TypeError):  # (no translation, or a number that is no float: zoo)
        return None
    H, values, z0 = both[:m], both[m:], packed[1 + n : 1 + n + m]
    order = np.lexsort((rows, cols))  # (casadi's nonzeros run column by column)
    Hz = casadi.SX(casadi.Sparsity.triplet(m, m, rows[order].tolist(), cols[order].tolist()), values[order.tolist()])
    V, R, beta, row_order, col_order = casadi.qr_sparse(Hz)
    z1 = z0 + casadi.qr_solve(-H, V, R, beta, row_order, col_order)
    residual = casadi.substitute(H, z0, z1)  # (H itself at z1: the residual the bound reads, affine or not)
    scaled = casadi.mtimes(casadi.fabs(Hz), casadi.fabs(z1))
    outputs = [z1, residual, scaled]
    function = casadi.Function("affine_step", [packed], [casadi.densify(casadi.vertcat(*outputs))])
    if function.n_instructions() > AFFINE_MAX_INSTRUCTIONS:
        return None
    # (det H_z's sign from the QR, where its reflections are m long (casadi adds rows to a structurally singular
    # H_z) and R's diagonal complete; not where it would take the step past the bound: the branch check evaluates)
    if V.size1() == m and casadi.diag(R).nnz() == m:
        parity = (-1) ** (odd_permutation(np.asarray(row_order)) + odd_permutation(np.asarray(col_order)))
        outputs.append(householder_sign(casadi, Hz, beta, casadi.diag(R), parity))
        signed = casadi.Function("affine_step", [packed], [casadi.densify(casadi.vertcat(*outputs))])
        if signed.n_instructions() <= AFFINE_MAX_INSTRUCTIONS:
            return AffineStep(signed, n, m, parity)
    return AffineStep(function, n, m)


def prepare(compiled, numpy: bool = True) -> None:
    """Make the functions :func:`algebraic_from_states` evaluates for ``compiled`` (whether its determining equations
    are affine in z, their affine step, and their numpy code), where it has algebraic variables of index 2 or more:
    code generation, done in the setup, before any method's clock.  ``numpy=False``: their numpy code only where
    there is no affine step (with one, the numpy path solves only the outputs where it does not settle, usually
    none, and a few of them on casadi: ~70 ms of printing for each piece between events, made for nothing)."""
    if not resolves_algebraic(compiled):
        return
    tolerances(compiled)
    # (H_z's nonzeros are the branch check's, made with it)
    if affine_step(compiled) is None or numpy:
        constraint_checks(compiled).H.numpy()


def tolerances(compiled) -> NewtonTolerances:
    """The Newton tolerances of :func:`algebraic_from_states` for ``compiled`` (linear ones settle in a
    step: determining equations whose z Jacobian is free of z), made once per model."""

    def build() -> NewtonTolerances:
        determining = [c.determining for c in compiled.constraints]
        _, _, entries = jacobian_entries(determining, compiled.algebraics, compiled.numeric.calculus)
        linear = not any(e.has(*compiled.algebraics) for e in entries)
        return NewtonTolerances(max_iterations=RESOLVE_MAX_ITERATIONS, linear=linear)

    return compiled.cached("algebraic-from-states-tolerances", build)
