"""RADAU5's controller and many adaptive attempts in one casadi call (the casadi engine: dense systems
up to 24 unknowns, and with ``jit`` sparse ones on static factors made in C, :mod:`.kernel`).

With the attempt compiled (:func:`.compiled.step_function`), what Python still did per attempt, the
controller's arithmetic, the Jacobian's refresh and the state's bookkeeping, cost 25-40 us, ten
times the attempt itself in machine code (the pendulum: 3.3 us).  :func:`run_function` makes
:data:`RUN_ATTEMPTS` attempts of :meth:`.control.Radau5Controller.run` one casadi function.  With
``jit`` on static factors up to 200 unknowns the whole run is machine code, in the step's library
(:meth:`.casadi_engine.CasadiEngine._library`, 100 attempts a call: :func:`attempt_function`'s attempt
called by a loop in C, :func:`run_loop_source`): on casadi's virtual machine around the step's machine
code, the run's own graph (switches, copies, the controller's scalars) took ~10 of car axis's ~17 us an
attempt.  Each attempt, as
:meth:`.step.Stepper.compiled_attempt` and the controller make it:

- refreshes the Jacobian where it was dropped (with its factored systems and the sign of the
  algebraic variables' iteration matrix), or factors anew where h changed;
- runs the compiled attempt, and its retries: with a fresh Jacobian where a kept one failed, then
  from the start value;
- where all failed, checks that z stays determined over the step and halves h; else accepts or
  rejects the step and picks the next h.

The same arithmetic in the same order: the same steps, bit for bit.  Nothing of the controller is
written here: the run's head and tail (:func:`head_function`, :func:`tail_function`) are
:mod:`.sequence`'s functions (the decisions before and after an attempt, by :mod:`.formulas`'
formulas) called on casadi symbols, which :meth:`.control.Radau5Controller.run` calls on Python
floats, and the attempt's tries are :mod:`.tries`'; every packed vector's parts are named in one
:class:`.compiled.Layout` (:mod:`.sequence`'s layouts: the head and tail take and return them by
name).  What this module writes is the graph around them: the Jacobian's refresh and refactor
as casadi switches, the carried arrays, the records.  What only Python does ends
the run *before* the attempt, which Python then makes on its own path (the attempt runs twice),
where the errors are worded: a sign change of the iteration matrix's determinant, a singular
factorisation (a non-finite inverse; an exactly singular matrix, which LAPACK refuses, fails the
call, and Python makes the next attempt), a step size underflow (where values that turned
non-finite, which fail an attempt as a diverging Newton does, shrank h away, the general path names
where they arose).  A run also ends where the integration does and at ``limit`` attempts (the
controller's budget checks).  Each attempt that ran leaves a record (:data:`.sequence.RECORD`,
then the start value and the stages) from which :class:`CompiledRun` writes the steps back into
the stepper, and the statistics by :func:`.sequence.add_statistics`.
"""

from __future__ import annotations

import numpy as np
from daemodel.backends.progress import captured_output
from daemodel.backends.radau import formulas, sequence
from daemodel.backends.radau.compiled import Layout, iteration_matrix, lend, step_layouts
from daemodel.backends.radau.formulas import CASADI
from daemodel.backends.radau.sequence import (
    ATTEMPT,
    CONTROLLER,
    FINISHED,
    FULL,
    HANDBACK,
    HEAD,
    RECORD,
    SCALARS,
    SETTINGS,
)
from daemodel.backends.radau.sparse import MAX_GROWTH
from daemodel.backends.radau.tries import AbstractTriesSide, attempt_tries

from daemodel.errors import DaemodelError

# The name of the attempt in machine code, which the loop in C calls (run_loop_source).
MACHINE_ATTEMPT = "radau_attempt_machine_code"
# Attempts in one call.  An idle one (after the run ended) costs a copy of the state; measured on
# the pendulum (19 attempts at rtol 1e-6) and car axis (~800), 32 keeps both near their best.
RUN_ATTEMPTS = 32


