"""radau's casadi functions: the stage residual and Jacobians, the fused Newton iteration, the
inverses of the shifted systems, and one compiled adaptive attempt; and their machine code (``jit``).

On one trajectory in float64 (the casadi engine, dense systems) Python would otherwise run once
per Newton iteration: a residual call, then norms, divergence and convergence tests on arrays of a
few elements, each a numpy call of a few microseconds.  :func:`step_function` makes the whole
attempt of an adaptive step, up to the error norm that the controller reads, one casadi function
of the step's scalars, the last step's collocation polynomial and the inverses of the transformed
systems (bound to the function when they are factored), so that Python runs once per step.

It follows :meth:`.newton.Newton.simplified` (the RADAU5 controller's policy) and
:meth:`.error.ErrorEstimate.norm` exactly: the same iterates, tests and counts.  Which is written
where: the Newton iteration's passes once in :mod:`.iteration` (:func:`newton_tests` is one pass
on casadi SX, on the state :class:`.iteration.NewtonState`), the tests, the start guess's rate and
the error norm once in :mod:`.formulas`; what is here alone is the attempt's graph around them (the
start guess, the increments through the packed inverses, the unrolled passes, the error
estimate's systems).  Its packed input and output are named in one place (:func:`step_layouts`).
Any outcome but convergence (non-finite values, divergence, slow contraction, the iteration limit)
reports its code; :meth:`.step.Stepper.compiled_attempt` retries as the general path does and words
the failure, and hands non-finite values to the general path, which names where they arose.

The iteration is unrolled ``max_newton_iterations + 2`` times, each a casadi switch that runs one
pass while the state is active and passes it through unchanged after (the extra passes check a
one-iteration convergence and evaluate ``f`` at the final stages).
"""

from __future__ import annotations

import functools
import weakref
from typing import NamedTuple

import numpy as np
from daemodel.backends.radau import formulas
from daemodel.backends.radau.formulas import CASADI
from daemodel.backends.radau.increments import DenseInverses, inverse_size, transformed_increment
from daemodel.backends.radau.iteration import NewtonState, newton_pass, newton_start
from daemodel.backends.radau.kernel import transform_calls

from daemodel.cache import Build, cached_library, compiler_version
from daemodel.collocation import extrapolation_polynomial, horner
from daemodel.compiling.codegen import casadi_jacobian

# Outcome codes of the compiled step (Stepper._compiled_try words them as the general path does):
# .formulas.newton_iteration's, the same for both.
CONVERGED, NON_FINITE, DIVERGING, SLOW, NOT_CONVERGED = (
    formulas.CONVERGED, formulas.NON_FINITE, formulas.DIVERGING, formulas.SLOW, formulas.NOT_CONVERGED,
)  # fmt: skip
# The compiled step's scalars, in front of its packed input's arrays (see step_layouts).
STEP_SCALARS = ("t", "h", "ratio", "eta", "newton_tol", "first", "rtol", "atol")
# Its results, in front of its packed output's arrays.
STEP_RESULTS = ("outcome", "iterations", "evaluations", "theta", "eta", "error_norm")


class Layout:
    """Named parts of one packed vector, in order: where each sits, a position (a scalar) or a slice
    (``(name, size)``, an array), written in one place for the function that reads the vector and
    for the code that packs it (casadi functions take and return packed vectors: a call costs ~20 us
    per argument through argument conversion)."""

    def __init__(self, *parts):
        self.names, self.where, offset = [], {}, 0
        for part in parts:
            name, size = (part, None) if isinstance(part, str) else part
            self.where[name] = offset if size is None else slice(offset, offset + size)
            self.names.append(name)
            offset += 1 if size is None else size
        self.size = offset

    def __getitem__(self, name: str):
        return self.where[name]

    def read(self, vector) -> dict:
        """Each part of ``vector`` (numpy or casadi) by its name."""
        return {name: vector[where] for name, where in self.where.items()}

    def pack(self, **values) -> list:
        """The parts in their order (every name given, no other)."""
        if values.keys() != self.where.keys():
            raise KeyError(f"expected the parts {self.names}; got {sorted(values)}")
        return [values[name] for name in self.names]


def step_layouts(s: int, n: int, D: int, P: int) -> tuple[Layout, Layout]:
    """The compiled step's packed input (:data:`STEP_SCALARS`, the last step's start value and stages
    ``nodes``, f at the step's start ``f0``, the parameters ``p``) and output (:data:`STEP_RESULTS`,
    the stages ``W`` and f at the stages ``F``)."""
    inputs = Layout(*STEP_SCALARS, ("nodes", (s + 1) * D), ("f0", n), ("p", P))
    return inputs, Layout(*STEP_RESULTS, ("W", s * D), ("F", s * n))


