"""One Radau IIA step on an engine: the state, the start guess, Newton's matrices, acceptance.

Each step solves ``F = 0, G = 0`` of :func:`daemodel.collocation.stage_residual` (the equations
the Radau-PINN minimises) for the stage values of every sample at once (:mod:`.newton`), from a
start guess extrapolated from the last step's collocation polynomial, with one Jacobian at the
step's start whose transformed systems (:mod:`.transform`) are factored once and kept across
iterations and, while Newton contracts fast, across steps (RADAU5's strategy).  The controller
(:mod:`.control`) decides where the steps go and what Newton must reach; the step is the same for
both.  On dense systems of one trajectory the casadi engine runs an adaptive attempt in one
compiled call (:mod:`.compiled`), and many attempts with the controller in one (:mod:`.loop`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from daemodel.backends.grids import output_times
from daemodel.backends.radau import formulas
from daemodel.backends.radau.compiled import STEP_RESULTS
from daemodel.backends.radau.engines import Residual, factors_bytes
from daemodel.backends.radau.error import ErrorEstimate, numpy_copy
from daemodel.backends.radau.formulas import SCALAR
from daemodel.backends.radau.newton import STAGE_NEWTON_STEPS, Newton, jacobian_not_finite
from daemodel.backends.radau.records import OutputsAt, Records
from daemodel.backends.radau.transform import embedded_weights
from daemodel.backends.radau.tries import AbstractTriesSide, attempt_tries

from daemodel.collocation import extrapolation_polynomial, horner, lagrange_matrix
from daemodel.dense import collocation_values, step_owners
from daemodel.errors import ConvergenceError, InvalidOptionError, ResourceLimitError
from daemodel.files import memory_limit
from daemodel.messages import listed
from daemodel.tableau import radau_iia

# Reuse the Jacobian for the next step when Newton contracted at least this fast (RADAU5's THET:
# 0.001 for small systems, "0.1, say" where Jacobians and factorisations are costly).  Above
# REUSE_LARGE_SIZE unknowns REUSE_THETA_LARGE applies.  Measured at equal error (rtol 1e-6, 1e-8):
# chains of 40 and 160 unknowns and 160 dense particles 1.2-1.9x faster, a 600-unknown grid 1.3-2x;
# the pendulum (5) at rtol 1e-10 and the squeezer (27) 1.3x slower (more iterations, cheap LUs).
REUSE_THETA, REUSE_THETA_LARGE, REUSE_LARGE_SIZE = 1e-3, 0.03, 32
# The compiled attempt (casadi engine, dense): an iteration costs ~1-5 us there against 20-50 us for a
# Jacobian and its factorisations, so the Jacobian is kept while Newton contracts faster than 0.1
# (RADAU5's advice where factorisations are costly).  Measured with jit=True, best of 5 interleaved:
# car axis 1.3-1.7x, akzo-nobel 1.3-1.5x, transistor amplifier 1.35x (rtol 1e-6) faster, the
# pendulum at rtol 1e-8 and the squeezer at 1e-8 1.2-1.5x slower (benchmarks/radau_idas.py).
REUSE_THETA_COMPILED = 0.1
# The namespace of numpy arrays (:mod:`.formulas`): the index weights are made in numpy for every engine.
NUMPY = formulas.ArrayOps(np)


def nodes_around(W: np.ndarray) -> np.ndarray | None:
    """The nodes (B, s+1, n+m) whose rows after the first are the stage values ``W`` (B, s, n+m) (those of
    :meth:`Stepper.stage_buffer`), or None."""
    base = W.base
    if base is None or base.shape != (W.shape[0], W.shape[1] + 1, W.shape[2]) or not base.flags.c_contiguous:
        return None
    return base if base[:, 1:].ctypes.data == W.ctypes.data and base[:, 1:].strides == W.strides else None


class Stepper:
    """State of one integration on an engine: the step and its counters, driven by a controller.

    Arrays belong to the engine's ``xp`` (numpy or torch): ``y (B, n)``, ``z (B, m)`` and the
    stage values ``W (B, s, n+m)``, stage by stage ``[Y_i, Z_i]``.
    """

    def __init__(self, compiled, start, options, engine, controller):
        self.engine, self.xp = engine, engine.xp
        self.ops = formulas.ArrayOps(engine.xp)  # (the namespace of .formulas)
        self.y, self.z = engine.asarray(start.y0), engine.asarray(start.z0)
        self.compiled, self.options, self.controller = compiled, options, controller
        self.policy = controller.policy
        self.tableau = engine.tableau
        self.s, self.n, self.m, self.B = engine.s, engine.n, engine.m, engine.B
        # each algebraic variable's index (RADAU5's count, coupling included): its error weight is h^(k-1)
        self.z_index = np.array(compiled.algebraic_index, dtype=float)
        self._weights_by_h = bool((self.z_index > 1).any())  # (index 2 or 3: index_weights depend on h)
        self.newton = Newton(self, self.policy)
        e = embedded_weights(self.tableau)[1]
        self.error = ErrorEstimate(self, e)
        self._det_sign, self._det_time = None, compiled.t0  # the last fresh Jacobian's sign of det
        self.stats = {
            "mode": controller.name,
            "engine": engine.name,
            "stages": self.s,
            "order": self.tableau.order,
            "dtype": options.dtype,
            "device": options.device,
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
            "factor_bytes": 0,  # the largest factorisation's bytes (.engines.factors_bytes)
            "residual_evaluations": 0,
            "h_min": math.inf,
            "h_max": 0.0,
        }
        controller.start_stats(self.stats)
        self._jac = None  # (J, t) at the last refresh
        self.factors = None  # the Factors of the transformed systems of J and the current h
        self._index_weights = None  # (h, h^(k-1) per component (D,)) for the last h
        self._f_start = None  # f at the start of the next step (the last stage's f of this one)
        self.records = None  # the accepted steps' outputs (Records)
        self.stop, self.shown = None, 0  # the caller's stop and the blocks of records shown to it (integrate)
        self.eta = engine.asarray(np.ones(self.B))  # Newton's contraction estimate
        self._previous = None  # (h, nodes (B, s+1, n+m): u_start and W) of the last accepted step, for the start guess
        self.stage_steps = 0  # steps left that start with full Newton (see attempt)
        self._extrapolation = None  # (h / h_old, Lagrange matrices) of the last start guess
        self._extrapolation_polynomial = extrapolation_coefficients(self.s)  # the matrix by Horner's rule
        self._high_index = formulas.high_index_columns(self.s, self.n, self.z_index)  # (guessed apart)
        self.record_budget = math.inf  # accepted steps whose records fit in memory (set by the backend)
        # the RADAU5 controller on dense systems of one trajectory: each attempt in one compiled call
        self.compiled_step = (
            self.policy.trust_last_rate
            and options.start_guess is None
            and engine.make_compiled_step(self.policy.iterations, e, jit=engine.jit)
        )
        if self.compiled_step:
            self.stats["compiled_retries"] = 0  # compiled attempts that failed and ran again on the general path
        # where iterations are cheap (the compiled step), the Jacobian and factors are kept longer
        # (REUSE_THETA_COMPILED, control.KEEP_H_BAND_COMPILED), unless Newton's tolerance sits at the
        # rounding floor (Radau5Controller.rounding_floor: rtol below ~5e-10), where a slower contraction
        # leaves stage errors that the error estimate reads as the step's (the pendulum at rtol 1e-13,
        # s = 7: step size underflow)
        self.keep_longer = bool(self.compiled_step) and not controller.rounding_floor
        # and many attempts with the controller in one call (.loop), where the engine factors in casadi
        self.compiled_run = engine.make_compiled_run(self.policy.iterations) if self.compiled_step else None
        if self.compiled_run is not None:
            self.stats["compiled_runs"] = 0  # calls of the compiled run (each up to loop.RUN_ATTEMPTS attempts)
        engine.make_newton_step()  # (the general path's, where the compiled step did not bring it)

    # ---- pieces -------------------------------------------------------------------------
    def state(self):
        return self.xp.concatenate([self.y, self.z], axis=-1)

    def rms(self, x):
        """Root mean square over all but the batch axis, shape (B,)."""
        return self.ops.rms(x)

    def factor(self, J, t, h, error_only=False):
        factors = self.engine.factor(J, h, error_only)
        self.counted(factors, len(factors.shifts) if factors.complete else 1)
        self.check_singular(factors.singular, t, h, "Newton matrix", J)
        return factors

    def index_weights(self, h):
        """``h^(k-1)`` for each component (1 for the states), kept while h is unchanged."""
        # (every h's where all are of index 1, h^0 = 1: made once; and the last h's dropped before the next h's are
        # made: at 10^5 unknowns both, and the next one's pieces, were a cold solve's peak, 2.4 MB beside the rest)
        if self._index_weights is None or (self._index_weights[0] != h and self._weights_by_h):
            self._index_weights = None
            weights = formulas.index_weights(NUMPY, h, self.n, self.z_index - 1)
            self._index_weights = (h, self.engine.asarray(weights))
        return self._index_weights[1]

    def weights(self, h, u_ref, overwrite: bool = False):
        """Error scale of each of the n + m components, shape (B, n+m); ``overwrite``: in ``u_ref``'s place on numpy
        (the same bits: no temporaries of its size, two of a cold solve's peak at 10^5 unknowns, the error's norm)."""
        policy = self.policy
        if not (overwrite and self.xp is np):
            return formulas.error_scale(policy.atol, policy.rtol, u_ref, self.index_weights(h))
        u_ref *= policy.rtol
        u_ref += policy.atol
        u_ref /= self.index_weights(h)
        return u_ref

    def magnitude(self):
        """``|u|`` of the step's start value, a new array (a caller may overwrite it: :meth:`weights`)."""
        u = self.state()
        return self.xp.abs(u, out=u)

    def residual(self, t, h, W):
        self.stats["residual_evaluations"] += 1
        return self.engine.residual(t, h, self.y, W)

    def stage_buffer(self, dtype):
        """An array for stage values (1, s, n+m) in a step's nodes (1, s+1, n+m), whose first row :meth:`accept` fills
        with the step's start value (:meth:`.newton.Newton.simplified`'s own iterates: the nodes without a copy of
        them, 4.8 MB at 10^5 unknowns, s = 5); None where the engine is not numpy's or solves a batch."""
        return np.empty((1, self.s + 1, self.n + self.m), dtype)[:, 1:] if self.xp is np and self.B == 1 else None

    def constant_guess(self):
        """Every stage value equal to the step's start value."""
        u = self.state()
        return np.repeat(u[:, None, :], self.s, axis=1) if self.xp is np else u[:, None, :].expand(self.B, self.s, -1)

    def start_guess(self, h, t=None):
        """Stage values from ``options.start_guess`` where given, else extrapolated from the last
        step's collocation polynomial (or constant at the first step)."""
        xp = self.xp
        if self.options.start_guess is not None:
            W = self.options.start_guess(t, self.y, self.z)
            if xp is np:
                W = np.asarray(W.detach().cpu().numpy() if hasattr(W, "detach") else W, dtype=float)
            else:
                W = xp.as_tensor(W, dtype=self.y.dtype, device=self.y.device)
            if tuple(W.shape) != (self.B, self.s, self.n + self.m):
                raise InvalidOptionError(
                    f"start_guess returned stage values of shape {tuple(W.shape)}; expected "
                    f"{(self.B, self.s, self.n + self.m)} (samples, stages, n + m)"
                )
            return W
        if self._previous is None:
            return self.constant_guess()
        # (the last step's nodes as they are: a copy of them, joined from its start value and stage values, was the
        # first solve's peak at 10^5 unknowns, s = 5: 4.8 MB beside them)
        h_old, nodes = self._previous
        L, L_high = self.extrapolation(h / h_old)
        W = self.stage_buffer(np.result_type(L, nodes)) if xp is np else None  # (the next nodes' array: accept)
        W = xp.einsum("ij,bjk->bik", L, nodes) if W is None else np.einsum("ij,bjk->bik", L, nodes, out=W)
        if L_high is not None:  # (index-2/3 algebraic variables: formulas.HIGH_INDEX_GUESS_MIN_STAGES)
            W[..., self._high_index] = xp.einsum("ij,bjk->bik", L_high, nodes[..., self._high_index])
        return W

    def extrapolation(self, ratio):
        """The start guess's extrapolation matrices (s, s+1) for ``ratio`` = h / h_old (the whole polynomial's, and
        the index-2/3 algebraic variables' blind to their pattern, or None), kept while it is unchanged."""
        if self._extrapolation is None or self._extrapolation[0] != ratio:
            L = horner(self._extrapolation_polynomial, ratio)
            high = self._high_index and horner(extrapolation_coefficients(self.s, True), ratio)
            self._extrapolation = (ratio, tuple(None if x is None else self.engine.asarray(x) for x in (L, high)))
        return self._extrapolation[1]

    def start_f(self, t):
        """``f`` at the step's start: the last accepted step's final stage (Radau IIA is stiffly accurate)."""
        if self._f_start is None:
            self._f_start = self.engine.f(t, self.y, self.z)
        return self._f_start

    def check_singular(self, singular, t, h, what, J):
        """Raise :class:`ConvergenceError` where a factorisation reports a singular matrix, with the
        likely cause: a Jacobian ``J`` that is not finite (the state left f's domain), algebraic
        variables the constraints stop determining, or else the step size itself."""
        if not bool(singular.any()):
            return
        sample = self.engine.first(singular)
        head = f"radau: the {what} is singular for sample {sample} at t = {t:.6g} with h = {h:.3g}"
        matrices = J if isinstance(J, list) else [J]
        if not all(bool(self.xp.isfinite(m).all()) for m in matrices):
            raise ConvergenceError(f"{head}: {jacobian_not_finite(self.compiled, self.engine, matrices)}")
        signs = self.engine.z_matrix_sign(J)
        if self.m and bool((signs == 0).any()):
            raise ConvergenceError(
                f"{head}; the constraints do not determine the algebraic variables there (their iteration matrix, "
                "g_z or g_y f_z, is singular)"
            )
        determined = ", though the constraints determine the algebraic variables" if self.m else ""
        raise ConvergenceError(
            f"{head}{determined}: an eigenvalue of the Jacobian times h meets one of the method's shifts (a stiff "
            "mode at this h); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
        )

    # ---- the run --------------------------------------------------------------------------
    def integrate(self, t_span, stop=None):
        """Values at the output times: ``(times (T,), values (B, T, n+m))``.

        ``stop``: the caller's ``stop(times (k,), Y (k, n), Z (k, m)) -> bool`` (one sample), called on
        each block of the step ends (:meth:`stopped`); where it returns True the integration ends
        there, and the outputs are those up to it (t_eval's up to the last step's end)."""
        t0 = t_span[0]
        grid = self.controller.grid(t_span)
        t_out = output_times(self.options.t_eval, t_span, grid)
        u0 = self.state()
        dense, at_times = self.options.dense_output, self.options.t_eval is not None
        # t_eval without the dense output: each block's polynomials give the outputs it covers as it comes
        outputs = OutputsAt(t_out, t0, u0, self.tableau.c, self.engine, self.index) if at_times and not dense else None
        self.records = Records(t0, u0, dense=dense, outputs=outputs)
        self.stop, self.shown = stop, 0
        self.controller.run(self, t_span, grid)
        if at_times:
            reached = self.records.times[-1][-1]
            if outputs is not None:
                return outputs.result(reached)
            if self.xp is np:  # (the dense output's nodes joined before the values at t_eval are made: .records)
                self.records.join()
            return self.dense_output(t_out[t_out <= reached], u0, t0, self.records)
        times, values = self.records.ends(self.xp)
        return times, numpy_copy(values)

    def polynomials(self):
        """The accepted steps' collocation polynomials (:class:`~daemodel.dense.CollocationPolynomials`)
        after :meth:`integrate`, or None where they were not kept (``dense_output=False``)."""
        if not self.options.dense_output:
            return None
        return self.records.polynomials(self.tableau.c)

    def stopped(self) -> bool:
        """Whether the caller's ``stop`` (:meth:`integrate`) ends the integration: it is shown each block
        of outputs it has not seen (the start value first), in order, until it returns True."""
        if self.stop is None:
            return False
        while self.shown < len(self.records.times):
            times, values = self.records.block(self.shown)
            dense = self.records.block_polynomials(self.shown, self.tableau.c) if self.shown else None
            self.shown += 1
            values = numpy_copy(values[0])
            if self.stop(times, values[:, : self.n], values[:, self.n :], dense):
                return True
        return False

    # ---- one step -----------------------------------------------------------------------
    def attempt(self, t, h):
        """Newton on the step from ``t`` with ``h``.

        First with the step-start Jacobian through the transformed systems (reused while it serves,
        refreshed once if a reused one fails); if that fails, full Newton with each stage's Jacobian
        at the starting guess (with the policy's rescue), which also checks that z stays determined
        at the stages.  After a step needed full Newton, the next STAGE_NEWTON_STEPS steps start
        with it directly.
        """
        newton = self.newton
        J = self.current_jacobian(t, h)
        if self.options.start_guess is not None:
            # a guess close to the collocation solution: full Newton from it converges quadratically
            # (the pendulum at h = 0.05 from a Radau-PINN's stages: 2 iterations a step, against 6 of
            # simplified Newton with the step-start Jacobian, which contracts at ~0.1 there)
            self.stage_steps = max(self.stage_steps, 1)
        if self.stage_steps > 0:
            self.stage_steps -= 1
            self.current_lu(J, t, h, error_only=True)  # the error estimate's system
            W0 = self.start_guess(h, t)
            guessed = self._previous is not None or self.options.start_guess is not None
            if guessed and not self.finite_at(t, h, W0):
                # the guess left f's domain (Akzo Nobel: y2 < 0 under a sqrt): start from the start value
                W0, guessed = self.constant_guess(), False
            found = newton.full(t, h, W0)
            if found[0] is None and guessed:
                return newton.full(t, h, self.constant_guess())
            return found
        # with the transformed systems: the tries of .tries (with a stale Jacobian refreshed, from the
        # start value, then z's determinedness checked), as the compiled attempt and run make them
        extrapolated = self._previous is not None or self.options.start_guess is not None
        side = GeneralTries(self, t, h)
        # (the start value's guess made where a try starts from it, and the extrapolated one each time a try starts
        # from it, the same values: GeneralTries.attempt; neither is held beside Newton's iterates, nor J beside a
        # refreshed one: 0.4 and 0.24 MB of the solve's peak at 10^4 unknowns, s = 5)
        factors = self.current_lu(J, t, h)
        del J
        guess = self.start_guess(h, t) if self.options.start_guess is not None else lambda: self.start_guess(h, t)
        tries = attempt_tries(SCALAR, side, factors, guess, self.constant_guess, extrapolated)
        del factors
        if tries.result[0] is None and self.policy.rescue:  # (every try started from the start value then)
            return newton.full(t, h, self.constant_guess())
        return tries.result

    def attempt_with_error(self, t, h, first):
        """:meth:`attempt` and the error norm of :meth:`.ErrorEstimate.norm`: ``(result, iterations, why,
        sample, error norm)``, in compiled calls where the engine has the compiled step (:mod:`.compiled`)."""
        found = self.compiled_attempt(t, h, first) if self.compiled_step else None
        if found is not None:
            return found
        result, iterations, why, sample = self.attempt(t, h)
        if result is None:
            return result, iterations, why, sample, math.inf
        W, r, _ = result
        return result, iterations, None, None, self.error.norm(t, h, r, W, first)

    def compiled_attempt(self, t, h, first):
        """The attempt of :meth:`attempt_with_error` in compiled calls, where Newton runs on the transformed
        systems; None where the step must run on the general path (full Newton pending, factors that
        cannot serve, or with the policy's rescue values that turned non-finite: full Newton follows).

        The retries of :meth:`attempt`, in its order (:func:`.tries.attempt_tries`, which the compiled
        run builds into its graph too): from the extrapolated guess, again with a fresh Jacobian
        where the kept one is stale, then from the start value; where all fail, the determinedness
        of z over the step is checked as :meth:`attempt` checks it.
        """
        if self.stage_steps > 0:
            return None
        factors = self.current_lu(self.current_jacobian(t, h), t, h)
        if factors.inverse is None:
            return None
        # every node at the start value: a constant guess (at the ratio 0, the start value's weight is 1)
        start = (np.tile(self.state()[0], self.s + 1), 0.0)
        extrapolated = self._previous is not None
        guess = (self._previous_nodes, h / self._previous[0]) if extrapolated else start
        side = CompiledTries(self, t, h, first)
        tries = attempt_tries(SCALAR, side, factors, guess, start, extrapolated)
        self.stats["compiled_retries"] += tries.retries
        self.stats["residual_evaluations"] += tries.evaluations
        if not tries.usable or (self.policy.rescue and side.non_finite(tries.result)):
            return None
        return tries.result.found

    def compiled_try(self, factors, t, h, guess, first, f0):
        """One compiled attempt from ``guess`` = (the last step's nodes, h / h_old): a :class:`CompiledTry`
        whose ``found`` is as :meth:`attempt_with_error` returns it (non-finite values unnamed)."""
        previous, ratio = guess
        policy, stats = self.policy, self.stats
        scalars = dict(t=t, h=h, ratio=ratio, eta=float(self.eta[0]), newton_tol=policy.tol, first=float(first))
        out = self.engine.compiled_step(factors, dict(scalars, rtol=policy.rtol, atol=policy.atol), previous, f0)
        # (Python floats: cheaper to test)
        outcome, k, evaluations, theta, eta, err = out[: len(STEP_RESULTS)].tolist()
        k, outcome, evaluations = int(k), int(outcome), int(evaluations)
        if outcome != formulas.CONVERGED:
            why = {
                formulas.DIVERGING: f"diverging (contraction {theta:.2f})",
                formulas.SLOW: f"converging too slowly (contraction {theta:.2f})",
                formulas.NOT_CONVERGED: f"not converged in {k} iteration{'s' if k != 1 else ''}",
                formulas.NON_FINITE: formulas.UNNAMED_NON_FINITE,
            }.get(outcome)
            return CompiledTry((None, k, why, 0, math.inf), outcome, evaluations)
        stats["newton_iterations"] += k
        stats["max_newton_iterations"] = max(stats["max_newton_iterations"], k)
        self.eta = np.array([eta])
        s, n, D = self.s, self.n, self.n + self.m
        results = self.engine.step_output.read(out)
        W = results["W"].reshape(1, s, D)
        r = Residual(R=None, stage_f=results["F"].reshape(1, s, n), G=None)
        found = (W, r, theta), k, None, None, formulas.finite_or_inf(formulas.SCALAR, err)
        return CompiledTry(found, outcome, evaluations)

    def finite_at(self, t, h, W) -> bool:
        """Whether the stage residual (f and g) is finite at the stage values ``W``."""
        return bool(self.xp.isfinite(self.residual(t, h, W).R).all())

    def factor_stages(self, stage_J, t, h):
        """The full Newton matrix of per-stage Jacobians, factored; the next steps start with it."""
        factors = self.engine.factor_stages(stage_J, h)
        self.counted(factors, 1)
        self.stats["newton_refreshes"] += 1
        self.check_singular(factors.singular, t, h, "Newton matrix", stage_J)
        self.stage_steps = STAGE_NEWTON_STEPS
        return factors

    def counted(self, factors, systems: int) -> None:
        """Count a factorisation of ``systems`` systems and its bytes (the largest in ``factor_bytes``)."""
        self.stats["lu_decompositions"] += systems
        self.stats["factor_bytes"] = max(self.stats["factor_bytes"], factors_bytes(factors))

    def accept(self, t, h, result, t_next):
        """Take the step: record its output, move the state to ``t_next``, decide on the Jacobian's reuse."""
        W, r, theta = result
        if self.records.count > self.record_budget:
            raise ResourceLimitError(
                f"radau: at t = {t:.6g}, the {self.records.count} steps' outputs of {self.B} sample(s) reach "
                f"the memory allowed ({memory_limit() / 2**30:.3g} GiB, DAEMODEL_MEMORY_LIMIT): solve fewer samples "
                "at a time, loosen rtol, give t_eval, or keep the step ends only (dense_output=False; with a fixed h, "
                "a grid's size is checked before the solve)"
            )
        # (the last step's nodes go before this one's are made: the start guess has read them; at 10^5 unknowns,
        # s = 5, both and the stage values were the first solve's peak, 4.8 MB each)
        u, self._previous = self.state(), None
        if self.stop is None:  # (and the records' copy of them, t_eval's outputs from them filled: take_steps)
            self.records.release(len(self.records.times), newest=False)
        nodes = nodes_around(W) if self.xp is np else None  # (B, s+1, n+m)
        if nodes is None:
            nodes = self.xp.concatenate([u[:, None], W], axis=1)
        else:
            nodes[:, 0] = u
        nodes, u = nodes[:, None], None  # (B, 1, s+1, n+m)
        f_end = r.stage_f[:, -1]  # (copied on numpy: the casadi engine's residual is its buffer, the next call's)
        f_end = f_end.copy() if self.xp is np else f_end
        self.take_steps(np.array([t]), np.array([h]), np.array([t_next]), nodes, f_end)
        if not self.keeps_jacobian(theta):
            self._jac = None  # slow contraction (or no reuse asked for): a fresh Jacobian next step

    def take_steps(self, starts, lengths, ends, nodes, f_end):
        """Take accepted steps (one, or a compiled run's): ``starts``, ``lengths`` and ``ends`` (k,) numpy,
        ``nodes`` (B, k, s+1, n+m) their start values and stages, ``f_end`` (B, n) f at the last one's end.

        Records their outputs (the nodes whole with ``dense``, else a copy of the end values: a view
        would keep all of them), moves the state to the last one's end, keeps its polynomial for the
        next start guess and counts them.
        """
        if self.records.nodal:
            kept = nodes
        else:
            end = nodes[:, :, -1:]
            kept = end.copy() if self.xp is np else end.clone()
        last = nodes[:, -1]  # (B, s+1, n+m)
        self._previous = (float(lengths[-1]), last)
        if self.compiled_step:  # the compiled step's start guess reads the nodes packed (B = 1)
            self._previous_nodes = last[0].reshape(-1).copy()
        # (the end values copied where the nodes are not kept to the end: views would keep them beside the next
        # step's, which accept makes once the start guess has read these)
        end = last[:, -1]  # (B, n+m)
        end = end if self.records.dense else end.copy() if self.xp is np else end.clone()
        self.y, self.z = end[:, : self.n], end[:, self.n :]
        # (t_eval's outputs: the older blocks' nodes go, the last one's too, which nothing reads now, before this
        # block's outputs are filled: two steps' nodes and the fill were the first solve's peak, 10^4 unknowns;
        # with a caller's stop, once it has seen them)
        if self.stop is None:
            self.records.release(len(self.records.times), newest=False)
        self.records.add(starts, lengths, ends, kept)
        if self.stop is not None:
            self.records.release(self.shown)
        self._f_start = f_end
        self.stats["steps"] += len(starts)
        lengths = lengths.tolist()
        self.stats["h_min"] = min(self.stats["h_min"], *lengths)
        self.stats["h_max"] = max(self.stats["h_max"], *lengths)

    def reuse_theta(self) -> float:
        """The contraction up to which the next step keeps the Jacobian (-inf: never, reuse_jacobian=False)."""
        if not self.options.reuse_jacobian:
            return -math.inf
        if self.keep_longer:
            return REUSE_THETA_COMPILED
        return REUSE_THETA_LARGE if self.n + self.m > REUSE_LARGE_SIZE else REUSE_THETA

    def run_ready(self) -> bool:
        """Whether the next attempts may run in one compiled call (:mod:`.loop`): the engine has it, no
        full Newton is pending, and the records of as many accepted steps fit the memory allowed."""
        if self.compiled_run is None or self.stage_steps > 0:
            return False
        return self.records.count + self.compiled_run.attempts <= self.record_budget

    # ---- Newton's matrices ----------------------------------------------------------------
    def current_jacobian(self, t, h):
        """The Jacobian at the step's start (kept while Newton contracts fast), as RADAU5."""
        if self._jac is None:
            self.stats["jacobian_evaluations"] += 1
            J, factors, signs = self.engine.refresh(t, self.y, self.z, h)
            self._jac, self.factors = (J, t), factors
            if factors is not None:  # factored along with J (see the engine's refresh)
                self.counted(factors, len(factors.shifts))
            self.check_determined(J, t, h, signs=signs)
        return self._jac[0]

    def keeps_jacobian(self, theta) -> bool:
        """Whether the next step, after this one is accepted with Newton's contraction ``theta``, starts
        with the Jacobian it has: one is held (full Newton may have dropped it) and Newton contracted
        fast enough (:func:`.formulas.jacobian_kept`)."""
        return self._jac is not None and formulas.jacobian_kept(SCALAR, theta, self.reuse_theta())

    def drop_jacobian(self):
        """A fresh Jacobian at the next step's start."""
        self._jac = None

    def drop_factors(self):
        """Factor anew at the next attempt (its h changes)."""
        self.factors = None

    def current_lu(self, J, t, h, error_only=False):
        """The factored transformed systems of ``J`` for step ``h`` (kept while both are, h to rounding), or
        (``error_only``) the error estimate's system alone."""
        factors = self.factors  # (of an h that t's rounding moved, they serve: formulas.factors_serve)
        serve = factors is not None and formulas.factors_serve(SCALAR, factors.h, h, t)
        if not (serve and (factors.complete or error_only)):
            # (the old ones dropped first: the band kernel makes the new ones in their buffers, .band)
            self.factors = factors = None
            self.factors = self.factor(J, t, h, error_only)
        return self.factors

    def check_determined(self, J, t, h, keep=True, signs=None):
        """Refuse a step across a point where the constraints stop determining z.

        The iteration matrix of the algebraic variables (row by row ``g_z`` for an index-1 and
        ``g_y f_z`` for an index-2 constraint, as at compile time) must stay nonsingular; its
        determinant changing sign between two fresh Jacobians means it passed through zero, where
        z is undetermined and may blow up (``q' = (0.7 - t) z, 0 = q - sin t``).  Index-2 z is
        measured against ``(atol + rtol |z|) / h``, so the error estimate alone would step over it.
        ``signs``: the engine's ``z_matrix_sign(J)`` where it came with J.
        """
        if not self.m:
            return
        if signs is None:  # (B,), or (B, s) for the stages of one step
            signs = self.engine.z_matrix_sign(J)
        signs = signs[:, None] if signs.ndim == 1 else signs
        if self._det_sign is not None:
            signs = self.xp.concatenate([self._det_sign[:, None], signs], axis=1)
        flips = formulas.sign_flip(signs[:, :-1], signs[:, 1:]).any(axis=1)
        if bool(flips.any()):
            sample = self.engine.first(flips)
            names = listed(c.name for c in self.compiled.constraints)  # (the first ten, and how many more)
            error = ConvergenceError(
                f"radau: the constraints ({names}) stop determining the algebraic variables between t = "
                f"{self._det_time:.6g} and {t + h:.6g} (sample {sample}): the determinant of their iteration "
                "matrix (g_z, or g_y f_z at index 2) changes sign, so it passes through zero, where z is not "
                "determined and may blow up; end t_span before that time or reformulate the constraints"
            )
            error.sign_change = (self._det_time, t + h)  # (the backend checks a fixed step's at a smaller h)
            raise error
        if keep:  # (not for the stages of a failed attempt: the step is retried shorter)
            self._det_sign, self._det_time = signs[:, -1], t

    def dense_output(self, t_out, u0, t0, records):
        """Values at ``t_out`` (ascending) from each step's collocation polynomial through (t_n, u_n),
        (t_n + c_i h, W_i), all points in one product (Lagrange weights at theta = (t - t_n) / h)."""
        xp = self.xp
        t_out = np.asarray(t_out, dtype=float)
        # (B, T, n+m): u0 where t <= t0
        out = xp.repeat(u0[:, None], len(t_out), axis=1) if xp is np else xp.stack([u0] * len(t_out), axis=1)
        after = (t_out > t0).nonzero()[0]  # (np.flatnonzero, without its Python wrapper)
        if not records.starts or not len(after):
            return t_out, numpy_copy(out)
        starts, lengths = np.concatenate(records.starts), np.concatenate(records.lengths)
        owner, theta = step_owners(starts, lengths, t_out[after])  # (the step ending at or after each)
        # the product form, for all points at once: exact at the nodes (a weight of 1 and zeros), which
        # Horner's rule is not (the PINN starts from stages read here and must find them on the solution)
        nodes = np.concatenate([[0.0], self.tableau.c])
        weights = self.engine.asarray(lagrange_matrix(nodes, theta))  # (P, s+1)
        nodes_of = lambda k: records.nodes_of(k, xp, self.index)  # noqa: E731
        if xp is np:  # (each step's values in their place: after is t_out's tail, t_out ascending)
            collocation_values(weights, owner, nodes_of, xp, self.index, out=out[:, after[0] :])
        else:
            out[:, after] = collocation_values(weights, owner, nodes_of, xp, self.index)
        return t_out, numpy_copy(out)

    def index(self, indices: np.ndarray):
        """``indices`` as the engine's arrays take them (a tensor on the engine's device for torch)."""
        return indices if self.xp is np else self.engine.torch.as_tensor(indices, device=self.y.device)