def sign_det_function(m: int):
    """casadi function of the sign of the determinant of an (m, m) matrix (column-major values): by
    :func:`.linalg.small_sign_det`'s formula up to m = 3, by an LU with partial pivoting above; 0 where
    it is singular or not finite."""
    import casadi

    a = casadi.SX.sym("a", m * m)
    if m == 0:
        return casadi.Function("sign_det", [a], [casadi.SX(1.0)])
    if m <= 3:
        if m == 1:
            det = a[0]
        elif m == 2:
            det = a[0] * a[3] - a[1] * a[2]
        else:
            det = (
                a[0] * (a[4] * a[8] - a[5] * a[7])
                - a[3] * (a[1] * a[8] - a[2] * a[7])
                + a[6] * (a[1] * a[5] - a[2] * a[4])
            )
        finite = casadi.logic_and(det < casadi.inf, det > -casadi.inf)
        return casadi.Function("sign_det", [a], [casadi.if_else(finite, casadi.sign(det), 0)])
    A = [[a[i + j * m] for j in range(m)] for i in range(m)]
    sign = casadi.SX(1.0)
    for k in range(m):
        for r in range(k + 1, m):  # the largest |A[r][k]| to row k, one comparison at a time
            swap = casadi.fabs(A[r][k]) > casadi.fabs(A[k][k])
            for j in range(k, m):
                A[k][j], A[r][j] = casadi.if_else(swap, A[r][j], A[k][j]), casadi.if_else(swap, A[k][j], A[r][j])
            sign = casadi.if_else(swap, -sign, sign)
        pivot = A[k][k]
        sign = sign * casadi.sign(pivot)
        for r in range(k + 1, m):
            factor = casadi.if_else(pivot != 0, A[r][k] / pivot, 0)
            for j in range(k + 1, m):
                A[r][j] = A[r][j] - factor * A[k][j]
    return casadi.Function("sign_det", [a], [casadi.if_else(casadi.fabs(sign) <= 1, sign, 0)])  # (NaN: 0)


def not_finite(casadi, values):
    """Whether any of ``values`` is NaN or infinite (their sum is then not finite, or overflows: singular enough)."""
    total = casadi.sum1(values)
    return casadi.logic_not(casadi.logic_and(total < casadi.inf, total > -casadi.inf))


def unusable(casadi, packed, static):
    """Whether the packed factors cannot serve: a value not finite (dense inverses), or with ``static``
    (:class:`.increments.StaticFactors`) also growth beyond :data:`.sparse.MAX_GROWTH` or a zero pivot
    (:meth:`.casadi_engine.CasadiEngine.factor` then factors with LAPACK or SuperLU, on Python's path)."""
    if static is None:
        return not_finite(casadi, packed)
    growth, pivot = packed[static.checks_offset], packed[static.checks_offset + 1]
    return any_of(casadi, not_finite(casadi, packed), growth > MAX_GROWTH, pivot == 0)


def any_of(casadi, *flags):
    """The logical or of casadi ``flags``."""
    out = flags[0]
    for flag in flags[1:]:
        out = casadi.logic_or(out, flag)
    return out


# The head's and the tail's inputs.
HEAD_INPUTS = {"scalars": SCALARS, "settings": SETTINGS}
TAIL_INPUTS = {"scalars": SCALARS, "settings": SETTINGS, "attempt": ATTEMPT}


def head_function():
    """The run's loop head (SX, scalars): :func:`.sequence.before_attempt` and
    :func:`.sequence.run_head` on casadi symbols, from the :data:`.sequence.SCALARS` and
    :data:`.sequence.SETTINGS` to the :data:`.sequence.HEAD`, each input and output by its name."""
    import casadi

    symbols = {name: casadi.SX.sym(name, layout.size) for name, layout in HEAD_INPUTS.items()}
    v, c = (layout.read(symbols[name]) for name, layout in HEAD_INPUTS.items())
    out = sequence.before_attempt(CASADI, v, c)
    out.update(sequence.run_head(CASADI, v, c, out["h"]))
    return casadi.Function("head", list(symbols.values()), [out[name] for name in HEAD], list(symbols), HEAD)


