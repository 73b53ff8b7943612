"""The embedded local error estimate of a Radau IIA step (order s), as RADAU5 computes it.

With ``gamma0`` the real eigenvalue of A (s odd) and ``bhat`` of order s including the start point
(:func:`~.transform.embedded_weights`; Hairer & Wanner, Solving ODEs II, IV.8, generalised to s
stages),

    (M - h gamma0 J) err = [gamma0 h f(y_n) + h sum_i (bhat_i - b_i) f(Y_i) ; 0]

where ``M = diag(I, 0)``.  As in RADAU5, the error of an algebraic variable determined through an
index-k constraint is multiplied by ``h^(k-1)`` before the norm (its stage values are only accurate
to order s - k + 2); so adaptive steps return them solved from the states at the outputs (:mod:`.outputs`).
A batch shares the step sequence (the worst sample decides).

The adaptive controller reads :meth:`ErrorEstimate.norm`; the fixed grid checks every step with
:meth:`ErrorEstimate.check_fixed`, in units of the solution's size ``1 + max |u|`` so far: Newton
converges on a step across a singularity as readily as on a good one, and only the estimate
tells them apart.  What a fixed step's estimate is in those units (the stiff filter once more where
it is beyond a bound, and only where the flow damps what that filter damps) is :func:`fixed_step_units`,
the one function that radau's fixed grid and the PINN's certificate (:mod:`daemodel.backends.pinn.certificate`,
radau's estimate on the PINN's steps) both judge by.
"""

from __future__ import annotations

import math

import numpy as np
from daemodel.backends.base import LOCAL_ERROR_BOUND, estimate_status
from daemodel.backends.radau import formulas

from daemodel.errors import LocalErrorBoundError

# The refiltered estimate of a fixed step judges it only where the flow damps what the filter damps
# (:func:`flow_damps`), read on at most this many Ritz values of the filter (Arnoldi's solves, made only
# where the unfiltered estimate is beyond a bound): an oscillator beside a stiff mode (3 states) read on 2
# passed an oscillator damped to 1e-66 at h = 1e7 as "success"
FILTER_KRYLOV = 8
# ... and a mode may be damped by the filter up to this many times more than by the flow: a slow mode's
# |h lambda| < 5, oscillating or not, barely filtered (1 / |1 - gamma0 h lambda|, 1.7 at h omega = 5), beside a
# stiff mode's transient (in one sample, or in a batch) must not block the filter; h omega = 1e7's is 2.7e6
FILTER_EXCESS = 2.0
# Arnoldi stops where the next vector is below this share of the column's largest entry (an invariant space)
KRYLOV_BREAKDOWN = 1e-10
# A Ritz value below this share of the row's largest is the rounding of a direction the filter annihilates
# (a constraint's normal in an index-2 system: the squeezer's read 7e-17 to 6e-13, of either sign, and a sign
# below zero read as a growing mode, h lambda = +5e16, that radau's and the certificate's steps told apart at
# random); an oscillation's at h omega = 1e7 is 3.6e-7, at 1e12 3.6e-12: of the largest, not of 1 (a floor of 1
# read a lone oscillator's pair at h omega >= 1e12 as zero, damped, and its true error 0.49 came back "success")
RITZ_ROUNDING = 1e-11
# ... and every Ritz value is known to within this share of the largest (eigvals of the Hessenberg matrix)
RITZ_PRECISION = 1e-14