class CompiledTry(NamedTuple):
    """One compiled attempt's result (:meth:`Stepper.compiled_try`)."""

    found: tuple  # as Stepper.attempt_with_error returns it
    outcome: int  # .formulas.newton_iteration's
    evaluations: int  # of the residual


class StepperTries(AbstractTriesSide):
    """The tries (:func:`.tries.attempt_tries`) on Python values: the matrices the stepper's factors, a
    refresh and the stages' check the stepper's."""

    def __init__(self, stepper: Stepper, t: float, h: float):
        self.stepper, self.t, self.h = stepper, t, h

    def kept(self):
        jac = self.stepper._jac
        return jac is not None and jac[1] != self.t

    def refresh(self, matrices):
        stepper, t, h = self.stepper, self.t, self.h
        stepper.drop_jacobian()
        stepper.drop_factors()
        matrices.release()  # (the stale factors: the tries hold them, the fresh ones reuse their buffers)
        return stepper.current_lu(stepper.current_jacobian(t, h), t, h)

    def check_stages(self, matrices):
        stepper, t, h = self.stepper, self.t, self.h
        if stepper.policy.rescue:  # (full Newton follows, which checks them)
            return False
        stage_J = stepper.engine.stage_jacobians(t, h, stepper.constant_guess())
        stepper.stats["jacobian_evaluations"] += 1
        stepper.check_determined(stage_J, t, h, keep=False)  # (raises where the sign changes)
        return False