def tail_function(s: int, iterations: int):
    """The run after the attempt (SX, scalars): :func:`.sequence.after_attempt` and
    :func:`.sequence.run_tail` on casadi symbols, from the :data:`.sequence.SCALARS`,
    :data:`.sequence.SETTINGS` and :data:`.sequence.ATTEMPT` to the scalars ``after`` it, whether it
    ``ran``, whether a step was ``taken``, and its ``record`` (:data:`.sequence.RECORD`)."""
    import casadi

    symbols = {name: casadi.SX.sym(name, layout.size) for name, layout in TAIL_INPUTS.items()}
    v, c, a = (layout.read(symbols[name]) for name, layout in TAIL_INPUTS.items())
    # (Stepper.keeps_jacobian's test: the run holds a Jacobian after every attempt)
    a["jac_kept"] = formulas.jacobian_kept(CASADI, a["theta"], c["reuse_theta"])
    after, decisions = sequence.after_attempt(CASADI, v, c, a, s, iterations)
    scalars, ran, taken, record = sequence.run_tail(CASADI, v, c, a, after, decisions)
    outputs = {
        "after": casadi.vertcat(*(scalars[name] for name in SCALARS.names)),
        "ran": ran,
        "taken": taken,
        "record": casadi.vertcat(*(record[name] for name in RECORD)),
    }
    return casadi.Function("tail", list(symbols.values()), list(outputs.values()), list(symbols), list(outputs))


def run_function(
    engine,
    step,
    refresh,
    inverses,
    stage_jacobians,
    sign,
    static,
    iterations: int,
    attempts: int = RUN_ATTEMPTS,
):
    """The casadi function of ``attempts`` attempts of the RADAU5 controller (see the module docstring),
    :func:`attempt_function`'s attempt written out one call after the other, each a switch that passes
    the state through once the run ended: for casadi's virtual machine (in machine code the attempts
    are a loop in C, :func:`run_loop_source`).  Inputs ``[state, settings]``; output the state, then
    each attempt's record (:func:`record_layout`)."""
    import casadi

    attempt = attempt_function(engine, step, refresh, inverses, stage_jacobians, sign, static, iterations)
    state, settings = attempt.mx_in()
    active = state_layout(engine.s, engine.n, engine.D, len(engine.rows), engine.packed_size())["active"]
    idle = casadi.Function("idle", [state, settings], [state, casadi.MX.zeros(attempt.nnz_out(1))])
    maybe = casadi.Function.if_else("maybe_attempt", attempt, idle)
    carried, records = state, []
    for _ in range(attempts):
        carried, rec = maybe(carried[active], carried, settings)
        records.append(rec)
    return casadi.Function("radau_run", [state, settings], [casadi.vertcat(carried, *records)])


