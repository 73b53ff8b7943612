"""The equations ``f`` and ``g`` of a repeated stencil in C: one loop per run of one template (issue 44).

Above :data:`.compiled.INLINED_RESIDUAL_MAX_SIZE` unknowns the stage residual calls ``f`` and ``g`` at
every stage on casadi's virtual machine: at 10^5 unknowns of reaction-diffusion 3.6 of its 4.9 ms, ~1 ns
an operation (0.42 ms for f's 450,001 instructions, 0.30 for g's 350,001).  Compiling them whole would take
minutes; but a discretised PDE is a few templates repeated with shifted indices
(:func:`daemodel.compiling.runs.equation_runs`).  Here each template is a small casadi function in C
(casadi's code generator: the operations its virtual machine runs, in the same order), called in a loop
over each run with its leaves' pointers advanced by their strides, and the rows in no run (the
boundaries) a casadi function of their own in the same library; the source grows with the templates and
runs, not with the unknowns, so it compiles in a fraction of a second and the disk cache
(:mod:`daemodel.cache`) keeps it.  One function ``stencil_fg(t, x, z, p) -> (f, g)``, the same bits as the
model's ``f`` and ``g`` (``tests/backends/test_radau_stencil.py``), and ``stencil_jacobian(t, x, z, p)``, each
template's partial derivatives (casadi's AD of the template) at each row of its runs and the rest's Jacobian
(on casadi's virtual machine instead where it has more than :data:`REST_JACOBIAN_C_MAX` operations), which
taken in casadi's order (:func:`daemodel.compiling.runs.jacobian_layout`) are the model's Jacobian's nonzeros
(bit for bit where casadi colours the whole model's Jacobian forward, to rounding else: :data:`.runs.FORWARD`):
with them a solve does not make the model's whole casadi graph (at 10^5 unknowns of reaction-diffusion 89 MB
kept, 280 MB while it was made, and its Jacobian's function another 46 MB).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
from daemodel.backends.radau.compiled import (
    COMPILER_FLAGS,
    INLINED_RESIDUAL_MAX_SIZE,
    Buffered,
    casadi_functions,
    compiler_flags,
    find_compiler,
    stage_f_of,
)

# The names of the functions in the library: f and g, the stage residual, and the Jacobian's values.
NAME, RESIDUAL, JACOBIAN, STAGE_F = "stencil_fg", "stencil_residual", "stencil_jacobian", "stencil_stage_f"
# casadi's external functions' parameters.
SIGNATURE = "(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem)"
# Seconds the compiler may take (a few templates, their runs' table and the boundary rows).
STENCIL_COMPILE_TIMEOUT = 120.0
# With GCC, besides .compiled's flags: the library's own functions called directly and inlined (the templates
# are exported, so -fPIC called each through the PLT at every row, and casadi's sq too): the same operations.
GCC_STENCIL_FLAGS = ("-fno-semantic-interposition",)
# The most operations of the rest rows' Jacobian compiled in C; beyond, casadi's virtual machine evaluates it
# (boundary rows of products of 70 leaves: 139,338 operations, 3.3 MB of C that cc did not finish in 120 s,
# and the whole library, f, g and the residual with it, fell back to the virtual machine).
REST_JACOBIAN_C_MAX = 20_000


def _table(name: str, rows: list) -> str:
    """A C table of integers, one row per entry of ``rows`` (at least one row: C has no empty arrays)."""
    rows = rows or [[0]]
    body = ",\n".join("  {" + ", ".join(str(int(v)) for v in row) + "}" for row in rows)
    return f"static const casadi_int {name}[{len(rows)}][{len(rows[0])}] = {{\n{body}\n}};\n"


def _run_loop(k: int, count: int, leaves: int, function: str, start: str, output: str, advance: str = "") -> str:
    """C: the loop over the ``count`` runs of template ``k`` (``runs{k}``'s rows) calling ``function`` on each of
    their rows' ``leaves``; ``start``: the lines that begin a run (may ``continue``), ``output``: where a row's
    result goes (an expression of ``o`` and ``i``), ``advance``: the lines after a row."""
    size = max(leaves, 1)  # (C has no empty arrays: a row of a constant)
    return (
        f"  for (r = 0; r < {count}; r++) {{\n"
        f"    const casadi_int* q = runs{k}[r];\n"
        f"    const casadi_real* a[{size}];\n"
        f"    const casadi_real* in[{size}];\n"
        f"    casadi_int s[{size}];\n"
        "    casadi_real* out[1];\n"
        f"{start}"
        f"    for (j = 0; j < {leaves}; j++) {{\n"
        "      a[j] = arg[q[1 + 3 * j]] + q[2 + 3 * j];\n"
        "      s[j] = q[3 + 3 * j];\n"
        "    }\n"
        "    for (i = 0; i < q[0]; i++) {\n"
        f"      for (j = 0; j < {leaves}; j++) in[j] = a[j] + s[j] * i;\n"
        f"      out[0] = {output};\n"
        f"      if ({function}(in, out, iw, w, 0)) return 1;\n"
        f"{advance}"
        "    }\n"
        "  }\n"
    )


def stencil_source(runs) -> str:
    """The C of :data:`NAME` (casadi's external-function interface) for ``runs``
    (:class:`daemodel.compiling.runs.EquationRuns`): the templates and the rest by casadi's code
    generator, then the loops over the runs and the rest's rows put in place."""
    import casadi

    generator = casadi.CodeGenerator("daemodel_stencil", {"with_header": False})
    for template in (*runs.templates, *runs.derivatives):
        generator.add(template)
    # (the rest's rows and their Jacobian on the leaves they read, gathered by rest_gather: casadi's MX functions of
    # the whole inputs copied them into their work at each call, 0.4 MB at 10^5 unknowns a bound function)
    rest = runs.rest_inner[0]
    if rest is not None:
        generator.add(rest)
    if rest_jacobian_in_c(runs):
        generator.add(runs.rest_inner[1])
    n, m, P = runs.sizes
    out = [generator.dump(), "\n/* daemodel: runs of the templates (generated; numbers only) */\n"]
    # each template's runs: count, then per leaf its input, base and stride, then output, base and stride
    for k, template in enumerate(runs.templates):
        leaves = template.n_in()
        rows = [[r.count, *[v for j in range(leaves) for v in (r.inputs[j], r.bases[j], r.strides[j])],
                 r.output, r.out_base, r.out_stride] for r in runs.runs if r.template == k]  # fmt: skip
        out.append(_table(f"runs{k}", rows))
    f_rows, g_rows = (list(map(int, r)) for r in runs.rest_rows)
    out.append(_table("rest_out", [[0, i] for i in f_rows] + [[1, i] for i in g_rows]))
    out.append(_table("rest_leaves", runs.rest_leaves.tolist() or [[0, 0]]))
    counts = np.bincount(runs.rest_leaves[:, 0], minlength=4)
    rest_w = 0 if rest is None else rest.sz_w()
    rest_iw = 0 if rest is None else rest.sz_iw()
    rest_arg = 0 if rest is None else rest.sz_arg()
    rest_res = 0 if rest is None else rest.sz_res()
    out.append(
        f"#define N_X {n}\n#define N_Z {m}\n#define N_P {P}\n#define N_REST {len(f_rows) + len(g_rows)}\n"
        f"#define REST_W {rest_w}\n#define REST_IW {rest_iw}\n#define REST_ARG {max(rest_arg, 4)}\n"
        f"#define REST_RES {max(rest_res, 1)}\n#define N_LEAVES {len(runs.rest_leaves)}\n"
        f"#define LEAVES_T {counts[0]}\n#define LEAVES_X {counts[1]}\n#define LEAVES_Z {counts[2]}\n"
        "static const casadi_int sp_t[3] = {1, 1, 1};\n"
        "static const casadi_int sp_x[3] = {N_X, 1, 1};\n"
        "static const casadi_int sp_z[3] = {N_Z, 1, 1};\n"
        "static const casadi_int sp_p[3] = {N_P, 1, 1};\n"
        # the rest's leaves from the whole inputs (a null input: zeros, as casadi's), its inputs pointed at them
        "static void rest_gather(const casadi_real** arg, casadi_real* leaves, const casadi_real** local) {\n"
        "  casadi_int j;\n"
        "  for (j = 0; j < N_LEAVES; j++) {\n"
        "    const casadi_real* a = arg[rest_leaves[j][0]];\n"
        "    leaves[j] = a ? a[rest_leaves[j][1]] : 0;\n"
        "  }\n"
        "  local[0] = leaves; local[1] = leaves + LEAVES_T; local[2] = local[1] + LEAVES_X;\n"
        "  local[3] = local[2] + LEAVES_Z;\n"
        "}\n"
        f"int {NAME}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {{\n"
        "  casadi_int r, i, j;\n"
    )
    for k, template in enumerate(runs.templates):
        leaves, count = template.n_in(), sum(r.template == k for r in runs.runs)
        start = (f"    casadi_real* o = res[q[{3 * leaves + 1}]];\n    if (!o) continue;\n"
                 f"    o += q[{3 * leaves + 2}];\n")  # fmt: skip
        out.append(_run_loop(k, count, leaves, template.name(), start, f"o + q[{3 * leaves + 3}] * i"))
    if rest is not None:
        out.append(
            "  {\n"
            "    const casadi_real** rest_arg = arg + 4;\n"
            "    casadi_real** rest_res = res + 2;\n"
            "    rest_gather(arg, w + REST_W + N_REST, rest_arg);\n"
            "    rest_res[0] = w + REST_W;\n"
            "    if (rest_rows(rest_arg, rest_res, iw, w, 0)) return 1;\n"
            "    for (i = 0; i < N_REST; i++)\n"
            "      if (res[rest_out[i][0]]) res[rest_out[i][0]][rest_out[i][1]] = w[REST_W + i];\n"
            "  }\n"
        )
    out.append(
        "  return 0;\n}\n"
        f"casadi_int {NAME}_n_in(void) {{ return 4; }}\n"
        f"casadi_int {NAME}_n_out(void) {{ return 2; }}\n"
        f"const casadi_int* {NAME}_sparsity_in(casadi_int i) {{\n"
        "  return i == 0 ? sp_t : i == 1 ? sp_x : i == 2 ? sp_z : i == 3 ? sp_p : 0;\n}\n"
        f"const casadi_int* {NAME}_sparsity_out(casadi_int i) {{ return i == 0 ? sp_x : i == 1 ? sp_z : 0; }}\n"
        f"int {NAME}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {{\n"
        "  if (sz_arg) *sz_arg = 4 + REST_ARG;  /* (the rest's arguments after its own) */\n"
        "  if (sz_res) *sz_res = 2 + REST_RES;\n"
        "  if (sz_iw) *sz_iw = REST_IW;\n"
        "  if (sz_w) *sz_w = REST_W + N_REST + N_LEAVES;  /* (the rest's work, its outputs, its leaves) */\n"
        "  return 0;\n}\n"
    )
    out.append(jacobian_source(runs))
    return "".join(out)


def jacobian_source(runs) -> str:
    """The C of :data:`JACOBIAN` (after :func:`stencil_source`'s): ``(t, x, z, p)`` to the values of each
    template's partial derivatives at each row of its runs, in order, then the rest's Jacobian's nonzeros
    (the order :func:`daemodel.compiling.runs.jacobian_layout` reads them in)."""
    rest = runs.rest_inner[1] if rest_jacobian_in_c(runs) else None
    functions = [*runs.derivatives, *([] if rest is None else [rest])]
    sizes = [max([f.sz_arg(), f.sz_res(), f.sz_iw(), f.sz_w()][k] for f in functions) if functions else 0
             for k in range(4)]  # fmt: skip
    total = sum(r.count * len(runs.derivative_leaves[r.template]) for r in runs.runs)
    total += 0 if rest is None else runs.rest_pattern[0].size
    out = [
        f"#define N_JAC {total}\n#define JAC_ARG {max(sizes[0], 4)}\n#define JAC_RES {max(sizes[1], 1)}\n"
        f"#define JAC_IW {sizes[2]}\n#define JAC_W {sizes[3]}\n"
        "static const casadi_int sp_jac[3] = {N_JAC, 1, 1};\n"
        f"int {JACOBIAN}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {{\n"
        "  casadi_int r, i, j;\n"
        "  casadi_real* o = res[0];\n"
        "  if (!o) return 0;\n"
    ]
    for k, derivative in enumerate(runs.derivatives):
        leaves, width = derivative.n_in(), len(runs.derivative_leaves[k])
        if width:  # (else a constant row: no partial derivatives, nothing written)
            count = sum(r.template == k for r in runs.runs)
            out.append(_run_loop(k, count, leaves, derivative.name(), "", "o", f"      o += {width};\n"))
    if rest is not None:
        out.append(
            "  {\n"
            "    const casadi_real** rest_arg = arg + 4;\n"
            "    casadi_real** rest_res = res + 1;\n"
            "    rest_gather(arg, w + JAC_W, rest_arg);\n"
            "    rest_res[0] = o;\n"
            "    if (rest_jacobian_rows(rest_arg, rest_res, iw, w, 0)) return 1;\n"
            "  }\n"
        )
    out.append(
        "  return 0;\n}\n"
        f"casadi_int {JACOBIAN}_n_in(void) {{ return 4; }}\n"
        f"casadi_int {JACOBIAN}_n_out(void) {{ return 1; }}\n"
        f"const casadi_int* {JACOBIAN}_sparsity_in(casadi_int i) {{\n"
        "  return i == 0 ? sp_t : i == 1 ? sp_x : i == 2 ? sp_z : i == 3 ? sp_p : 0;\n}\n"
        f"const casadi_int* {JACOBIAN}_sparsity_out(casadi_int i) {{ return i == 0 ? sp_jac : 0; }}\n"
        f"int {JACOBIAN}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {{\n"
        "  if (sz_arg) *sz_arg = 4 + JAC_ARG;  /* (the rest's arguments after its own) */\n"
        "  if (sz_res) *sz_res = 1 + JAC_RES;\n"
        "  if (sz_iw) *sz_iw = JAC_IW;\n"
        "  if (sz_w) *sz_w = JAC_W + N_LEAVES;  /* (the functions' work, then the rest's leaves) */\n"
        "  return 0;\n}\n"
    )
    return "".join(out)


def residual_source(tableau) -> str:
    """The C of :data:`RESIDUAL` (after :func:`stencil_source`'s): :func:`.compiled.casadi_functions`' stage
    residual of ``[t, h, y_n, W, p]`` to ``[R, f at the stages]``, its operations in the order of that MX
    graph (``t + c_i h``; ``Y_i - y_n - h (a_i1 f_1 + ... + a_is f_s)`` summed from the left), the
    tableau's numbers as C99 hexadecimal literals (exact); :data:`STAGE_F`, f at the stages alone; and each
    of the two of the five inputs ``(t, h, y_n, W, p)`` apart (``_parts``: :class:`Sliced` binds them to the
    caller's arrays, no packed copy), the packed ones calling those."""
    s, A, c = tableau.stages, tableau.A, tableau.c
    hexes = lambda values: ", ".join(float(v).hex() for v in values)  # noqa: E731
    parts = "".join(
        f"int {name}{SIGNATURE} {{\n"
        "  const casadi_real** parts = arg + 1;  /* (the five inputs in the packed one, then the parts' own) */\n"
        "  parts[0] = arg[0]; parts[1] = arg[0] + 1; parts[2] = arg[0] + 2; parts[3] = parts[2] + N_X;\n"
        "  parts[4] = parts[3] + N_S * N_D;\n"
        f"  return {name}_parts(parts, res, iw, w, mem);\n}}\n"
        for name in (RESIDUAL, STAGE_F)
    )
    interfaces = "".join(
        f"casadi_int {name}_n_in(void) {{ return {inputs}; }}\n"
        f"casadi_int {name}_n_out(void) {{ return 1; }}\n"
        f"const casadi_int* {name}_sparsity_in(casadi_int i) {{ return {sparsity}; }}\n"
        f"const casadi_int* {name}_sparsity_out(casadi_int i) {{ return i == 0 ? {out} : 0; }}\n"
        f"int {name}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {{\n"
        f"  if (sz_arg) *sz_arg = {inputs} + {5 if inputs == 1 else 0} + 4 + REST_ARG;  /* (then the stencil's) */\n"
        "  if (sz_res) *sz_res = 1 + 2 + REST_RES;\n"
        "  if (sz_iw) *sz_iw = REST_IW;\n"
        "  if (sz_w) *sz_w = REST_W + N_REST + N_LEAVES;\n"
        "  return 0;\n}\n"
        for function, out in ((RESIDUAL, "sp_out"), (STAGE_F, "sp_stage_f"))
        for name, inputs, sparsity in (
            (function, 1, "i == 0 ? sp_in : 0"),
            (f"{function}_parts", 5, "i < 2 ? sp_t : i == 2 ? sp_x : i == 3 ? sp_W : i == 4 ? sp_p : 0"),
        )
    )
    return (
        f"\n/* daemodel: the stage residual on {NAME} (generated; numbers only) */\n"
        f"#define N_S {s}\n#define N_D (N_X + N_Z)\n"
        f"static const casadi_real stage_c[N_S] = {{{hexes(c)}}};\n"
        f"static const casadi_real stage_a[N_S][N_S] = {{{', '.join('{' + hexes(row) + '}' for row in A)}}};\n"
        "static const casadi_int sp_in[3] = {2 + N_X + N_S * N_D + N_P, 1, 1};\n"
        "static const casadi_int sp_W[3] = {N_S * N_D, 1, 1};\n"
        "static const casadi_int sp_out[3] = {N_S * N_D + N_S * N_X, 1, 1};\n"
        "static const casadi_int sp_stage_f[3] = {N_S * N_X, 1, 1};\n"
        f"int {RESIDUAL}_parts{SIGNATURE} {{\n"
        "  const casadi_real* yn = arg[2];\n"
        "  const casadi_real* W = arg[3];\n"
        "  const casadi_real* p = arg[4];\n"
        "  casadi_real* R = res[0];\n"
        "  casadi_real* F = R + N_S * N_D;\n"
        "  casadi_real t, h = arg[1][0], q;\n"
        "  casadi_int i, j, k;\n"
        "  if (!R) return 0;\n"
        "  for (i = 0; i < N_S; i++) {\n"
        "    const casadi_real** a = arg + 5;\n"
        "    casadi_real** r = res + 1;\n"
        "    t = arg[0][0] + stage_c[i] * h;\n"
        "    a[0] = &t; a[1] = W + i * N_D; a[2] = W + i * N_D + N_X; a[3] = p;\n"
        "    r[0] = F + i * N_X; r[1] = R + i * N_D + N_X;\n"
        f"    if ({NAME}(a, r, iw, w, 0)) return 1;\n"
        "  }\n"
        "  for (i = 0; i < N_S; i++)\n"
        "    for (k = 0; k < N_X; k++) {\n"
        "      q = stage_a[i][0] * F[k];\n"
        "      for (j = 1; j < N_S; j++) q = q + stage_a[i][j] * F[j * N_X + k];\n"
        "      R[i * N_D + k] = W[i * N_D + k] - yn[k] - h * q;\n"
        "    }\n"
        "  return 0;\n}\n"
        # f at the stages alone (the error estimate's, :func:`.compiled.stage_f_function`): g's rows not written
        f"int {STAGE_F}_parts{SIGNATURE} {{\n"
        "  const casadi_real* W = arg[3];\n"
        "  casadi_real* F = res[0];\n"
        "  casadi_real t, h = arg[1][0];\n"
        "  casadi_int i;\n"
        "  if (!F) return 0;\n"
        "  for (i = 0; i < N_S; i++) {\n"
        "    const casadi_real** a = arg + 5;\n"
        "    casadi_real** r = res + 1;\n"
        "    t = arg[0][0] + stage_c[i] * h;\n"
        "    a[0] = &t; a[1] = W + i * N_D; a[2] = W + i * N_D + N_X; a[3] = arg[4];\n"
        "    r[0] = F + i * N_X; r[1] = 0;\n"
        f"    if ({NAME}(a, r, iw, w, 0)) return 1;\n"
        "  }\n"
        "  return 0;\n}\n"
        f"{parts}{interfaces}"
    )


def stencil_function(runs, tableau, compiler: str):
    """The casadi functions :data:`NAME` and :data:`RESIDUAL` of ``runs`` and ``tableau`` compiled by
    ``compiler`` (through the disk cache), and what the cache did ("hit", "miss", ...).  Raises
    :class:`~daemodel.errors.CompileError` where the compiler fails."""
    from daemodel.cache import Build, cached_library

    what = "radau's machine code: compiling the stencil's equations"
    fix = "solve with jit=False (casadi's virtual machine: the same results)"
    flags = compiler_flags(compiler)
    flags += GCC_STENCIL_FLAGS if flags != COMPILER_FLAGS else ()  # (GCC's flags added: not clang)
    build = Build(compiler, flags, what, fix, libraries=("-lm",), timeout=STENCIL_COMPILE_TIMEOUT)
    source = stencil_source(runs) + residual_source(tableau)
    names = (NAME, RESIDUAL, JACOBIAN, STAGE_F, f"{RESIDUAL}_parts", f"{STAGE_F}_parts")
    library = cached_library(source, list(names), build)
    return (*(library.functions[name] for name in names), library.outcome)


class StencilFunctions(NamedTuple):
    """:func:`stencil_equations`' functions: of the packed inputs (casadi functions, for casadi graphs and
    :func:`.compiled.casadi_functions`), and the same on the caller's arrays (:class:`Sliced`, for the engine)."""

    fg: object  # (t, x, z, p) -> (f, g): :data:`NAME`
    residual: object  # [t, h, y_n, W, p] -> [R, f at the stages]: :data:`RESIDUAL`
    jacobian: object  # [t, x, z, p] -> the Jacobian's nonzeros (casadi's order), or None: :func:`gathered_jacobian`
    stage_f: object  # [t, h, y_n, W, p] -> f at the stages: :data:`STAGE_F`
    sliced_f: Sliced
    sliced_residual: Sliced
    sliced_jacobian: Sliced | None
    sliced_stage_f: Sliced


def stencil_equations(compiled, tableau):
    """``(functions, said)``: the compiled :class:`StencilFunctions` of ``compiled`` and ``tableau`` (made once
    per model and s) and what a solve's stats say of them, or ``(None, why)`` where the model is not a repeated
    stencil (:func:`daemodel.compiling.runs.equation_runs`), there is no compiler, or it failed."""
    from daemodel.compiling.runs import model_runs, runs_jacobian_layout
    from daemodel.errors import CompileError

    def build():
        compiler = find_compiler()
        if compiler is None:
            return None, "casadi's virtual machine (no C compiler)"
        runs = model_runs(compiled)
        if runs is None:
            return None, "casadi's virtual machine (not a repeated stencil)"
        try:
            fg, residual, raw, stage_f, residual_parts, stage_f_parts, outcome = stencil_function(
                runs, tableau, compiler
            )
        except CompileError as error:
            return None, f"casadi's virtual machine (the compiler failed: {str(error)[:200]})"
        layout = runs_jacobian_layout(compiled)
        rest = None if rest_jacobian_in_c(runs) else runs.rest_jacobian  # (None: in the library, or no rest)
        jacobian = sliced = None
        n, m, P = sizes = runs.sizes
        if layout is not None:
            jacobian = gathered_jacobian(raw, layout[2], sizes, rest)
            sliced = Sliced("jacobian", [raw, *([] if rest is None else [rest])], (1, n, m, P), layout[2])
        stages = (1, 1, n, tableau.stages * (n + m), P)  # (t, h, y_n, W, p)
        functions = StencilFunctions(fg, residual, jacobian, stage_f, Sliced("f", [fg], (1, n, m, P)),
                                     Sliced("residual", [residual_parts], stages), sliced,
                                     Sliced("stage_f", [stage_f_parts], stages))  # fmt: skip
        return functions, f"machine code ({runs.describe()}; cache: {outcome})"

    return compiled.cached(("radau-stencil-equations", tableau.stages), build)


class Sliced:
    """A function of inputs apart (``sizes``: ``(t, x, z, p)``, or ``(t, h, y_n, W, p)``) made of casadi functions of
    them (the library's), called on the caller's arrays in place: their first outputs one after the other are its
    values, or those at ``taken`` where it is given.  The engine's f, Jacobian, stage residual and stages' f of a
    stencil (:func:`engine_functions`): casadi functions of one packed input held a copy of it (the residual's 4.4 MB
    at 10^5 unknowns of reaction-diffusion, s = 5), and an MX function around the library's Jacobian its split
    input's copies, the library's values and their gather in its work (7.2 MB; f's 2.4 MB)."""

    def __init__(self, name: str, functions, sizes, taken=None):
        self.name, self.functions, self.taken = name, tuple(functions), taken
        self.sizes = tuple(int(size) for size in sizes)
        self.buffered = SlicedBuffered  # (the kind .compiled.lend binds to it)

    def nnz_in(self, k: int = 0) -> int:
        """The packed input's size (:meth:`SlicedBuffered.__call__`'s)."""
        return sum(self.sizes)

    def nnz_out(self, k: int = 0) -> int:
        return len(self.taken) if self.taken is not None else sum(f.nnz_out(0) for f in self.functions)


class SlicedBuffered(Buffered):
    """:class:`Sliced`'s functions on casadi's FunctionBuffers: each call binds each input to the caller's array
    (a C-contiguous float64 array of its size; else, and scalars, a copy in a buffer of its own), each function's
    first output to its part of the values (later outputs not written: g with f), and gathers the values at
    ``taken`` into the output (numpy, in place); ``output``: the float64 array its output is written to."""

    def __init__(self, function: Sliced, inputs: int = 1, input_of=None, output: np.ndarray | None = None):
        """``inputs``, ``input_of``: Buffered's, not used (each call binds the caller's arrays)."""
        self.name, self.function, size = function.name, function, function.nnz_out()
        writable = output is not None and output.flags.c_contiguous and output.flags.writeable
        if output is not None and (output.dtype != float or output.shape != (size,) or not writable):
            raise ValueError(
                f"{self.name} gives {size} outputs, not {output.shape} (into a writable contiguous float64 array)"
            )
        self.inputs = []  # (nothing bound between calls: see packed)
        self._copies = {}  # (input k's buffer, where a call's part is not an array to bind)
        self._outputs = np.zeros(size) if output is None else output
        self._buffers = [(*each.buffer(), each.name()) for each in function.functions]
        self._values_size = sum(each.nnz_out(0) for each in function.functions)
        if function.taken is None:
            self._bind_outputs(self._outputs)

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """The outputs for the packed input ``values`` (its parts bound in place)."""
        values = np.ascontiguousarray(values, dtype=float)
        bounds = np.cumsum((0, *self.function.sizes))
        return self.packed(*(values[a:b] for a, b in itertools.pairwise(bounds)))

    def packed(self, *parts, copy: bool = True) -> np.ndarray:
        """The outputs for the inputs ``parts``, one a size of :attr:`Sliced.sizes`; ``copy``: as Buffered's."""
        sizes = self.function.sizes
        if len(parts) != len(sizes) or any(np.size(part) != size for part, size in zip(parts, sizes, strict=False)):
            given = [int(np.size(part)) for part in parts]
            raise ValueError(f"{self.name} takes inputs of sizes {list(sizes)}; the parts hold {given}")
        for k, part in enumerate(parts):
            if not (isinstance(part, np.ndarray) and part.dtype == float and part.flags.c_contiguous):
                if k not in self._copies:
                    self._copies[k] = np.empty(sizes[k])
                part = self._copies[k]
                part[:] = np.ravel(parts[k])
            for buffer, _, _ in self._buffers:  # (the parts are alive until the call returns: the caller's)
                buffer.set_arg(k, memoryview(part.reshape(-1)))
        # (values to gather made for the call: kept, the Jacobian's were 2.8 MB of a cold solve's peak at 10^5 unknowns)
        values = None if self.function.taken is None else self._bind_outputs(None)
        for buffer, evaluate, name in self._buffers:
            evaluate()
            if buffer.ret() != 0:
                raise RuntimeError(f"casadi function {name} failed (return code {buffer.ret()})")
        if values is not None:  # ("clip": each index is valid; numpy's "raise" copies out first)
            np.take(values, self.function.taken, out=self._outputs, mode="clip")
        return self._outputs.copy() if copy else self._outputs

    def _bind_outputs(self, values: np.ndarray | None) -> np.ndarray:
        """Each function's first output bound to its part of ``values`` (a new array where None), returned."""
        values, at = np.empty(self._values_size) if values is None else values, 0
        for (buffer, _, _), function in zip(self._buffers, self.function.functions, strict=True):
            buffer.set_res(0, memoryview(values[at : at + function.nnz_out(0)]))
            at += function.nnz_out(0)
        return values

    def evaluate(self, copy: bool = True) -> np.ndarray:
        """Not on bound inputs: they are the last caller's arrays, perhaps gone (:meth:`packed` binds them)."""
        raise TypeError(f"{self.name} reads its inputs where each call gives them: call packed(), not evaluate()")


def gathered_jacobian(raw, taken, sizes, rest=None):
    """casadi function of the packed ``[t, x, z, p]`` to the Jacobian's nonzeros in casadi's order: :data:`JACOBIAN`'s
    values (``raw``), then ``rest``'s (the rest rows' Jacobian where it is not in the library:
    :func:`rest_jacobian_in_c`), at ``taken`` (:func:`daemodel.compiling.runs.jacobian_layout`)."""
    import casadi

    n, m, P = sizes
    packed = casadi.MX.sym("x", 1 + n + m + P)
    t, x, z, p = casadi.vertsplit(packed, [0, 1, 1 + n, 1 + n + m, 1 + n + m + P])
    values = raw(t, x, z, p) if rest is None else casadi.vertcat(raw(t, x, z, p), rest(t, x, z, p))
    return casadi.Function("jacobian", [packed], [values[taken.tolist()]])


def rest_jacobian_in_c(runs) -> bool:
    """Whether :data:`JACOBIAN` computes the rest rows' Jacobian too: there is a rest and its Jacobian has at
    most :data:`REST_JACOBIAN_C_MAX` operations (else :func:`gathered_jacobian` calls it on the virtual machine)."""
    rest = runs.rest_inner[1]
    # (its operations are those of the function of the rows' own symbols it calls: runs._rest_functions)
    return rest is not None and rest.n_instructions() <= REST_JACOBIAN_C_MAX


def uses_stencil(compiled, jit, machine_code: bool) -> bool:
    """Whether a casadi engine of ``jit`` (an option's value) and ``machine_code`` (:func:`.backend.jit_choice`'s)
    tries :func:`stencil_equations` (see :func:`engine_functions`)."""
    D = len(compiled.states) + len(compiled.algebraics)
    return jit is not False and not machine_code and D > INLINED_RESIDUAL_MAX_SIZE and find_compiler() is not None


def engine_functions(compiled, tableau, machine: bool):
    """``(functions, lent, stage_f, said)`` of the casadi engine: :func:`.compiled.casadi_functions` and
    :func:`.compiled.stage_f_of` (made once per model and s), on :func:`stencil_equations`' functions
    where ``machine`` code may run (a C compiler, ``jit`` not False; with ``jit`` True the whole solve's
    functions are compiled instead) above :data:`.compiled.INLINED_RESIDUAL_MAX_SIZE` unknowns and the
    model is a repeated stencil; ``lent``: what the engine evaluates f, the stage residual and the Jacobian
    with (the first three functions, or the stencil's :class:`Sliced`); ``said``: what a solve's stats say
    of it (None where it was not tried)."""
    stencil, said = None, None
    if machine and len(compiled.states) + len(compiled.algebraics) > INLINED_RESIDUAL_MAX_SIZE:
        stencil, said = stencil_equations(compiled, tableau)
    key = ("casadi-radau", tableau.stages) + (() if stencil is None else ("stencil",))
    functions = compiled.cached(key, lambda: casadi_functions(compiled, tableau, stencil))
    if stencil is None:
        return functions, functions[:3], stage_f_of(compiled, tableau, stencil), said
    lent = (stencil.sliced_f, stencil.sliced_residual, stencil.sliced_jacobian or functions[2])
    return functions, lent, stencil.sliced_stage_f, said