# The iteration's state in the compiled step: the stages W (D, s), f at them F (n, s), then the scalars
# of NEWTON_STATE, .iteration's NewtonState but `iterating` (one trajectory: mode == ITERATING).
NEWTON_STATE = tuple(name for name in NewtonState._fields if name != "iterating")
ITERATION = ("W", "F", *NEWTON_STATE)
# newton_tests' input: the increment's norm, the state's scalars but active (a pass runs where it is),
# Newton's tolerance; its output: whether the pass iterated (the increment taken), the state after it.
NEWTON_BEFORE = Layout("norm", *(name for name in NEWTON_STATE if name != "active"), "tol")
NEWTON_AFTER = Layout("iterate", *NEWTON_STATE)


def newton_tests(iterations: int, geometric: bool = False):
    """One pass of the simplified Newton iteration on its scalars, :func:`.iteration.newton_pass` (the one
    :meth:`.newton.Newton.simplified` runs) on casadi SX symbols: an SX function from ``before``
    (:data:`NEWTON_BEFORE`) to ``after`` (:data:`NEWTON_AFTER`); ``geometric``: the contraction's mean
    (:func:`.formulas.geometric_contraction` of the stages)."""
    import casadi

    x = casadi.SX.sym("before", NEWTON_BEFORE.size)
    v = NEWTON_BEFORE.read(x)
    state = NewtonState(
        **{name: v[name] for name in NEWTON_STATE if name != "active"},
        active=1,
        iterating=v["mode"] == formulas.ITERATING,
    )
    found = newton_pass(CASADI, state, v["norm"], v["tol"], iterations, geometric=geometric)
    after = found.state._asdict()
    out = NEWTON_AFTER.pack(iterate=found.iterate, **{name: after[name] for name in NEWTON_STATE})
    return casadi.Function("newton_tests", [x], [casadi.vertcat(*out)], ["before"], ["after"])