def attempt_function(
    engine, step, refresh, inverses, stage_jacobians, sign, static, iterations: int, machine: bool = False
):
    """The casadi function of one attempt of the RADAU5 controller (see the module docstring), from
    ``[state, settings]`` to ``[state after it, its record]``; ``machine``: for machine code, named
    :data:`MACHINE_ATTEMPT` (the loop in C calls it: :func:`run_loop_source`).

    ``step``: the compiled attempt (:func:`.compiled.step_function`, or its machine code);
    ``refresh`` and ``inverses``: :func:`.compiled.refresh_function` and
    :func:`.compiled.inverse_function`, or with ``static`` (the engine's
    :class:`.increments.StaticFactors`) the packed static factors' (:mod:`.kernel`); ``sign``: a
    function of the sign of det of an (m, m) matrix above m = 3 (None: :func:`sign_det_function`);
    ``stage_jacobians``: the Jacobian's nonzeros at every stage
    (:func:`.compiled.casadi_functions`).  Inputs ``[state, settings]`` (:data:`.sequence.SCALARS` and the
    arrays, :data:`.sequence.SETTINGS` and p); outputs the state after it and its record (:func:`record_layout`).
    The scalar logic is in two SX functions (:func:`head_function`, :func:`tail_function`): on casadi's
    virtual machine an MX operation costs ~20 ns, an SX one ~2.
    """
    import casadi

    s, n, D, m = engine.s, engine.n, engine.D, engine.m
    P, nnz, size_inverse = engine.p.size, len(engine.rows), engine.packed_size()
    layout, step_in, step_out = state_layout(s, n, D, nnz, size_inverse), *step_layouts(s, n, D, P)
    state = casadi.MX.sym("state", layout.size)
    settings = casadi.MX.sym("settings", SETTINGS.size + P)
    scalars = state[: SCALARS.size]
    u, nodes, f0, J, inverse = (state[layout[name]] for name in ("u", "nodes", "f0", "J", "inverse"))
    given = settings[: SETTINGS.size]
    c = SETTINGS.read(given)
    p = settings[SETTINGS.size :]
    t, eta, det_sign = state[layout["t"]], state[layout["eta"]], state[layout["det_sign"]]
    head = head_function()(scalars=scalars, settings=given)
    h, refreshed, factored, ratio = head["h"], head["refreshed"], head["factored"], head["ratio"]

    # the Jacobian, refreshed (with its factored systems) where it was dropped; else factored where h changed
    sign_det = sign if sign is not None and m > 3 else sign_det_function(m)
    t_jac = casadi.if_else(refreshed, t, state[layout["t_jac"]])
    side = CasadiTries(engine, step, refresh, sign_det, stage_jacobians, static, step_out, t_jac != t)
    fresh = lambda *matrices: side.refresh(matrices)[4:]  # noqa: E731
    J, sign, inverse = CASADI.branch(
        "refresh", refreshed, fresh, lambda *matrices: matrices[4:], t, h, u, p, J, det_sign, inverse
    )
    factor = lambda h, J, inverse: inverses(casadi.vertcat(h, J))  # noqa: E731
    inverse = CASADI.branch("refactor", factored, factor, lambda h, J, inverse: inverse, h, J, inverse)
    matrices = (t, h, u, p, J, sign, inverse)
    singular = unusable(casadi, inverse, static)

    # the attempt from the last step's polynomial (a constant guess at the first step: ratio 0), then
    # its retries (.tries, as Stepper.compiled_attempt makes them): with a fresh Jacobian where the kept
    # one failed, then from the start value (the state at the start, s+1 times, at ratio 0); where
    # every try failed (values finite), before h is halved, whether z stays determined over the step
    fixed = dict(t=t, h=h, eta=eta, newton_tol=c["newton_tol"], first=head["first"], rtol=c["rtol"], atol=c["atol"])
    x = casadi.vertcat(*step_in.pack(**fixed, ratio=ratio, nodes=nodes, f0=f0, p=p))
    start = casadi.vertcat(*step_in.pack(**fixed, ratio=0.0, nodes=casadi.repmat(u, s + 1, 1), f0=f0, p=p))
    tries = attempt_tries(CASADI, side, matrices, x, start, state[layout["h_old"]] > 0)
    stale, result, (J, retry_sign, inverse) = tries.stale, tries.result, tries.matrices[4:]
    singular = casadi.logic_or(singular, casadi.logic_not(tries.usable))
    results = step_out.read(result)
    outcome, evaluations, retries = results["outcome"], tries.evaluations, tries.retries
    newton_failed, stage_flip = tries.newton_failed, tries.stage_flip

    attempt = dict(head, stale=stale, singular=singular, sign=sign, retry_sign=retry_sign, outcome=outcome)
    attempt.update(iterations=results["iterations"], theta=results["theta"], eta=results["eta"])
    attempt.update(error_norm=results["error_norm"], evaluations=evaluations, retries=retries)
    attempt.update(newton_failed=newton_failed, stage_flip=stage_flip)
    del attempt["ratio"], attempt["first"]  # (the step's inputs)
    attempt = casadi.vertcat(*ATTEMPT.pack(**attempt))
    after = tail_function(s, iterations)(scalars=scalars, settings=given, attempt=attempt)
    ran, taken, W = after["ran"], after["taken"], results["W"]

    # in machine code switches that copy the branch taken: casadi's if_else on arrays makes four passes over
    # both, ~9 % of car axis's machine code with the state's 213 entries of J and the factors (on the virtual
    # machine the switches' calls cost more: the chain of 20 pendulums 1.8 % more instructions)
    def pick(name, condition, new, old):
        if not machine:
            return casadi.if_else(condition, new, old)
        return CASADI.branch(name, condition, lambda a, b: a, lambda a, b: b, new, old)

    W_last, F_last, J_start = W[(s - 1) * D :], results["F"][(s - 1) * n :], layout["J"].start
    arrays = pick("taken", taken, casadi.vertcat(W_last, u, W, F_last), state[layout["u"].start : J_start])
    moved = casadi.vertcat(after["after"], arrays, pick("ran", ran, casadi.vertcat(J, inverse), state[J_start:]))
    zeros = casadi.MX.zeros(D * (s + 1)) if machine else 0
    record = casadi.vertcat(after["record"], pick("kept", ran, casadi.vertcat(u, W), zeros))
    return casadi.Function(MACHINE_ATTEMPT if machine else "attempt", [state, settings], [moved, record])