class ErrorEstimate:
    """The local error estimate of the steps of one :class:`~.step.Stepper`."""

    def __init__(self, stepper, e):
        self.stepper = stepper
        self.e = stepper.engine.asarray(e)  # bhat - b, (s,)
        self.gamma0 = stepper.engine.transform.gamma0
        self.scale = None  # fixed grid: 1 + max |u| over the steps' start values so far, (B, n+m)
        self.per_step = []  # fixed grid: each step's largest estimate in units of scale (z unweighted)
        self.worst = None  # fixed grid: (estimate, step, t, h, estimates (B, n+m)) of the largest so far

    def local(self, h, factors, f0, stage_f):
        """The embedded local error estimate of the step, shape (B, n+m).

        ``factors`` hold ``(1 / (h gamma0)) M - J``, ``f0`` (B, n) is ``f`` at the step's start,
        ``stage_f`` (B, s, n) at its stages.  Returns the estimate and what :meth:`refiltered` needs.
        """
        stepper = self.stepper
        xp = stepper.xp
        quadrature = xp.einsum("i,bin->bn", self.e, stage_f)  # sum_i (bhat_i - b_i) f(Y_i), (B, n)
        # (M - h gamma0 J) err = [h (quadrature + gamma0 f0); 0] divided row-wise by diag(h gamma0, -1).
        # The constraint rows carry no local error: each step's Newton enforces g at its stages,
        # and its leftover |g(y_n)| (Newton's tolerance) must not block ever smaller steps.
        # (the zeros go with the right-hand side, made again by a refiltered estimate: 0.4 MB of a cold solve's peak
        # at 10^5 unknowns, the error's norm)
        rhs = formulas.error_rhs(stepper.ops, quadrature, self.gamma0, f0, xp.zeros_like(stepper.z))
        return stepper.engine.error_solve(factors, rhs), (factors, quadrature)

    def refiltered(self, t, err, matrices):
        """The estimate with the stiff filter applied once more (Hairer-Wanner's first or rejected step)."""
        stepper = self.stepper
        (factors, quadrature), zeros = matrices, stepper.xp.zeros_like(stepper.z)
        n = stepper.n
        f1 = stepper.engine.f(t, stepper.y + err[:, :n], stepper.z + err[:, n:])
        return stepper.engine.error_solve(factors, formulas.error_rhs(stepper.ops, quadrature, self.gamma0, f1, zeros))

    def norm(self, t, h, r, W, first) -> float:
        """RADAU5's scaled local error of the step, worst sample (the adaptive controller's)."""
        stepper = self.stepper
        xp = stepper.xp
        err, matrices = self.local(h, stepper.factors, stepper.start_f(t), r.stage_f)
        u_new = W[:, -1]
        size = stepper.magnitude()
        w = stepper.weights(h, xp.maximum(size, xp.abs(u_new), out=size), overwrite=True)
        norm = formulas.error_norm(stepper.ops, err, w, first, lambda: self.refiltered(t, err, matrices))
        return formulas.finite_or_inf(formulas.SCALAR, float(norm.max()))  # (max: NaN where any is)

    def check_fixed(self, step, t, h, r):
        """Fixed step: the step's local error estimate in units of the solution's size; raise beyond the bound.

        The unit is ``1 + max |u|`` over the steps' start values so far (an algebraic variable of
        index k: that over ``h^(k-1)``), so a step across a singularity cannot excuse its error by
        its own huge result, nor an oscillation be judged where it crosses zero.  It reuses the
        factored Newton matrix of the step's Jacobian and takes ``f`` at the step's start from the
        last step's final stage (Radau IIA is stiffly accurate: ``c_s = 1``).
        """
        stepper = self.stepper
        xp, stats, engine = stepper.xp, stepper.stats, stepper.engine
        u = xp.abs(stepper.state()) + 1.0
        self.scale = u if self.scale is None else xp.maximum(self.scale, u)
        err, matrices = self.local(h, stepper.factors, stepper.start_f(t), r.stage_f)
        index_weight = numpy_copy(stepper.index_weights(h))
        raw = fixed_step_units(
            numpy_copy(err),
            numpy_copy(self.scale),
            index_weight,
            stepper.options.estimate_bound,
            lambda: numpy_copy(self.refiltered(t, err, matrices)),
            lambda rhs: numpy_copy(engine.error_solve(matrices[0], engine.asarray(rhs))),
            h * self.gamma0,
            self.gamma0,
            stepper.n,
            np.concatenate([np.zeros(stepper.n, dtype=bool), stepper.z_index >= 2]),
        )
        ratio = raw * index_weight
        worst = float(ratio.max())
        if worst <= LOCAL_ERROR_BOUND:  # the usual case: False for NaN too
            stats["max_local_error_estimate"] = max(stats["max_local_error_estimate"], worst)
            # estimate_bound reads the estimate in each variable's own units (an index-2 z's is not
            # weighted by h: the slider-crank's multipliers at h = 0.02 are 5e-3 off where the weighted
            # estimate said 5e-4)
            largest = float(raw.max())
            self.per_step.append(largest)
            if self.worst is None or largest > self.worst[0]:
                self.worst = (largest, step, t, h, raw)
            return
        stats["max_local_error_estimate"] = math.inf if math.isnan(worst) else worst
        ratio = np.nan_to_num(ratio, nan=math.inf)
        D = stepper.n + stepper.m
        sample, k = divmod(int(np.argmax(ratio.reshape(-1))), D)
        compiled = stepper.compiled
        name = (*compiled.state_names, *compiled.algebraic_names)[k]
        index = int(stepper.z_index[k - stepper.n]) if k >= stepper.n else 1
        size = f"1 + max|{name}|" if index == 1 else f"(1 + max|{name}|) / h^{index - 1}"
        value = float(ratio.reshape(-1)[sample * D + k])
        raise LocalErrorBoundError(
            f"radau: step {step} from t = {t:.6g} with h = {h:.3g}: the local error estimate of '{name}' "
            f"(sample {sample}) is {value:.3g} times the solution's size {size} so far, beyond "
            f"LOCAL_ERROR_BOUND = {LOCAL_ERROR_BOUND:g}: the step has no correct digit (the solution may be "
            "singular, switch or change too fast there); take a smaller h, or the adaptive mode (rtol=...)"
        )

    def status(self, method: str, bound: float) -> str:
        """The fixed grid's status: "success", or flagged at its worst step beyond ``bound`` (see
        :func:`~daemodel.backends.base.estimate_status`)."""
        if self.worst is None:
            return "success"
        worst, step, t, h, ratio = self.worst
        stepper = self.stepper
        sample, k = divmod(int(np.argmax(ratio.reshape(-1))), stepper.n + stepper.m)
        name = (*stepper.compiled.state_names, *stepper.compiled.algebraic_names)[k]
        where = f"step {step} from t = {t:.6g} (h = {h:.3g}), in '{name}'"
        where += f", sample {sample}" if stepper.B > 1 else ""
        return estimate_status(method, worst, bound, where)