def step_function(f, residual, engine, iterations: int, e: np.ndarray, error_weights: np.ndarray, solver=None):
    """The casadi function of one adaptive attempt (see the module docstring).

    Inputs (:func:`step_layouts`): :data:`STEP_SCALARS` with ``ratio`` = h / h_old, ``nodes`` the
    last accepted step's start value and stages (the start value s+1 times at the first step: a
    constant guess), ``f0`` f at the step's start, ``p``; and the packed inverses
    (:func:`inverse_size`).  ``e`` (s,): the error estimate's ``bhat - b``.  ``error_weights`` (m,):
    each algebraic variable's index k, its error weighed by ``h^(k-1)``.

    Output (:func:`step_layouts`): :data:`STEP_RESULTS` (the outcome, Newton's iterations, the
    residual evaluations, theta, eta, the error norm), the stages ``W`` (s D) and f at them ``F`` (s n).
    """
    import casadi

    s, n, D, tr = engine.s, engine.n, engine.D, engine.transform
    inputs, outputs = step_layouts(s, n, D, engine.p.size)
    x = casadi.MX.sym("x", inputs.size)
    solver = solver or DenseInverses(tr, D)
    inverse = casadi.MX.sym("inverse", solver.size)
    v = inputs.read(x)
    t, h, ratio, tol, first = v["t"], v["h"], v["ratio"], v["newton_tol"], v["first"]
    rtol, atol = v["rtol"], v["atol"]
    prev = casadi.reshape(v["nodes"], D, s + 1)  # column j: node j
    f0, p = v["f0"], v["p"]
    u_n = prev[:, s]  # the last stage of the last step (c_s = 1): this step's start value
    y_n = u_n[:n]

    # start guess: the last step's collocation polynomial at the new stages, by the same Horner
    # evaluation as the general path (the extrapolation is ill-conditioned at large ratios: another
    # formula's rounding changed Newton's iteration count and so the step sequence)
    L = horner([casadi.DM(C) for C in extrapolation_polynomial(engine.tableau.c)], ratio)  # (s, s+1)
    W0 = casadi.mtimes(prev, L.T)  # (D, s)
    high = formulas.high_index_columns(s, n, error_weights)  # (index-2/3 z: blind to their stages' pattern)
    if high is not None:
        blind = extrapolation_polynomial(engine.tableau.c, formulas.high_index_pattern(engine.tableau.A))
        W0[high, :] = casadi.mtimes(prev[high, :], horner([casadi.DM(C) for C in blind], ratio).T)

    index_w = formulas.index_weights(CASADI, h, n, error_weights - 1)
    scale = casadi.repmat(formulas.error_scale(atol, rtol, casadi.fabs(u_n), index_w), 1, s)

    # one iteration on the state (ITERATION), or none where it is no longer active
    W_s = casadi.MX.sym("W", D, s)
    state_in = {"W": W_s, "F": casadi.MX.sym("F", n, s), **{name: casadi.MX.sym(name) for name in NEWTON_STATE}}
    fixed = [t, h, y_n, p, scale, tol, inverse]
    fixed_syms = [
        casadi.MX.sym(name, e.sparsity())
        for name, e in zip(("t", "h", "y_n", "p", "scale", "tol", "inverse"), fixed, strict=True)
    ]
    ts, hs, ys, ps, scs, tols, invs = fixed_syms
    tests = newton_tests(iterations, formulas.geometric_contraction(s))
    scalars = [state_in[name] for name in NEWTON_BEFORE.names[1:-1]]
    out = residual(casadi.vertcat(ts, hs, ys, casadi.vec(W_s), ps))
    stage_f = casadi.reshape(out[s * D :], n, s)
    if getattr(solver, "machine", False):
        # in machine code on static factors: the transforms, the increment and its norm as loops in C
        # (.kernel.transform_calls), the same operations in the same order as the MX below, whose copies,
        # slices and transposes between them took 27 % of the chain of 20 pendulums' run at rtol 1e-4
        # (46,000 instructions an iteration; the run 14.2 -> 12.9 million instructions a solve)
        transform_in, transform_out = transform_calls(tr, n, D)
        blocks = transform_in(out, hs)
        blocks = [blocks] if len(tr.blocks) == 1 else blocks
        solved = [solver.stacked(casadi, invs, index, rhs) for index, rhs in enumerate(blocks)]
        dW, norm = transform_out(*solved, casadi.vec(scs))
        dW = casadi.reshape(dW, D, s)
    else:
        dW = transformed_increment(casadi, casadi.reshape(out[: s * D], D, s), hs, invs, tr, n, D, solver)
        norm = CASADI.rms(dW / scs)
    # the tests on the scalars in one SX function (an MX operation costs ~40 ns on casadi's virtual
    # machine, an SX one ~2: a pendulum step of 3 iterations 23.6 -> 19.7 us)
    before = NEWTON_BEFORE.pack(norm=norm, tol=tols, **dict(zip(NEWTON_BEFORE.names[1:-1], scalars, strict=True)))
    after = NEWTON_AFTER.read(tests(before=casadi.vertcat(*before))["after"])
    state_out = dict(after, W=casadi.if_else(after["iterate"], W_s + dW, W_s), F=stage_f)
    symbols = [*(state_in[name] for name in ITERATION), *fixed_syms]
    one = casadi.Function("iteration", symbols, [state_out[name] for name in ITERATION])
    idle = casadi.Function("idle", symbols, [state_in[name] for name in ITERATION])
    switch = casadi.Function.if_else("maybe_iterate", one, idle)

    eta0 = formulas.start_rate(CASADI, v["eta"], np.finfo(float).eps)
    start = newton_start(eta0, 0.0, 1.0)._asdict()
    state = dict(W=W0, F=casadi.MX.zeros(n, s), **{name: start[name] for name in NEWTON_STATE})
    state.update((name, float(value)) for name, value in state.items() if isinstance(value, (bool, int)))
    for _ in range(iterations + 2):  # (a failed check at k = 1 takes a pass more)
        state = dict(zip(ITERATION, switch(state["active"], *(state[name] for name in ITERATION), *fixed), strict=True))
    W, F, theta, eta, k, evaluations = (state[name] for name in ("W", "F", "theta", "eta", "k", "evaluations"))
    outcome = casadi.if_else(state["active"], NOT_CONVERGED, state["outcome"])

    # the embedded error estimate (.error's ErrorEstimate.norm: local, refiltered)
    gamma0 = tr.gamma0
    quadrature = casadi.mtimes(F, casadi.DM(e))
    zeros = casadi.MX.zeros(D - n)
    err = solver.error(casadi, inverse, formulas.error_rhs(CASADI, quadrature, gamma0, f0, zeros))
    u_new = W[:, s - 1]
    w = formulas.error_scale(atol, rtol, casadi.fmax(casadi.fabs(u_n), casadi.fabs(u_new)), index_w)

    def refiltered():
        f1 = f(casadi.vertcat(t, u_n + err, p))
        return solver.error(casadi, inverse, formulas.error_rhs(CASADI, quadrature, gamma0, f1, zeros))

    error_norm = formulas.error_norm(CASADI, err, w, first, refiltered)
    results = dict(outcome=outcome, iterations=k, evaluations=evaluations, theta=theta, eta=eta)
    out = outputs.pack(**results, error_norm=error_norm, W=casadi.vec(W), F=casadi.vec(F))
    return casadi.Function("radau_step", [x, inverse], [casadi.vertcat(*out)])