def run_loop_source(engine, function, attempts: int) -> str:
    """C of casadi's external-function interface: ``radau_run_machine_code``, :func:`run_function`'s
    signature and output (``[state, settings]`` to the state, then ``attempts`` records) as a loop in C
    around ``radau_attempt_machine_code``, the exported C of ``function`` (:func:`attempt_function`'s, on
    ``engine``), in the same library after it (:func:`.compiled.machine_library`).

    casadi's own loop (``mapaccum``) kept every attempt's state (100 x 287 entries on car axis) and
    copied it at each of its levels, and its switch copied the state through every idle attempt; here
    two buffers take turns, and the loop stops where the run does.  The records after the last attempt
    are left as they were (zeroing them wrote 0.9 MB a call at 200 unknowns, s = 5): the reader takes
    the state's count of the attempts that ran (:meth:`CompiledRun._write_back`)."""
    attempt, name = MACHINE_ATTEMPT, "radau_run_machine_code"
    layout = state_layout(engine.s, engine.n, engine.D, len(engine.rows), engine.packed_size())
    state, settings, record, active = layout.size, function.nnz_in(1), function.nnz_out(1), layout["active"]
    return f"""
/* daemodel: radau's compiled run, {attempts} attempts of {attempt} in a loop (numbers only) */
static const casadi_int {name}_in[2][3] = {{{{{state}, 1, 1}}, {{{settings}, 1, 1}}}};
static const casadi_int {name}_out[3] = {{{state + attempts * record}, 1, 1}};

int {name}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {{
  const casadi_real* settings = arg[1];
  casadi_real* out = res[0];
  casadi_real* now = w;
  casadi_real* next = w + {state};
  casadi_real* swap;
  casadi_int i, k;
  if (!out) return 0;
  for (i = 0; i < {state}; i++) now[i] = arg[0] ? arg[0][i] : 0;
  for (k = 0; k < {attempts} && now[{active}] != 0; k++) {{
    arg[2] = now;
    arg[3] = settings;
    res[1] = next;
    res[2] = out + {state} + k * {record};
    if ({attempt}(arg + 2, res + 1, iw, w + {2 * state}, mem)) return 1;
    swap = now, now = next, next = swap;
  }}
  for (i = 0; i < {state}; i++) out[i] = now[i];
  return 0;
}}
casadi_int {name}_n_in(void) {{ return 2; }}
casadi_int {name}_n_out(void) {{ return 1; }}
const casadi_int* {name}_sparsity_in(casadi_int i) {{ return i == 0 || i == 1 ? {name}_in[i] : 0; }}
const casadi_int* {name}_sparsity_out(casadi_int i) {{ return i == 0 ? {name}_out : 0; }}
int {name}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {{
  casadi_int n_arg = 0, n_res = 0, n_iw = 0, n_w = 0;
  {attempt}_work(&n_arg, &n_res, &n_iw, &n_w);
  if (sz_arg) *sz_arg = 2 + n_arg;
  if (sz_res) *sz_res = 1 + n_res;
  if (sz_iw) *sz_iw = n_iw;
  if (sz_w) *sz_w = {2 * state} + n_w;
  return 0;
}}
"""