def fixed_step_units(err, scale, weight, estimate_bound, refilter, solve, hg, gamma0, n, high_index) -> np.ndarray:
    """A fixed step's local error estimate in units of the solution's size, shape (R, D): what radau's fixed
    grid (:meth:`ErrorEstimate.check_fixed`) and the PINN's certificate (its copy of radau's estimate on the
    PINN's steps, :func:`daemodel.backends.pinn.certificate.certify`) both judge, row by row (a sample, or a
    segment of a sample), so that the PINN is never "success" where radau at the same h is not.

    ``|err| / scale``; in a row whose estimate is beyond a bound (weighted by ``weight``, ``h^(k-1)`` of an
    index-k algebraic variable, beyond :data:`LOCAL_ERROR_BOUND`, or unweighted beyond ``estimate_bound``),
    the refiltered one ``|refilter()| / scale`` (the stiff filter once more, Hairer-Wanner: unfiltered, a stiff
    mode's transient flagged y' = -1e6 (y - cos t) at h = 0.01 from y0 = 0.95 at 2.6e-2, 1.5e-5 off) where it
    is finite (f at y + err may leave f's domain: the first is kept then), and lower than the first only where
    the flow damps what the filter damps (:func:`flow_damps`: an oscillator at h omega = 1e7 read 1e-7
    refiltered, and was damped to 1e-66), and never in an algebraic variable of index 2 or more
    (``high_index``): the filter damps a stiff mode of the states, and such a variable is none (it follows
    the states' derivative, not their values); the squeezer at h = 0.00075 read 1.5e-4 to 8.6e-4 refiltered
    in its accelerations and multipliers where their true local errors were 2e-3 to 0.5 of their size,
    and the unfiltered estimates 1e-3 to 0.12.

    Parameters
    ----------
    err : ndarray, shape (R, D)
        The embedded estimate, unscaled, states then algebraic variables.
    scale : ndarray, shape (R, D)
        ``1 + max |u|`` over the step starts so far.
    weight : ndarray, broadcastable to (R, D)
    estimate_bound : float
    refilter : callable () -> ndarray (R, D)
        The refiltered estimate, unscaled; called only where a row is beyond a bound.
    solve : callable, ndarray (R, D) -> ndarray (R, D)
        ``((1 / (h gamma0)) M - J)^-1`` applied to each row (the estimate's factored matrix).
    hg : float or ndarray (R,)
        Each row's ``h gamma0``.
    gamma0 : float
    n : int
        The number of states.
    high_index : ndarray of bool, shape (D,)
        The algebraic variables of index 2 or more.
    """
    first = np.nan_to_num(np.abs(err) / scale, nan=np.inf)  # (NaN: no digit, never within a bound)
    judged = ((first * weight).max(axis=1) > LOCAL_ERROR_BOUND) | (first.max(axis=1) > estimate_bound)
    if not judged.any():  # the usual case: no solve, no f
        return first
    filtered = np.abs(refilter()) / scale
    again = judged & np.isfinite(filtered).all(axis=1)
    if not again.any():
        return first
    q = np.where(again[:, None], err[:, :n] / scale[:, :n], 0.0)  # (no Ritz value where not refiltered)
    hg = np.broadcast_to(np.asarray(hg, dtype=float), (len(err),))
    damps = flow_damps(q, scale[:, :n], solve, hg, gamma0, err.shape[1])
    lowered = np.where(damps[:, None] & ~high_index, filtered, np.maximum(first, filtered))
    return np.where(again[:, None], lowered, first)