# C compilers tried for jit=True, in this order (the first on PATH compiles).
COMPILERS = ("cc", "gcc", "clang")
# Optimisation of the machine code: -O2 (-O1 compiles car axis's library 1.5x faster and solves 15-20 %
# slower; -O1 with -finline-small-functions -fstrict-aliasing 8-11 % slower); no fused multiply-adds (the
# loops of .kernel give the SX factors and solves bit for bit: a compiler may not contract a - b c); no
# errno (sqrt inline: it changes no value).
COMPILER_FLAGS = ("-O2", "-ffp-contract=off", "-fno-math-errno")
# With GCC, -O2's passes that cost compiling and no solve time on this code: the second instruction
# scheduling and partial redundancy elimination (tree and RTL), 12-15 % of the compiler's time on the Test
# Set problems' libraries, the same us per attempt (car axis, transistor amplifier, squeezer) and the same
# bits; without the vectorisers too would save 5 % more and cost 7 % of the transistor amplifier's attempts.
GCC_FLAGS = ("-fno-schedule-insns2", "-fno-tree-pre", "-fno-gcse")
# The most translation units a library's source is cut into and compiled at once (daemodel.translation_units;
# at most one per CPU this process may use, and about one per 20 kB of functions: car axis 5 at most).
COMPILE_UNITS = 8
# The stage residual inlines its s copies of the equations (SX) up to this many unknowns, the most that
# jit="auto" compiles (.backend.JIT_AUTO_MAX_SIZE): called as functions (MX) the machine code took 8-11 %
# longer a solve (car axis, the transistor amplifier; the same values bit for bit); above it, where
# casadi's virtual machine runs it, calls cost the same to evaluate and save building the copies
# (1.58 -> 0.36 s at 10^5 unknowns).
INLINED_RESIDUAL_MAX_SIZE = 200
# What a failed compile's message proposes.
JIT_FIX = "solve with jit=False (the same results to rounding, slower steps)"


class MachineCode(NamedTuple):
    """A function in machine code (:func:`machine_code`), and what the disk cache did to give it
    (:class:`daemodel.cache.Library`'s ``outcome``: "hit", "miss", "refused: ...", "not stored: ...")."""

    function: object
    outcome: str


def compiler_flags(compiler: str) -> tuple:
    """:data:`COMPILER_FLAGS`, and :data:`GCC_FLAGS` where ``compiler`` is not clang (``--version``'s
    first line, :func:`daemodel.cache.compiler_version`: GCC's, whose ``cc`` does not always say so)."""
    return COMPILER_FLAGS + (() if "clang" in compiler_version(compiler).lower() else GCC_FLAGS)


def find_compiler() -> str | None:
    """The absolute path of the first of :data:`COMPILERS` on PATH, or None (absolute: the compiler runs
    inside a private temporary folder, where a relative PATH entry's ``bin/cc`` is not found).  Kept per
    value of PATH and working folder while the path found is still an executable file (a search of PATH
    took 90 us, twice in each of the wheelset's 2,700 solves and trial solves of its events)."""
    import os
    import shutil

    search = (os.environ.get("PATH", ""), os.getcwd())
    found = _FOUND_COMPILERS.get(search)
    if found is None or not os.access(found, os.X_OK):
        found = next((os.path.abspath(path) for path in map(shutil.which, COMPILERS) if path), None)
        if found is not None:
            _FOUND_COMPILERS[search] = found
    return found


# find_compiler's compilers found, by the value of PATH and the working folder
_FOUND_COMPILERS: dict[tuple[str, str], str] = {}


def machine_library(functions: dict, compiler: str, kernel: str = "", kernel_names=(), what: str = "", after: str = ""):
    """The casadi ``functions`` ({name: function}) compiled by ``compiler`` into one library, through
    the disk cache of compiled libraries (:mod:`daemodel.cache`): the C source of casadi's code
    generator for all of them (a function they share, the stage residual, written once), after
    ``kernel``, C that the source needs and whose own functions ``kernel_names`` the library offers
    too (:func:`.kernel.kernel_source`: the static factors' loops, which the calls of
    :func:`.kernel.solve_call` inside ``functions`` reach), and before ``after``, C that calls them
    and whose own functions are among ``kernel_names`` too (:func:`.loop.run_loop_source`), compiled
    with :func:`compiler_flags` in a private temporary folder (cut into up to :data:`COMPILE_UNITS`
    translation units compiled at once, :mod:`daemodel.translation_units`), stored and loaded with
    ``casadi.external``; or loaded from the cache where an earlier process stored it.  One library
    for everything a solve runs in machine code.

    Returns :class:`daemodel.cache.Library`: ``functions`` by the names given (and ``kernel_names``),
    and what the cache did.  Raises :class:`~daemodel.errors.CompileError` with the compiler's
    message where it fails.
    """
    import casadi

    generator = casadi.CodeGenerator("daemodel_jit")
    for name, function in functions.items():
        if function.name() == name:  # (no other calls it: its own code, without a wrapper that copies its outputs)
            generator.add(function)
            continue
        inputs = function.mx_in()  # (an SX function makes new symbols on every call)
        # (a call, never inlined: a function that another of them calls too, the step that the run calls,
        # is then written once; inlined, car axis's library held the step twice, 5,891 lines)
        generator.add(casadi.Function(name, inputs, function.call(inputs, False, True)))
    what = what or f"radau's machine code: compiling the step of {next(iter(functions.values())).name()!r}"
    build = Build(compiler, compiler_flags(compiler), what, JIT_FIX, libraries=("-lm",), units=COMPILE_UNITS)
    return cached_library(kernel + generator.dump() + after, [*functions, *kernel_names], build)