class CasadiTries(AbstractTriesSide):
    """The compiled attempt's tries (:func:`.tries.attempt_tries`) on casadi symbols, in
    :func:`run_function`'s graph: ``matrices`` = ``(t, h, u, p, J, sign, inverse)`` (the step's start,
    the Jacobian's nonzeros, the sign of the algebraic variables' iteration matrix, the packed
    factors), a guess the compiled step's packed input, a result its packed output."""

    def __init__(self, engine, step, refresh, sign_det, stage_jacobians, static, step_out, stale_jacobian):
        self.engine, self.step, self.refresh_function, self.sign_det = engine, step, refresh, sign_det
        self.stage_jacobians, self.static, self.out = stage_jacobians, static, step_out
        self.stale_jacobian = stale_jacobian  # (the Jacobian's time is not the step's)

    def attempt(self, matrices, guess):
        return self.step(guess, matrices[6])

    def kept(self):
        return self.stale_jacobian

    def failed(self, result):
        return result[self.out["outcome"]] != 0

    def evaluations(self, result):
        return result[self.out["evaluations"]]

    def refresh(self, matrices):
        import casadi

        t, h, u, p = matrices[:4]
        nnz, m = len(self.engine.rows), self.engine.m
        out = self.refresh_function(casadi.vertcat(t, u, p, h))
        return (t, h, u, p, out[:nnz], self.sign_det(out[nnz : nnz + m * m]), out[nnz + m * m :])

    def usable(self, matrices):
        import casadi

        return casadi.logic_not(unusable(casadi, matrices[6], self.static))

    def check_stages(self, matrices):
        """The iteration matrix's sign at each stage of the start value, against the last fresh one's."""
        import casadi

        t, h, u, p, _, sign, _ = matrices
        engine = self.engine
        s, nnz = engine.s, len(engine.rows)
        values = self.stage_jacobians(casadi.vertcat(t, h, casadi.repmat(u, s, 1), p))
        sparse = self.static is not None
        chain = [sign] + [
            self.sign_det(
                iteration_matrix(casadi, values[i * nnz : (i + 1) * nnz], engine.rows, engine.cols, engine, sparse)
            )
            for i in range(s)
        ]
        return sum(formulas.sign_flip(chain[i], chain[i + 1]) for i in range(s)) > 0


def state_layout(s: int, n: int, D: int, nnz: int, size_inverse: int) -> Layout:
    """The carried state: the :data:`.sequence.SCALARS`, then ``u``, the last step's ``nodes``, ``f0``, ``J``'s
    nonzeros and the packed ``inverse``."""
    arrays = (("u", D), ("nodes", (s + 1) * D), ("f0", n), ("J", nnz), ("inverse", size_inverse))
    return Layout(*SCALARS.names, *arrays)


def record_layout(s: int, D: int) -> Layout:
    """One attempt's record: :data:`.sequence.RECORD`, then the start value and the stages (``nodes``)."""
    return Layout(*RECORD, ("nodes", (s + 1) * D))