def flow_damps(q, unit, solve, hg, gamma0, width) -> np.ndarray:
    """Whether, in each row (bool (R,)), the exact flow damps the states' estimate ``q`` (R, n), in units of
    ``unit`` (R, n), over the step about as much as the stiff filter ``F = (M - h gamma0 J)^-1 M`` does,
    so that the refiltered estimate may judge the step.

    The filter damps every mode of ``|h lambda| >> 1`` by ``|mu| = 1 / |1 - gamma0 h lambda|``, the flow by
    ``exp(Re h lambda)``: a decaying mode (y' = -1e6 (y - cos t) at h = 0.01) is damped by both, an oscillator
    (x' = v, v' = -x at h = 1e7) by the filter alone.  The modes that ``q`` excites are read off the Ritz
    values ``mu`` of F on the Krylov space of ``q`` (:func:`krylov_ritz_values`: up to :data:`FILTER_KRYLOV`
    solves with the factored matrix, ``solve``, O(n) each beyond the factors, no n x n matrix; on an
    invariant space, as one decaying mode's or one oscillation's, they are its eigenvalues, whatever the
    scaling): each gives ``h lambda = (1 - 1 / mu) / gamma0``, and none may be damped by the filter more than
    :data:`FILTER_EXCESS` times the flow (:func:`ritz_values_damp`).  A row with ``q = 0`` has no Ritz value
    and passes.  ``solve`` takes (R, ``width``) right-hand sides, the states' and the algebraic rows."""
    R, n = q.shape
    if not n:
        return np.ones(R, dtype=bool)

    def F(v):  # the filter on the states' part, in the estimate's units: (M - hg J)^-1 M v = ((1/hg) M - J)^-1 M v / hg
        x = solve(np.concatenate([v * unit / hg[:, None], np.zeros((R, width - n))], axis=1))
        return x[:, :n] / unit

    ritz = krylov_ritz_values(F, q)
    return np.array([ritz_values_damp(mu, gamma0) for mu in ritz], dtype=bool)