def machine_code(function, compiler: str) -> MachineCode:
    """``function`` compiled to machine code by ``compiler`` (:func:`machine_library` of it alone),
    and what the disk cache did (:class:`daemodel.cache.Library`'s ``outcome``).  Raises
    :class:`~daemodel.errors.CompileError` with the compiler's message where it fails."""
    name = function.name() + "_machine_code"
    code = machine_library({name: function}, compiler)
    return MachineCode(code.functions[name], code.outcome)


def dense_jacobian(casadi, rows: np.ndarray, cols: np.ndarray, values, D: int):
    """The dense (D, D) matrix of the nonzeros ``values`` at ``(rows, cols)`` (casadi's triplet order)."""
    if not len(rows):  # f and g depend on no unknown (f = f(t)): casadi refuses an empty value vector
        return casadi.MX.zeros(D, D)
    return casadi.densify(casadi.MX(casadi.Sparsity.triplet(D, D, rows.tolist(), cols.tolist()), values))


def inverse_function(rows: np.ndarray, cols: np.ndarray, engine):
    """The casadi function of the packed inverses (:func:`inverse_size`) from ``[h, J's nonzeros]``.

    A complex system ``(a + i b) M - J`` is inverted as the real ``[[a M - J, -b M], [b M, a M - J]]``
    of twice its size (casadi computes in real numbers); LAPACK's LU (casadi's ``lapacklu``) factors
    each.  A singular system makes the call fail: the caller then factors with scipy, which names it.
    """
    import casadi

    n, D, tr = engine.n, engine.D, engine.transform
    x = casadi.MX.sym("x", 1 + len(rows))
    h = x[0]
    J = dense_jacobian(casadi, rows, cols, x[1:], D)
    M = casadi.DM(np.diag(np.r_[np.ones(n), np.zeros(D - n)]))
    identity = casadi.DM.eye(D)
    packed, real_block = [], None
    for _, lam in tr.blocks:
        a, b = lam.real / h, lam.imag / h
        if lam.imag == 0:
            packed.append(casadi.vec(casadi.solve(a * M - J, identity, "lapacklu")))
            real_block = (lam.real, packed[-1])
            continue
        big = casadi.blockcat([[a * M - J, -b * M], [b * M, a * M - J]])
        both = casadi.solve(big, casadi.vertcat(identity, casadi.DM.zeros(D, D)), "lapacklu")
        packed += [casadi.vec(both[:D, :]), casadi.vec(both[D:, :])]
    error = 1.0 / tr.gamma0
    if real_block is not None and abs(real_block[0] - error) <= 1e-12 * error:
        packed.append(real_block[1])  # s odd: the error estimate's system is the real block
    else:
        packed.append(casadi.vec(casadi.solve(error / h * M - J, identity, "lapacklu")))
    return casadi.Function("inverses", [x], [casadi.vertcat(*packed)])


def refresh_function(jacobian, inverses, rows: np.ndarray, cols: np.ndarray, engine, sparse: bool = False):
    """The casadi function of a fresh Jacobian at the step's start, in one call: from ``[t, y, z, p, h]``,
    ``[J's nonzeros, the algebraic variables' iteration matrix (m, m) column-major, the packed inverses]``.

    The iteration matrix is :meth:`CasadiEngine.z_matrix_sign`'s (rows ``g_z`` at index 1, ``g_y f_z``
    at index 2; ``sparse``: from J's nonzeros, see :func:`iteration_matrix`); ``jacobian`` and
    ``inverses`` are the engine's functions of the nonzeros (``inverses``: or its packed static factors).
    """
    import casadi

    x = casadi.MX.sym("x", jacobian.nnz_in(0) + 1)
    values = casadi.vec(jacobian(x[:-1]))  # (a Jacobian without nonzeros comes as 1 x 0)
    z_matrix = iteration_matrix(casadi, values, rows, cols, engine, sparse)
    return casadi.Function("refresh", [x], [casadi.vertcat(values, z_matrix, inverses(casadi.vertcat(x[-1], values)))])