class CompiledRun:
    """The stepper's side of :func:`run_function`: its state packed in, the attempts' steps and
    statistics written back as :meth:`.step.Stepper.accept` and the controller would have."""

    def __init__(self, function, engine):
        s, D = engine.s, engine.D
        self.buffered = lend(self, function, inputs=2)  # (its state stays in it between advances)
        self.layout = state_layout(s, engine.n, D, len(engine.rows), engine.packed_size())
        self.record = record_layout(s, D)
        self.attempts = (function.nnz_out(0) - self.layout.size) // self.record.size
        self.shifts = len(engine.transform.shifts(1.0))  # LU decompositions a factorisation counts

    def advance(self, stepper, carried: dict, settings: dict):
        """Up to :attr:`attempts` attempts from the controller's scalars ``carried``
        (:data:`.sequence.CONTROLLER`) with ``settings`` (:data:`.sequence.SETTINGS`): ``(carried after,
        how the run ended)``; the stepper's state and statistics move with the accepted steps."""
        L, t = self.layout, carried["t"]
        state = self.buffered.inputs[0]
        previous, factors, jac = stepper._previous, stepper.factors, stepper._jac
        scalars = {
            **carried,
            "h_old": previous[0] if previous is not None else 0.0,
            "eta": float(stepper.eta[0]),
            "first": float(carried["first"]),
            "rejected_last": float(carried["rejected_last"]),
            "jac_kept": float(jac is not None),
            "t_jac": jac[1] if jac is not None else 0.0,
            "factors_h": factors.h if factors is not None and factors.inverse is not None else 0.0,
            "det_sign": float(stepper._det_sign[0]) if stepper._det_sign is not None else 0.0,
            "t_det": stepper._det_time,
            "attempts": 0.0,
            "active": 1.0,
            "code": FULL,
        }
        state[: SCALARS.size] = SCALARS.pack(**scalars)
        u = stepper.state()[0]
        state[L["u"]] = u
        if previous is not None:
            state[L["nodes"]] = stepper._previous_nodes
        else:  # (u at every node, written in place: np.tile made a copy first)
            state[L["nodes"]].reshape(stepper.s + 1, len(u))[:] = u
        state[L["f0"]] = stepper.start_f(t)[0]
        if jac is not None:
            state[L["J"]] = jac[0]
        if scalars["factors_h"]:
            state[L["inverse"]] = factors.inverse
        inputs = self.buffered.inputs[1]
        inputs[: SETTINGS.size] = SETTINGS.pack(**settings)
        inputs[SETTINGS.size :] = stepper.engine.p
        try:
            with captured_output():  # (casadi prints a failing call's inputs, all nested functions', before it raises)
                out = self.buffered.evaluate(copy=False)  # (_write_back copies what it keeps)
        except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
            raise
        except RuntimeError:
            # a factorisation inside failed (LAPACK refuses an exactly singular matrix): the next attempt
            # on Python's path, which factors with scipy and names why it is singular
            return carried, HANDBACK
        stepper.stats["compiled_runs"] += 1
        stats, packed = stepper.stats, 8 * stepper.engine.packed_size()  # (the factors in the run's state)
        stats["factor_bytes"] = max(stats["factor_bytes"], packed)
        return self._write_back(stepper, out)

    def _write_back(self, stepper, out):
        L, stats, engine = self.layout, stepper.stats, stepper.engine
        s, D = stepper.s, stepper.n + stepper.m
        R = self.record
        v = dict(zip(SCALARS.names, out[: SCALARS.size].tolist(), strict=True))
        carried = {name: v[name] for name in CONTROLLER}
        carried["first"], carried["rejected_last"] = bool(v["first"]), bool(v["rejected_last"])
        ran = int(v["attempts"])  # (the first records: those after them hold nothing of this call in machine code)
        records = out[L.size : L.size + ran * R.size].reshape(ran, R.size)  # (a view of the run's output buffer)
        held = records[:, R["ran"]] > 0
        # (the counters alone taken out of the records, and the accepted steps' times and nodes alone: the rows
        # whole were copied twice before, ~70 kB each at 20 pendulums, s = 3)
        counts = records[held, : len(RECORD)]
        if not len(counts):  # (the first attempt handed back: nothing moved)
            return carried, int(v["code"])
        sums = dict(zip(RECORD, counts.sum(axis=0).tolist(), strict=True))  # (one numpy call)
        sequence.add_statistics(stats, sums, self.shifts)
        stats["max_newton_iterations"] = max(stats["max_newton_iterations"], int(counts[:, R["iterations"]].max()))
        if sums["refreshed"] and stepper.m:
            stepper._det_sign, stepper._det_time = np.array([v["det_sign"]]), v["t_det"]
        accepted = held & (records[:, R["accepted"]] > 0)
        k = int(np.count_nonzero(accepted))
        if k:
            # (copies, of the output buffer that the next call overwrites: the records' other entries are not
            # kept, as step_record_bytes counts)
            nodes = records[accepted, R["nodes"]].reshape(1, k, s + 1, D)  # (the start value, then the stages)
            stepper.take_steps(
                records[accepted, R["t"]],
                records[accepted, R["h"]],
                records[accepted, R["t_next"]],
                nodes,
                out[L["f0"]][None].copy(),
            )
        stepper.eta = np.array([v["eta"]])
        if v["code"] == FINISHED:  # (the integration is over: no attempt reads the Jacobian or its factors;
            stepper._jac = stepper.factors = None  # building their Factors took 5 us of the pendulum's ~330 us)
            return carried, FINISHED
        stepper._jac = (out[L["J"]].copy(), v["t_jac"]) if v["jac_kept"] else None
        factors_h = v["factors_h"]
        stepper.factors = engine._packed_factors(out[L["inverse"]].copy(), factors_h) if factors_h else None
        return carried, int(v["code"])