def krylov_ritz_values(F, q, dimension=None) -> list:
    """Each row's Ritz values of the linear map ``F`` ((R, n) to (R, n), rows apart) on the Krylov space of
    ``q`` (R, n), by Arnoldi (Gram-Schmidt twice) up to ``dimension`` (default :data:`FILTER_KRYLOV`) vectors,
    or fewer where the space is invariant: a list of R arrays of complex values (none where q is 0; NaN where
    q or F's values are not finite, judged as not damped)."""
    R, n = q.shape
    k = min(n, dimension or FILTER_KRYLOV)
    bad = ~np.isfinite(q).all(axis=1)  # (each row apart: a batch's other samples are judged on their own)
    q = np.where(bad[:, None], 0.0, q)
    norms = np.linalg.norm(q, axis=1)
    V = np.zeros((R, k + 1, n))
    H = np.zeros((R, k + 1, k))
    V[:, 0] = q / np.where(norms > 0, norms, 1.0)[:, None]
    size = np.where(norms > 0, 0, -1)  # each row's dimension so far (-1: q = 0, no Ritz value)
    live = norms > 0
    for j in range(k):
        if not live.any():
            break
        w = F(V[:, j])
        for _ in range(2):
            for i in range(j + 1):
                c = np.einsum("rn,rn->r", V[:, i], w)
                H[:, i, j] += np.where(live, c, 0.0)
                w = w - c[:, None] * V[:, i]
        beta = np.linalg.norm(w, axis=1)
        size = np.where(live, j + 1, size)
        scale = np.abs(H[:, : j + 1, j]).max(axis=1)
        live = live & np.isfinite(beta) & (beta > KRYLOV_BREAKDOWN * scale)
        H[:, j + 1, j] = np.where(live, beta, 0.0)
        V[:, j + 1] = np.where(live[:, None], w / np.where(beta > 0, beta, 1.0)[:, None], 0.0)
    out = []
    for r in range(R):
        m = max(int(size[r]), 0)
        block = H[r, :m, :m]
        if bad[r] or not np.isfinite(block).all():
            out.append(np.array([np.nan + 0j]))  # (F left the finite numbers: judged as not damped)
        else:
            out.append(np.linalg.eigvals(block) if m else np.array([], complex))
    return out


def ritz_values_damp(mus, gamma0) -> bool:
    """Whether for every Ritz value ``mu`` of the filter (:func:`krylov_ritz_values`) the flow damps its mode
    about as much as the filter: ``Re h lambda <= log |mu| + log FILTER_EXCESS`` with ``h lambda = (1 - 1 / mu)
    / gamma0`` (see :func:`flow_damps`); False for a value that is not finite.  A value within
    :data:`RITZ_ROUNDING` times the largest is zero: damped to nothing, ``h lambda -> -inf`` along it."""
    mus = np.asarray(mus, dtype=complex)
    if not np.isfinite(mus).all():
        return False
    largest = float(np.abs(mus).max(initial=0.0))
    zero = RITZ_ROUNDING * largest  # (of the largest: no floor of 1, see RITZ_ROUNDING)
    for mu in mus:
        if abs(mu) <= zero and abs(mu.imag) <= abs(mu.real):  # (an oscillation's is imaginary: judged)
            continue
        # Re h lambda to within the Ritz value's rounding (RITZ_PRECISION of the largest), read at its largest:
        # 1 / mu moves by that over |mu|^2 (an oscillation's at h omega = 1e12 beside a slow mode, 0.78, read
        # Re h lambda from -2e6 to +2e6 by the sign of its real part's rounding, 1e-17 where 1.3e-23 is true)
        blur = RITZ_PRECISION * largest / (gamma0 * abs(mu) ** 2)
        if ((1 - 1 / mu) / gamma0).real + blur > np.log(abs(mu) * FILTER_EXCESS):
            return False
    return True


def numpy_copy(values) -> np.ndarray:
    """A float64 numpy copy of an engine's array."""
    if isinstance(values, np.ndarray):
        return values.astype(float, copy=False)
    return values.detach().cpu().double().numpy()