def iteration_matrix(casadi, values, rows: np.ndarray, cols: np.ndarray, engine, sparse: bool = False):
    """The algebraic variables' iteration matrix (m, m), column-major, of the Jacobian's nonzeros
    ``values``: :meth:`CasadiEngine.z_matrix_sign`'s rows, ``g_z`` at index 1, ``g_y f_z`` at index 2.
    ``sparse``: the product on J's nonzeros (at 100-200 unknowns the dense one costs 30-250 us on
    casadi's virtual machine), the result dense."""
    n, D = engine.n, engine.D
    m = D - n
    if sparse and len(rows):
        J = casadi.MX(casadi.Sparsity.triplet(D, D, rows.tolist(), cols.tolist()), values)
    else:
        J = dense_jacobian(casadi, rows, cols, values, D)
    index2 = engine.index2_rows
    coupled = casadi.mtimes(J[n:, :n], J[:n, n:]) if index2.any() else None
    z_rows = [coupled[i, :] if index2[i] else J[n + i, n:] for i in range(m)]
    return casadi.vec(casadi.densify(casadi.vertcat(*z_rows))) if m else casadi.MX(0, 1)


def lend(owner, function, inputs: int = 1) -> Buffered:
    """A :class:`Buffered` of ``function`` for ``owner`` alone: one an owner gone before left (:data:`_LENDABLE`),
    else a new one; taken back when ``owner`` is gone.  A Buffered keeps what was written into its inputs, so
    two owners alive never share one (each binds its own factors' inverses); an engine was made for each solve
    with ~9 of them at ~17 us each, 2,700 times in the wheelset's events' trial solves.  For an owner that
    keeps its Buffered to itself (its inputs are zeros, as a new one's; its outputs are what the last call
    wrote, which every call overwrites: zeroing the compiled run's, 1 MB at 200 unknowns and s = 5, was 3 %
    of a solve).  ``function``: a casadi function, or one that names the kind bound to it (its ``buffered``)."""
    free = _LENDABLE.get(function)
    parts = free.get(inputs) if free is not None else None
    try:  # (none free, or another thread took the last one since a check: a new one, not IndexError)
        state = parts.pop() if parts is not None else None
    except IndexError:
        state = None
    kind = getattr(function, "buffered", Buffered)  # (a function of sliced inputs: .stencil.Sliced)
    if state is not None:
        buffered = kind.__new__(kind)
        buffered.__dict__.update(state, function=function)
        for values in buffered.inputs:  # (zeros, as a new one's: nothing of its last owner)
            values[:] = 0.0
    else:
        buffered = kind(function, inputs)
    lent = _LENT.get(owner)
    if lent is None:  # (one finalizer an owner: ~3 us each)
        lent = _LENT[owner] = []
        weakref.finalize(owner, _give_back, lent)
    state = dict(buffered.__dict__)
    del state["function"]  # (the pool's key)
    lent.append((weakref.ref(function), inputs, state))
    return buffered


def _give_back(lent: list) -> None:
    for function, inputs, state in lent:
        function = function()
        if function is not None:
            _LENDABLE.setdefault(function, {}).setdefault(inputs, []).append(state)


# Buffered functions' parts free to lend again (:func:`lend`), by casadi function (gone with it) and inputs;
# and what each owner alive was lent, given back when it is gone.
_LENDABLE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_LENT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