class GeneralTries(StepperTries):
    """The general path's tries: each :meth:`.newton.Newton.simplified` from stage values, its result
    ``(result or None, iterations, why, sample)``."""

    def attempt(self, matrices, guess):
        """Newton from ``guess``: stage values, or a function that makes them (:meth:`Stepper.constant_guess`)."""
        if callable(guess):  # (made for this try alone: Newton adds its increments to it in place)
            return self.stepper.newton.simplified(self.t, self.h, matrices, guess(), owned=True)
        return self.stepper.newton.simplified(self.t, self.h, matrices, guess)

    def failed(self, result):
        return result[0] is None

    def evaluations(self, result):
        return 0  # (counted as they are made)

    def usable(self, matrices):
        return True  # (a singular factorisation raised, naming why)


class CompiledTries(StepperTries):
    """The compiled attempt's tries: each a compiled call (a :class:`CompiledTry`) from a guess
    ``(the last step's nodes, h / h_old)``."""

    def __init__(self, stepper: Stepper, t: float, h: float, first: bool):
        super().__init__(stepper, t, h)
        self.first, self.f0 = first, stepper.start_f(t)[0]

    def attempt(self, matrices, guess):
        return self.stepper.compiled_try(matrices, self.t, self.h, guess, self.first, self.f0)

    def failed(self, result):
        return result.outcome != formulas.CONVERGED

    def non_finite(self, result):
        """Whether the try failed on values that turned non-finite (the compiled step does not say where)."""
        return result.outcome == formulas.NON_FINITE

    def evaluations(self, result):
        return result.evaluations

    def usable(self, matrices):
        return matrices.inverse is not None


@functools.cache
def extrapolation_coefficients(stages: int, high_index: bool = False) -> np.ndarray:
    """:func:`~daemodel.collocation.extrapolation_polynomial` of the s-stage tableau (its pattern: ``high_index``)."""
    A = radau_iia(stages).A
    return extrapolation_polynomial(radau_iia(stages).c, formulas.high_index_pattern(A) if high_index else None)
