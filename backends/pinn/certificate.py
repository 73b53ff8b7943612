"""The Radau-PINN's certificate: how far its answer is from the Radau IIA solution at the same
stages and h, set beside Radau's own error.

The PINN minimises the Radau stage residual, so its ceiling is the classical Radau solution,
and its distance from that solution is one Newton correction away.  For every segment k and
sample b, the segment's networks predict the stages and end values of one step from their own
start ``(y_k, z_k)`` (the chained prediction).  Full Newton on the same stage equations
(:func:`daemodel.collocation.collocation_step`), started from the networks' stages, gives the
Radau step from that start; the difference of the end values is the networks' local distance
``d_k``.  Where Newton converges this is the distance itself, not an estimate.

Radau's own local error at that step, ``le_k``, is estimated by the (s+1)-stage step from the
same start (order 2s+1 against 2s-1: their difference is the leading term of the s-stage
step's local error; far sharper than the embedded estimate of order s that radau's step
control uses).

Both are carried along the grid by the step map's sensitivity ``Phi_k = d(y, z)_{k+1} / dy_k``
(the stage equations' Jacobian solved against ``dF/dy_n = -I``), with their signs::

    D_{k+1} = Phi_k D_k + d_k,      E_{k+1} = Phi_k E_k + le_k      (D_0 = E_0 = 0)

Signs matter: for an index-2 system Radau's local errors normal to the constraint manifold are
O(h^(s+1)), far above its global error O(h^(2s-1)), and the next step's projection removes them;
carried in absolute values they overestimated Hessenberg's error 70x (y) and 3000x (z), carried
with signs they give it to 0.1 % (2.4279e-8 against 2.4279e-8 at h = 0.05).  ``|D|`` is a
first-order estimate of the PINN's distance from Radau's solution; the certificate reports
:data:`CERTIFICATE_SAFETY` times it as the distance.  The PINN is *certified* when that distance
is within Radau's own error ``|E|`` (its largest value so far along the grid, so that an error
crossing zero does not demand the impossible), or below :data:`CERTIFICATE_FLOOR`, at every grid
time, variable and sample: its error against the exact solution is then at most about twice
Radau's at the same h.  A step whose Newton check fails, or whose estimated Radau error has no
correct digit (beyond ``LOCAL_ERROR_BOUND`` of the variable's size, where radau itself refuses the
step: a spurious collocation root, e.g. stages on two branches of a constraint), is not certified.
Nothing here uses a classical solution of the whole trajectory: every Newton solve starts from the
networks' own start values.

The certificate proves closeness to radau, not accuracy.  So that the PINN's status is never better
than radau's at the same h and stages, every step also carries radau's own fixed-step error estimate
(:func:`embedded_estimate`: the embedded estimate of order s of :mod:`daemodel.backends.radau.error`,
at the Radau step's stages from the networks' start, judged by radau's own function for it,
:func:`~daemodel.backends.radau.error.fixed_step_units`: the stiff filter once more and where it may lower
the estimate), in radau's units (``1 + max|u|`` over the step
starts so far, an index-k algebraic variable's weighted by ``h^(k-1)``): the backend raises
:class:`~daemodel.errors.LocalErrorBoundError` where radau would, and flags where radau would flag.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from daemodel.backends.base import DEFAULT_ESTIMATE_BOUND, LOCAL_ERROR_BOUND
from daemodel.backends.pinn.segments import segment_steps

from daemodel.collocation import collocation_step, lagrange_matrix
from daemodel.tableau import radau_iia

# Full Newton iterations the certificate spends per step (from the networks' stages, converged
# ones take 1-3); a step that needs more is reported uncertified.
CERTIFICATE_NEWTON_ITERATIONS = 10
# Newton's tolerance on increments relative to 1 + |value|: radau's fixed step (10 eps).
CERTIFICATE_NEWTON_TOL = 10 * float(np.finfo(np.float64).eps)
# Distances below this, relative to 1 + max|value| of the variable, are the rounding of the
# collocation solution itself (radau's Newton stops at 10 eps; 20 steps and the propagation
# add to it): a PINN within it cannot be told from radau.
CERTIFICATE_FLOOR = 100 * float(np.finfo(np.float64).eps)
# The reported distance is this multiple of the first-order estimate |D|.  Measured on trained
# PINNs (Hessenberg at h = 0.05 and 0.1, per variable): the true distance from radau was 0.96-1.04
# times |D|.
CERTIFICATE_SAFETY = 2.0
# Entries of the stage Jacobians held at once: segment-steps are certified in chunks of
# CERTIFICATE_ENTRIES / ((s+1) D)^2 rows (2^25 doubles: 256 MB, a few copies of it in the LU).
CERTIFICATE_ENTRIES = 2**25
# Why a sample is not certified, besides a distance beyond Radau's error.
NEWTON_FAILED, ESTIMATE_FAILED, NO_DIGIT = "newton", "estimate", "digit"


@dataclass(frozen=True)
class Certificate:
    """The certificate of a PINN answer on its grid (B samples, T = segments + 1 times, D = n + m
    variables, states then algebraics).

    Attributes
    ----------
    distance : ndarray, shape (B, T, D)
        The certified distance |PINN - Radau| at the grid times: :data:`CERTIFICATE_SAFETY` times
        the first-order estimate (0 at t0; inf after a step whose Newton check failed).
    radau_error : ndarray, shape (B, T, D)
        Estimate of |Radau - exact| at the grid times, propagated the same way.
    local_distance, local_radau_error : ndarray, shape (B, T - 1, D)
        The same per step, from the networks' own start values.
    floor : ndarray, shape (B, D)
        :data:`CERTIFICATE_FLOOR` times ``1 + max|value|`` of each variable of each sample.
    rounding : ndarray, shape (B, T, D)
        Where Newton's increments stagnated above its tolerance (ill-conditioned stage
        equations), the largest last increment so far, times :data:`CERTIFICATE_SAFETY`: the
        resolution of the Radau step it computed, added to ``floor``.
    failed : ndarray of str, shape (B, T - 1)
        Per step: "" where both Newton solves converged and Radau's error estimate has a correct
        digit, :data:`NEWTON_FAILED` where Newton from the networks' stages did not converge,
        :data:`ESTIMATE_FAILED` where it did but the (s+1)-stage step that estimates Radau's own
        error did not (no error to certify against), :data:`NO_DIGIT` where the estimated local error of
        Radau's step is beyond ``LOCAL_ERROR_BOUND`` of the variable's size (index-weighted as
        radau's fixed step weighs it: radau refuses such a step).
    certified : ndarray of bool, shape (B,)
    estimate : ndarray, shape (B, T - 1, D), optional
        Radau's own fixed-step local error estimate of each step (:func:`embedded_estimate`), in
        units of ``1 + max|u|`` over the step starts so far, as radau's fixed step measures it
        (:meth:`daemodel.backends.radau.error.ErrorEstimate.check_fixed`); NaN where the Newton
        check failed.  None with ``radau_error=False``.
    index_weight : ndarray, shape (T - 1, D), optional
        ``h^(k-1)`` of each step for an index-k algebraic variable (1 for the states): ``estimate``
        times it is what :data:`LOCAL_ERROR_BOUND` bounds.
    """

    distance: np.ndarray
    radau_error: np.ndarray
    local_distance: np.ndarray
    local_radau_error: np.ndarray
    floor: np.ndarray
    rounding: np.ndarray
    failed: np.ndarray
    certified: np.ndarray
    estimate: np.ndarray | None = None
    index_weight: np.ndarray | None = None

    def bound(self) -> np.ndarray:
        """What the distance is compared with, shape (B, T, D): Radau's error so far (its running
        maximum over the grid: an error that crosses zero does not demand the impossible there;
        so the PINN's largest error over the grid is at most about twice Radau's largest), or the
        resolution (floor and Newton's rounding), whichever is larger."""
        return np.maximum(np.maximum.accumulate(self.radau_error, axis=1), self.floor[:, None, :] + self.rounding)

    def ratio(self) -> np.ndarray:
        """``distance / bound``, shape (B, T, D): certified where every entry <= 1."""
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = self.distance / self.bound()
        return np.where(np.isnan(ratio), np.inf, ratio)

    def worst(self) -> tuple[int, int, int, float]:
        """``(sample, grid index, variable, ratio)`` of the largest :meth:`ratio` among the samples
        that are not certified (all samples when every one is)."""
        ratio = self.ratio()
        if not self.certified.all():
            ratio = np.where(self.certified[:, None, None], -np.inf, ratio)
        b, t, j = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
        return int(b), int(t), int(j), float(ratio[b, t, j])

    def failure(self) -> str:
        """Why the first uncertified sample's first failed step is not certified
        (:data:`NEWTON_FAILED`, :data:`ESTIMATE_FAILED`, :data:`NO_DIGIT`), or "" where no step
        failed (a distance beyond Radau's error, or every sample certified)."""
        for b in np.flatnonzero(~self.certified):
            for kind in self.failed[b]:
                if kind:
                    return str(kind)
        return ""

    def _worst_pair(self) -> dict:
        """The distance and its bound where their ratio is largest (the two numbers a verdict
        compares; the per-variable maxima may come from different variables and times)."""
        b, t, j, ratio = self.worst()
        return {"distance": float(self.distance[b, t, j]), "bound": float(self.bound()[b, t, j]), "ratio": ratio}

    def weighted_estimate(self) -> np.ndarray:
        """``estimate`` times ``index_weight``, shape (B, T - 1, D): what radau's fixed step bounds by
        :data:`LOCAL_ERROR_BOUND`."""
        return self.estimate * self.index_weight[None]

    def beyond_bound(self) -> tuple[int, int, int, float] | None:
        """``(sample, step, variable, weighted estimate)`` at the first step (0-based) where radau's own
        estimate is beyond :data:`LOCAL_ERROR_BOUND` for some sample (the variable and sample where it
        is largest there), i.e. where radau at the same h and stages raises
        :class:`~daemodel.errors.LocalErrorBoundError`; None where no step is (or no estimate was made).
        Steps whose Newton check failed (NaN) are judged by the certificate, not here."""
        if self.estimate is None:
            return None
        weighted = np.nan_to_num(self.weighted_estimate(), nan=0.0)
        beyond = weighted > LOCAL_ERROR_BOUND
        if not beyond.any():
            return None
        step = int(np.argmax(beyond.any(axis=(0, 2))))
        sample, j = np.unravel_index(int(np.argmax(weighted[:, step])), weighted[:, step].shape)
        return int(sample), step, int(j), float(weighted[sample, step, j])

    def largest_estimate(self) -> tuple[int, int, int, float] | None:
        """``(sample, step, variable, estimate)`` where radau's own estimate (unweighted, in units of
        ``1 + max|u|``) is largest: what radau's fixed step compares with ``estimate_bound``; None
        where no estimate was made or none is finite."""
        if self.estimate is None or not np.isfinite(self.estimate).any():
            return None
        estimate = np.where(np.isfinite(self.estimate), self.estimate, -np.inf)
        b, k, j = np.unravel_index(int(np.argmax(estimate)), estimate.shape)
        return int(b), int(k), int(j), float(estimate[b, k, j])

    def summary(self, names) -> dict:
        """Digest for ``Solution.stats``, as numpy arrays (a batch of 10^3 samples would make lists of
        lists that print as megabytes): which samples are certified (B,); per variable,
        the largest distance and Radau error over the grid (per sample); per segment and sample,
        at the segment's end, the largest distance and Radau error over the variables
        (``segment_distance``, ``segment_radau_error``, each (B, segments)) and the same from
        the segment's own start (``local_distance``, ``local_radau_error``); per variable, the largest
        resolution (``max_resolution``: :attr:`floor` plus Newton's :attr:`rounding`, below which a distance is
        not resolved)."""
        resolution = self.floor[:, None, :] + self.rounding
        return {
            "certified": np.asarray(self.certified, dtype=bool),
            "max_distance": {name: self.distance[..., j].max(axis=1) for j, name in enumerate(names)},
            "max_radau_error": {name: self.radau_error[..., j].max(axis=1) for j, name in enumerate(names)},
            # what a distance is resolved to (the collocation solution's rounding and Newton's last increment):
            # a true distance up to it is not one the certificate can tell from radau's
            "max_resolution": {name: resolution[..., j].max(axis=1) for j, name in enumerate(names)},
            "max_ratio": float(self.ratio().max()),
            "worst": self._worst_pair(),
            "failure": self.failure(),
            "segment_distance": self.distance[:, 1:].max(axis=2),
            "segment_radau_error": self.radau_error[:, 1:].max(axis=2),
            "local_distance": (CERTIFICATE_SAFETY * self.local_distance).max(axis=2),
            "local_radau_error": self.local_radau_error.max(axis=2),
            # radau's own fixed-step estimate on the same steps: its largest, unweighted and weighted
            "max_local_error_estimate": None if (worst := self.largest_estimate()) is None else worst[3],
            "max_weighted_local_error_estimate": (
                None if self.estimate is None else float(np.nan_to_num(self.weighted_estimate(), nan=0.0).max())
            ),
        }


def certify(
    compiled,
    config,
    grid,
    networks,
    input_columns,
    values,
    p,
    radau_error: bool = True,
    newton_tol=None,
    predictions=None,
    estimate_bound: float = DEFAULT_ESTIMATE_BOUND,
) -> Certificate:
    """Certify the values ``values`` (B, T, n+m) that ``networks`` (one per segment of ``grid``)
    chained from their start, for the parameters ``p`` (B, k), of which the columns
    ``input_columns`` are network inputs after the states.

    With ``radau_error=False`` only the distance from the Radau solution is computed (what
    ``Surrogate.solve(tol=)`` compares with tol): the (s+1)-stage steps are skipped, Radau's error
    is reported as 0, and no sample is ``certified`` (there is no Radau error to certify against);
    ``failed`` still marks the steps whose Newton check failed.  ``newton_tol`` (default
    :data:`CERTIFICATE_NEWTON_TOL`) is the Newton check's tolerance on increments relative to
    ``1 + |value|``: distances are resolved to about it.  ``predictions``: the networks' stage
    and end values along ``values`` where the caller has them (``Surrogate.rollout(stages=True)``).
    ``estimate_bound``: radau's option of that name, beyond which radau's fixed step applies the stiff
    filter once more before judging its estimate (as :attr:`Certificate.estimate` does)."""
    newton_tol = CERTIFICATE_NEWTON_TOL if newton_tol is None else newton_tol
    device, s = config.device, config.stages
    n, m = len(compiled.states), len(compiled.algebraics)
    B, S, D = values.shape[0], len(grid) - 1, n + m
    as_tensor = lambda a: torch.as_tensor(np.array(a, dtype=float), dtype=torch.float64, device=device)  # noqa: E731
    if predictions is None:
        predictions = _predictions(compiled, config, grid, networks, input_columns, values, p)
    Y, Z, y_end, z_end = (a.reshape(S * B, *a.shape[2:]) for a in predictions)
    start = as_tensor(values[:, :-1]).transpose(0, 1).reshape(S * B, D)  # row k B + b: segment k of sample b
    steps = np.repeat(np.array(segment_steps(grid)), B, axis=0)  # (S B, 2): t, h of each row
    rows_p = as_tensor(np.tile(np.asarray(p, dtype=float), (S, 1)))
    # radau's units for its own estimate: 1 + max|u| over the step starts so far (each sample's), and an index-k
    # algebraic variable's estimate weighted by h^(k-1) (what LOCAL_ERROR_BOUND bounds), per row
    scale = np.maximum.accumulate(1.0 + np.abs(values[:, :-1]), axis=1).transpose(1, 0, 2).reshape(S * B, D)
    h = np.array([step for _, step in segment_steps(grid)])
    weight = np.concatenate([np.ones((S, n)), h[:, None] ** (np.asarray(compiled.algebraic_index, float) - 1)], axis=1)
    high_index = np.concatenate([np.zeros(n, dtype=bool), np.asarray(compiled.algebraic_index) >= 2])
    chunk = max(1, CERTIFICATE_ENTRIES // ((s + 1) * D) ** 2)
    parts = []
    for first in range(0, S * B, chunk):
        rows = slice(first, min(S * B, first + chunk))
        parts.append(
            _steps(
                compiled,
                s,
                as_tensor(steps[rows]),
                start[rows],
                Y[rows],
                Z[rows],
                rows_p[rows],
                n,
                device,
                radau_error,
                newton_tol,
                (scale[rows], np.repeat(weight, B, axis=0)[rows], estimate_bound, high_index),
            )
        )
    radau_end, local_e, converged, estimated, rounding, sensitivity, units = (
        torch.cat([part[i] for part in parts]) for i in range(7)
    )
    pinn_end = torch.cat([y_end, z_end], dim=-1)
    inf = torch.tensor(float("inf"), dtype=torch.float64, device=device)
    local_d = torch.where(converged[:, None], pinn_end - radau_end, inf)
    local_e = torch.where((converged & estimated)[:, None], local_e, inf)

    def per_step(a):  # rows (S B, ...) -> (S, B, ...)
        return a.reshape(S, B, *a.shape[1:])

    local_d, local_e, rounding, sensitivity, converged, estimated, units = map(
        per_step, (local_d, local_e, rounding, sensitivity, converged, estimated, units)
    )
    distance = [torch.zeros(B, D, dtype=torch.float64, device=device)]
    error = [torch.zeros(B, D, dtype=torch.float64, device=device)]
    for k in range(S):  # signed, through each step's sensitivity to its start
        distance.append(torch.einsum("bij,bj->bi", sensitivity[k], distance[-1][:, :n]) + local_d[k])
        error.append(torch.einsum("bij,bj->bi", sensitivity[k], error[-1][:, :n]) + local_e[k])
    # after a failed step (inf) a product with a zero sensitivity is NaN: unknown, so inf
    distance = _unknown_is_inf(torch.stack(distance, dim=1).abs().cpu().numpy())
    error = _unknown_is_inf(torch.stack(error, dim=1).abs().cpu().numpy())
    # where Newton stagnated above 10 eps, distances below its last increment are not resolved
    rounding = _unknown_is_inf(rounding.cpu().numpy())  # a failed Newton's last increment is NaN
    rounding = np.maximum.accumulate(np.concatenate([np.zeros_like(rounding[:1]), rounding]), axis=0).transpose(1, 0, 2)
    local_d = local_d.abs().transpose(0, 1).cpu().numpy()
    local_e = local_e.abs().transpose(0, 1).cpu().numpy()
    size = 1 + np.abs(values).max(axis=1)  # (B, D): each sample's own scale
    # a step whose Radau error estimate has no correct digit is one radau refuses (its fixed step
    # weighs an index-k algebraic variable's estimate by h^(k-1), as here)
    digits = local_e * weight[None] <= LOCAL_ERROR_BOUND * size[:, None, :]
    converged, estimated = (a.transpose(0, 1).cpu().numpy() for a in (converged, estimated))
    failed = np.where(
        ~converged, NEWTON_FAILED, np.where(~estimated, ESTIMATE_FAILED, np.where(digits.all(2), "", NO_DIGIT))
    )
    certificate = Certificate(
        distance=CERTIFICATE_SAFETY * distance,
        radau_error=error,
        local_distance=local_d,
        local_radau_error=local_e,
        floor=CERTIFICATE_FLOOR * size,
        rounding=CERTIFICATE_SAFETY * rounding,
        failed=failed,
        certified=np.zeros(B, dtype=bool),
    )
    if not radau_error:
        return certificate
    ok = (certificate.ratio() <= 1).all(axis=(1, 2)) & (failed == "").all(axis=1)
    # radau's own fixed-step estimate (fixed_step_units), NaN where the Newton check failed (no Radau step)
    estimate = np.where(converged[..., None], units.transpose(0, 1).cpu().numpy(), np.nan)
    return dataclasses.replace(certificate, certified=ok, estimate=estimate, index_weight=weight)


def _unknown_is_inf(a: np.ndarray) -> np.ndarray:
    return np.where(np.isnan(a), np.inf, a)


def _predictions(compiled, config, grid, networks, input_columns, values, p) -> tuple:
    """Every segment's stage and end values from its chained start, for the whole batch at once
    (independent networks answer their own batch only): Y, Z, y_end, z_end, each (S, B, ...)."""
    n, dtype = len(compiled.states), getattr(torch, config.dtype)
    extra = torch.as_tensor(np.array(p[:, input_columns], dtype=float), dtype=dtype, device=config.device)
    start = torch.as_tensor(np.array(values[:, :-1, :n], dtype=float), dtype=dtype, device=config.device)
    predicted = []
    with torch.no_grad():
        for k, (net, (_, h)) in enumerate(zip(networks, segment_steps(grid), strict=True)):
            out = net.predict(torch.cat([start[:, k], extra], dim=1), h)
            predicted.append([a.to(torch.float64) for a in (out.Y, out.Z, out.y_end, out.z_end)])
    return tuple(torch.stack([row[i] for row in predicted]) for i in range(4))


def _steps(compiled, s, steps, start, Y, Z, p, n, device, radau_error: bool, newton_tol: float, units) -> tuple:
    """For rows of (t, h) ``steps`` (R, 2), starts (R, D) and the networks' stages: the Radau step's
    end values (R, D) by full Newton from those stages, Radau's local error estimate (R, D) (that
    step less the (s+1)-stage one; zeros with ``radau_error=False``), whether the step converged
    and whether the (s+1)-stage one did (R,) each,
    Newton's last increment of the end values (R, D), the step map's sensitivity
    d(y, z)_end / dy_n (R, D, n), and radau's fixed-step estimate of the step (R, D) in radau's units
    (:func:`embedded_estimate`, with ``units`` = (scale (R, D), weight (R, D), estimate_bound, high_index (D,));
    zeros with ``radau_error=False``)."""
    functions = compiled.torch_functions(dtype=torch.float64, device=device)
    t_n, h = steps[:, 0], steps[:, 1]
    y_n, z_n = start[:, :n], start[:, n:]
    A, _, c = radau_iia(s).to_torch(dtype=torch.float64, device=device)
    radau = collocation_step(
        functions, A, c, t_n, h, y_n, Y, Z, p, max_iterations=CERTIFICATE_NEWTON_ITERATIONS, tol=newton_tol
    )
    radau_end = torch.cat([radau.Y[:, -1], radau.Z[:, -1]], dim=-1)
    if not radau_error:
        done, zeros = radau.converged, torch.zeros_like(radau_end)
        return radau_end, zeros, done, done, radau.increment[:, -1], radau.end_sensitivity(), zeros
    # the (s+1)-stage step from the same start, started on the s-stage collocation polynomial
    A1, _, c1 = radau_iia(s + 1).to_torch(dtype=torch.float64, device=device)
    nodes = np.concatenate([[0.0], radau_iia(s).c])
    basis = torch.as_tensor(lagrange_matrix(nodes, radau_iia(s + 1).c), dtype=torch.float64, device=device)
    Y1 = torch.einsum("ij,...jn->...in", basis, torch.cat([y_n[:, None, :], radau.Y], dim=-2))
    Z1 = torch.einsum("ij,...jn->...in", basis, torch.cat([z_n[:, None, :], radau.Z], dim=-2))
    higher = collocation_step(
        functions,
        A1,
        c1,
        t_n,
        h,
        y_n,
        Y1,
        Z1,
        p,
        max_iterations=CERTIFICATE_NEWTON_ITERATIONS,
        tol=CERTIFICATE_NEWTON_TOL,
    )
    higher_end = torch.cat([higher.Y[:, -1], higher.Z[:, -1]], dim=-1)
    return (
        radau_end,
        radau_end - higher_end,
        radau.converged,
        higher.converged,
        radau.increment[:, -1],
        radau.end_sensitivity(),
        embedded_estimate(functions, s, t_n, h, y_n, z_n, radau.Y, radau.Z, p, *units),
    )


def embedded_estimate(functions, s, t_n, h, y_n, z_n, Y, Z, p, scale, weight, estimate_bound, high_index):
    """Radau's own fixed-step local error estimate of each row's step in radau's units (the one radau's fixed
    step checks: :func:`daemodel.backends.radau.error.fixed_step_units`, the same function), at the stage
    values ``Y`` (R, s, n), ``Z`` (R, s, m) of the step from ``t_n``, ``y_n``, ``z_n`` (R, ...) with ``h``
    (R,), over ``scale`` (R, D), with the index weights ``weight`` (R, D), radau's ``estimate_bound`` and
    ``high_index`` (D,), the algebraic variables of index 2 or more::

        ((1 / (h gamma0)) M - J) err = [sum_i (bhat_i - b_i) f(Y_i) / gamma0 + f(y_n); 0]

    with J the Jacobian of (f, g) at the step's start, and the same with ``f`` at ``u_n + err`` (the stiff
    filter once more, which radau applies before it judges a step beyond its bounds, where the flow damps
    what the filter damps).  What radau's fixed step gives differently: J is the one at each step's start
    (radau's ``reuse_jacobian`` may keep an older one: ``reuse_jacobian=False`` is this), and the start and
    the scale are the networks' values, not radau's.  Returns a tensor (R, D) on the device of ``Y``."""
    from daemodel.backends.radau.error import fixed_step_units
    from daemodel.backends.radau.transform import embedded_weights

    from daemodel.collocation import model_jacobian

    tableau = radau_iia(s)
    gamma0, e = embedded_weights(tableau)
    e = torch.as_tensor(e, dtype=Y.dtype, device=Y.device)
    _, _, c = tableau.to_torch(dtype=Y.dtype, device=Y.device)
    n, D = y_n.shape[-1], y_n.shape[-1] + z_n.shape[-1]
    stage_f = functions.f(t_n[:, None] + c * h[:, None], Y, Z, p[:, None, :])  # (R, s, n)
    quadrature = torch.einsum("i,rin->rn", e, stage_f) / gamma0
    M = torch.zeros(D, dtype=Y.dtype, device=Y.device)
    M[:n] = 1.0
    matrix = torch.diag_embed(M / (h[:, None] * gamma0)) - model_jacobian(functions, t_n, y_n, z_n, p)
    lu, pivots, _ = torch.linalg.lu_factor_ex(matrix)
    zeros = torch.zeros_like(z_n)

    def solve(rhs):  # ((1 / (h gamma0)) M - J)^-1 rhs, rows (R, D)
        return torch.linalg.lu_solve(lu, pivots, rhs[..., None])[..., 0]

    def as_numpy(a):
        return a.detach().cpu().numpy()

    err = solve(torch.cat([quadrature + functions.f(t_n, y_n, z_n, p), zeros], dim=-1))
    estimate = fixed_step_units(
        as_numpy(err),
        scale,
        weight,
        estimate_bound,
        lambda: as_numpy(
            solve(torch.cat([quadrature + functions.f(t_n, y_n + err[:, :n], z_n + err[:, n:], p), zeros], dim=-1))
        ),
        lambda rhs: as_numpy(solve(torch.as_tensor(rhs, dtype=Y.dtype, device=Y.device))),
        as_numpy(h) * gamma0,
        gamma0,
        n,
        high_index,
    )
    return torch.as_tensor(estimate, dtype=Y.dtype, device=Y.device)