class Buffered:
    """A casadi function of one dense vector, evaluated on bound numpy buffers (casadi's
    FunctionBuffer: ~3 us a call, against ~40-100 us through argument conversion)."""

    def __init__(self, function, inputs: int = 1, input_of: Buffered | None = None, output: np.ndarray | None = None):
        """``input_of``: a Buffered whose first input this one reads, not a copy of it (two functions of the same
        packed input called one after the other, each call writing all of it: :meth:`packed`; the residual's and the
        stages' f: 4.4 MB at 10^5 unknowns, s = 5); ``output``: the float64 array its output is written to."""
        # inputs after the first stay bound between calls: write them through ``inputs[k][:]``
        sizes = [function.nnz_in(k) for k in range(inputs)]
        self.name = function.name()
        if input_of is not None and input_of._inputs.size != sizes[0]:
            raise ValueError(
                f"casadi function {self.name} takes {sizes[0]} inputs; {input_of.name} {input_of._inputs.size}"
            )
        if output is not None and (
            output.dtype != float
            or output.shape != (function.nnz_out(0),)
            or not (output.flags.c_contiguous and output.flags.writeable)
        ):
            raise ValueError(
                f"casadi function {self.name} gives {function.nnz_out(0)} outputs, not {output.shape} "
                "(into a writable contiguous float64 array)"
            )
        self.inputs = [
            input_of._inputs if k == 0 and input_of is not None else np.zeros(size) for k, size in enumerate(sizes)
        ]
        self._inputs = self.inputs[0]
        self._outputs = np.zeros(function.nnz_out(0)) if output is None else output
        self._buffer, self._evaluate = function.buffer()
        for k, values in enumerate(self.inputs):
            self._buffer.set_arg(k, memoryview(values))
        self._buffer.set_res(0, memoryview(self._outputs))
        self.function = function

    def __call__(self, values: np.ndarray) -> np.ndarray:
        self._inputs[:] = values
        return self.evaluate()

    def packed(self, *parts, copy: bool = True) -> np.ndarray:
        """The outputs for the input ``np.concatenate(parts)``, written part by part into the input buffer
        without making it (at 10^5 unknowns and s = 5 the residual's is 4.4 MB a call, which numpy asks the
        kernel to back with huge pages: their clearing was ~15 % of a solve's CPU); ``copy``: as :meth:`evaluate`'s."""
        x, at = self._inputs, 0
        for part in parts:
            size = np.size(part)
            x[at : at + size] = np.ravel(part)
            at += size
        if at != x.size:
            raise ValueError(f"casadi function {self.name} takes {x.size} inputs; the parts hold {at}")
        return self.evaluate(copy)

    def evaluate(self, copy: bool = True) -> np.ndarray:
        """The outputs for the inputs as they are in ``inputs`` (written in place by the caller); with
        ``copy=False`` the output buffer itself, which the next call overwrites (for a caller that copies
        what it keeps: the compiled run's 100 attempts' records are 330 kB at 100 unknowns)."""
        self._evaluate()
        if self._buffer.ret() != 0:
            raise RuntimeError(f"casadi function {self.name} failed (return code {self._buffer.ret()})")
        return self._outputs.copy() if copy else self._outputs


def casadi_functions(compiled, tableau, stencil=None):
    """casadi functions of the casadi engine (cached on the compiled model, per s).

    Each takes one packed vector and returns one (a call costs ~20 us per argument): ``f`` of
    ``[t, y, z, p]``; the stage residual (the equations of
    :func:`daemodel.collocation.stage_residual`) of ``[t, h, y_n, W, p]``, ``W`` stage by stage
    ``[Y_i, Z_i]``, returning ``[R (stage by stage [F_i, G_i]), f at the stages]``; the Jacobian's
    nonzeros at ``[t, y, z, p]`` and at every stage of ``[t, h, W, p]``; its pattern (rows, cols).
    ``stencil``: functions ``(t, x, z, p) -> (f, g)``, of the stage residual and of the Jacobian's nonzeros (or
    None) that replace the model's own (above :data:`INLINED_RESIDUAL_MAX_SIZE` unknowns: :mod:`.stencil`, the
    same bits in C); with its Jacobian the model's whole casadi graph (:meth:`.CompiledDAE.casadi_dae`: 89 MB
    kept at 10^5 unknowns of reaction-diffusion, 280 MB while it is made) is not made.
    """
    import casadi

    if stencil is not None and stencil[2] is not None:
        from daemodel.compiling.runs import runs_jacobian_layout

        n, m, P = len(compiled.states), len(compiled.algebraics), len(compiled.parameters)
        packed = casadi.MX.sym("x", 1 + n + m + P)
        f = casadi.Function(
            "f", [packed], [stencil[0](*casadi.vertsplit(packed, [0, 1, 1 + n, 1 + n + m, packed.numel()]))[0]]
        )
        pattern = runs_jacobian_layout(compiled)[:2]  # (casadi_jacobian_pattern's: tests/compiling/test_runs.py)
        return (f, stencil[1], stencil[2], stage_jacobians(stencil[2], tableau, n + m, P), *pattern)
    dae = compiled.casadi_dae()
    t, x, z, p = dae["t"], dae["x"], dae["z"], dae["p"]
    s, n, D = tableau.stages, x.numel(), x.numel() + z.numel()
    model_pattern = compiled.casadi_jacobian_pattern()
    rows = np.bincount(model_pattern[0], minlength=D)  # (nonzeros per row)
    jac = casadi_jacobian(casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(x, z), rows)  # (dense rows apart)
    jacobian = casadi.Function("jacobian", [casadi.vertcat(t, x, z, p)], [jac.nz[:]])
    # (the model's own arrays where they are the same, not a second copy: 0.48 MB at 10^4 of reaction-diffusion)
    pattern = tuple(np.asarray(part, dtype=np.int64) for part in jac.sparsity().get_triplet())
    if all(np.array_equal(ours, model) for ours, model in zip(pattern, model_pattern, strict=True)):
        pattern = model_pattern
    stages = stage_jacobians(jacobian, tableau, D, p.numel())
    if stencil is not None:
        return (casadi.Function("f", [casadi.vertcat(t, x, z, p)], [dae["ode"]]), stencil[1], jacobian, stages,
                *pattern)  # fmt: skip
    f = casadi.Function("f", [t, x, z, p], [dae["ode"]])
    g = casadi.Function("g", [t, x, z, p], [dae["alg"]])
    A, c = tableau.A, tableau.c
    # above INLINED_RESIDUAL_MAX_SIZE the stage residual calls f and g s times (MX), as the stages' Jacobians
    # call the Jacobian's function: the same operations as s inlined copies, without building them
    kind = casadi.SX if D <= INLINED_RESIDUAL_MAX_SIZE else casadi.MX
    inputs = kind.sym("x", 2 + n + s * D + p.numel())
    t_r, h, y_n, W, p_r = (inputs[0], inputs[1], inputs[2 : 2 + n], inputs[2 + n : 2 + n + s * D],
                           inputs[2 + n + s * D :])  # fmt: skip
    times = [t_r + float(c[i]) * h for i in range(s)]
    Y = [W[i * D : i * D + n] for i in range(s)]
    Z = [W[i * D + n : (i + 1) * D] for i in range(s)]
    stage_f = [f(times[i], Y[i], Z[i], p_r) for i in range(s)]
    rows = []
    for i in range(s):
        quadrature = sum((float(A[i, j]) * stage_f[j] for j in range(s)), kind.zeros(n))
        rows += [Y[i] - y_n - h * quadrature, g(times[i], Y[i], Z[i], p_r)]
    residual = casadi.Function("residual", [inputs], [casadi.vertcat(*rows, *stage_f)])
    f = casadi.Function("f", [casadi.vertcat(t, x, z, p)], [dae["ode"]])
    return (f, residual, jacobian, stages, *pattern)


def stage_jacobians(jacobian, tableau, D: int, P: int):
    """:func:`casadi_functions`' fourth: a callable that makes (once) the casadi function of the stages'
    Jacobians, ``jacobian`` at every stage of ``[t, h, W, p]``.  Made where full Newton first needs it, not
    before: adaptive steps never do, and at 10^5 unknowns of reaction-diffusion (s = 5) it held 17 MB (casadi
    keeps a dense column's sparsity as its 2.25 x 10^6 row indices)."""

    @functools.cache
    def make():
        import casadi

        s, c = tableau.stages, tableau.c
        # the stages' Jacobians call the Jacobian's function s times (MX): the same operations as s inlined
        # copies, without building them (at 10^5 unknowns the copies took longer to build than a solve)
        packed = casadi.MX.sym("x", 2 + s * D + P)
        t_, h_, W_, p_ = packed[0], packed[1], packed[2 : 2 + s * D], packed[2 + s * D :]
        stages = [jacobian(casadi.vertcat(t_ + float(c[i]) * h_, W_[i * D : (i + 1) * D], p_)) for i in range(s)]
        return casadi.Function("stage_jacobians", [packed], [casadi.vertcat(*stages)])

    return make


def stage_f_function(compiled, tableau, stencil=None):
    """casadi function of f at the stages alone, from the residual's packed ``[t, h, y_n, W, p]``:
    ``[f(t + c_i h, Y_i, Z_i)]`` stage by stage, the residual's second output without its stage
    equations (the error estimate's evaluation after Newton has converged: 15 against 26 ms at 10^5
    unknowns of reaction-diffusion).  None up to :data:`INLINED_RESIDUAL_MAX_SIZE` unknowns, where the
    residual inlines its copies of f (its bits are those of this function's calls above only).
    ``stencil``: as :func:`casadi_functions`'; its stage f in C (:data:`.stencil.STAGE_F`) is returned."""
    import casadi

    s, n, P = tableau.stages, len(compiled.states), len(compiled.parameters)
    D = n + len(compiled.algebraics)
    if D <= INLINED_RESIDUAL_MAX_SIZE:
        return None
    if stencil is not None:  # (its own function in C: the same operations, g's rows not computed)
        return stencil[3]
    dae = compiled.casadi_dae()
    f = casadi.Function("f", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"]])
    inputs = casadi.MX.sym("x", 2 + n + s * D + P)
    t_r, h, W, p_r = inputs[0], inputs[1], inputs[2 + n : 2 + n + s * D], inputs[2 + n + s * D :]
    stage_f = [
        f(t_r + float(tableau.c[i]) * h, W[i * D : i * D + n], W[i * D + n : (i + 1) * D], p_r) for i in range(s)
    ]
    return casadi.Function("stage_f", [inputs], [casadi.vertcat(*stage_f)])


def stage_f_of(compiled, tableau, stencil=None):
    """:func:`stage_f_function`, built once per model, s and ``stencil``, or None where there is none."""
    key = ("casadi-radau-stage-f", tableau.stages, stencil is not None)
    return compiled.cached(key, lambda: stage_f_function(compiled, tableau, stencil))


def newton_step_function(residual, engine):
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
