"""The fixed-pivot sparse factorisation and triangular solves (:mod:`.sparse`) as loops in C.

:func:`.increments.static_factor_function` writes the elimination as straight-line SX: on casadi's
virtual machine ~2-3 ns an operation, so 170-320 us a factorisation of the 20-pendulum chain at
s = 3 and 5 (a third of its solve), and as machine code 3-15 s of compiling for a factor of two.
Here the elimination is data: arrays of positions (which entry is divided by which pivot, which
is updated from which), run by one fixed loop in C, compiled in well under a second per model;
the arrays are the only part that differs between models, and they are numbers, never names.

The loop makes the same operations on the same operands in the same order as the SX expressions
(complex ones with the same formulas), and is compiled without contracting ``a - b c`` into
fused multiply-adds, so its factors are those of :func:`.increments.static_factor_function` bit for
bit (a test compares them).  It is a casadi *external* function: it can be called from Python on
bound buffers and inside other casadi functions (:mod:`.loop`'s compiled run) alike.  The same
source holds ``sign_det``, the sign of the algebraic variables' iteration matrix's determinant by
a dense LU with LAPACK's row choice, which the run needs at each fresh Jacobian (in SX, with its
pivoting as branches, it grows with m^3 on the virtual machine).

Measured (2-core CPU, one thread): a factorisation of the 20-pendulum chain (100 unknowns) 160 ->
15 us at s = 3 and 280 -> 24 us at s = 5; the library compiles in about 0.1 s.

The triangular solves with those factors are loops on position arrays too (:func:`solve_program`),
the operations of :meth:`.sparse.StaticLU.solve_function` in its order, bit for bit: unrolled, they
were 2/3 of the compiled step's C (the 20-pendulum chain: 12,800 of 18,750 lines, 4 of its 5 s of
compiling).  The compiled step calls them (:func:`solve_call`) with this source in front of its own in
one library (:func:`.compiled.machine_library`), which also offers them (``static_solve``,
``static_solve_complex``) to the general path's solves in Python.

The compiled step's Newton increment passes through RADAU5's transforms on either side of those solves
(the stage residual through ``T^-1 A^-1`` and ``T^-1``, the solutions back through ``T``, then the
increment's scaled norm): as loops too (``dm_transform_in``, ``dm_transform_out``: :func:`transform_calls`), the sums of
casadi's dense products and dot product in their order, so the same bits, without the copies, slices and
transposes that casadi's code made between the MX products (the chain of 20 pendulums at rtol 1e-4: the
run's instructions 14.2 -> 12.9 million a solve).

Positions: the factors' nonzeros numbered as they are packed, L's (row by row, columns ascending)
then U's (row by row, columns ascending from the diagonal); each system's elimination runs in
place on them (an L entry is the matrix entry it replaces, divided by its pivot).
"""

from __future__ import annotations

import numpy as np

# C compilers' flags: no fused multiply-adds (the factors bit for bit those of the SX function); the
# cache adds those of a shared library (daemodel.cache.LIBRARY_FLAGS)
KERNEL_FLAGS = ("-O2", "-ffp-contract=off", "-fno-math-errno")
# Up to this many entries of the factors (L's and U's) the compiled step's triangular solves stay
# straight-line code (.sparse's SX): little to compile, and on such small systems faster than the loops
# (car axis, 53 entries: its step 5.4 against 6.0 us); above, the loops: the same step time or less
# (squeezer, 183: 15.2 against 15.5 us; the chain of 20 pendulums, 917: 2/3 of its step's C gone) and
# half the compiling (squeezer 0.6 against 1.5 s).
UNROLLED_SOLVE_MAX_ENTRIES = 100
# Seconds the compiler may take (a model's arrays are at most a few hundred kB of C)
KERNEL_COMPILE_TIMEOUT = 120.0


def factor_program(lu) -> dict:
    """The elimination of :class:`.sparse.StaticLU` ``lu`` as position arrays (int32):

    ``j_slot``: where each Jacobian nonzero goes (negated); ``d_slot``: the positions of M's
    diagonal (the shift over h is added); ``m_slot``: the positions the matrix has entries at (its
    largest entry, for the growth); ``div_slot``, ``div_pivot``: each division, an L entry by its
    pivot, in elimination order, and ``upd_begin``: where its updates start in ``upd_dst``,
    ``upd_src`` (entry ``dst`` minus the L entry times entry ``src``); ``pivot_slot``: the pivots.
    """
    D, n = lu.D, lu.n
    slot = {}
    for i in range(D):
        for k in lu.lower[i]:
            slot[(i, k)] = len(slot)
    for k in range(D):
        for j in lu.upper[k]:
            slot[(k, j)] = len(slot)
    j_slot = [slot[(int(lu.perm_r[i]), int(lu.perm_c[j]))] for i, j in zip(lu.rows, lu.cols, strict=True)]
    d_slot = [slot[(int(lu.perm_r[i]), int(lu.perm_c[i]))] for i in range(n)]
    m_slot = sorted(set(j_slot) | set(d_slot))
    div_slot, div_pivot, upd_begin, upd_dst, upd_src = [], [], [0], [], []
    for k in range(D):
        upper_k = [j for j in lu.upper[k] if j > k]
        for i in lu.below[k]:
            div_slot.append(slot[(i, k)])
            div_pivot.append(slot[(k, k)])
            for j in upper_k:
                upd_dst.append(slot[(i, j)])
                upd_src.append(slot[(k, j)])
            upd_begin.append(len(upd_dst))
    arrays = {
        "j_slot": j_slot,
        "d_slot": d_slot,
        "m_slot": m_slot,
        "div_slot": div_slot,
        "div_pivot": div_pivot,
        "upd_begin": upd_begin,
        "upd_dst": upd_dst,
        "upd_src": upd_src,
        "pivot_slot": [slot[(k, k)] for k in range(D)],
    }
    return {name: np.asarray(values, dtype=np.int32) for name, values in arrays.items()}


def solve_program(lu) -> dict:
    """The triangular solves of :meth:`.sparse.StaticLU.solve_function` as position arrays (int32):

    ``l_begin``, ``l_col``: row i of L (unit lower) holds the packed L entries ``l_begin[i]`` up to
    ``l_begin[i + 1]``, in columns ``l_col``; ``u_begin``, ``u_col``: row i of U likewise, its
    diagonal first; ``row_in``: the right-hand side's entry that row i of the permuted system reads
    (``Pr b``); ``col_out``: the permuted unknown that unknown k is (``x = Pc x'``).
    """
    row_in = np.empty(lu.D, dtype=np.int64)
    row_in[lu.perm_r] = np.arange(lu.D)
    arrays = {
        "l_begin": np.cumsum([0] + [len(columns) for columns in lu.lower]),
        "l_col": [k for columns in lu.lower for k in columns],
        "u_begin": np.cumsum([0] + [len(columns) for columns in lu.upper]),
        "u_col": [j for columns in lu.upper for j in columns],
        "row_in": row_in,
        "col_out": lu.perm_c,
    }
    return {name: np.asarray(values, dtype=np.int32) for name, values in arrays.items()}


def _array(name: str, values, kind: str = "int") -> str:
    """A C array definition (at least one element: C has no empty arrays)."""
    values = list(values) or [0]
    if kind == "int":
        body = ",".join(str(int(v)) for v in values)
    else:
        body = ",".join(float(v).hex() for v in values)  # (exact: C99 hexadecimal floating constants)
    return f"static const {kind} {name}[{len(values)}] = {{{body}}};\n"


# The kernel: the same for every model; the arrays and sizes in front of it are the model's.
_KERNEL = r"""
static void dm_load(const double* J, double h, double a_re, double a_im, double* re, double* im) {
  int q;
  for (q = 0; q < N_SLOT; q++) re[q] = 0.0;
  for (q = 0; q < N_J; q++) re[j_slot[q]] -= J[q];
  for (q = 0; q < N_DIAG; q++) re[d_slot[q]] += a_re / h;
  if (!im) return;
  for (q = 0; q < N_SLOT; q++) im[q] = 0.0;
  for (q = 0; q < N_DIAG; q++) im[d_slot[q]] += a_im / h;
}

static void dm_eliminate_real(double* w) {
  int e, u;
  for (e = 0; e < N_DIV; e++) {
    double f = w[div_slot[e]] / w[div_pivot[e]];
    w[div_slot[e]] = f;
    for (u = upd_begin[e]; u < upd_begin[e + 1]; u++) w[upd_dst[u]] = w[upd_dst[u]] - f * w[upd_src[u]];
  }
}

static void dm_eliminate_complex(double* re, double* im) {
  int e, u;
  for (e = 0; e < N_DIV; e++) {
    double a0 = re[div_slot[e]], a1 = im[div_slot[e]], b0 = re[div_pivot[e]], b1 = im[div_pivot[e]];
    double den = b0 * b0 + b1 * b1;
    double f0 = (a0 * b0 + a1 * b1) / den, f1 = (a1 * b0 - a0 * b1) / den;
    re[div_slot[e]] = f0;
    im[div_slot[e]] = f1;
    for (u = upd_begin[e]; u < upd_begin[e + 1]; u++) {
      double u0 = re[upd_src[u]], u1 = im[upd_src[u]];
      re[upd_dst[u]] = re[upd_dst[u]] - (f0 * u0 - f1 * u1);
      im[upd_dst[u]] = im[upd_dst[u]] - (f0 * u1 + f1 * u0);
    }
  }
}

static double dm_largest(const double* re, const double* im, int from, int to) {
  double out = 0.0;
  int q;
  for (q = from; q < to; q++) {
    out = fmax(out, fabs(re[q]));
    if (im) out = fmax(out, fabs(im[q]));
  }
  return out;
}

/* one system: its factors (packed at out), its growth and smallest pivot folded into checks */
static void dm_system(const double* J, double h, int s, double* out, double* work, double* checks) {
  int complex_ = shift_complex[s], q;
  double* re = complex_ ? work : out;
  double* im = complex_ ? work + N_SLOT : 0;
  double matrix = 0.0, growth, pivot = INFINITY;
  dm_load(J, h, shift_re[s], shift_im[s], re, im);
  for (q = 0; q < N_MATRIX; q++) {
    matrix = fmax(matrix, fabs(re[m_slot[q]]));
    if (im) matrix = fmax(matrix, fabs(im[m_slot[q]]));
  }
  if (complex_) dm_eliminate_complex(re, im); else dm_eliminate_real(re);
  growth = fmax(dm_largest(re, im, 0, N_L), dm_largest(re, im, N_L, N_SLOT) / fmax(matrix, 1e-300));
  for (q = 0; q < N_PIVOT; q++) {
    double size = im ? fabs(re[pivot_slot[q]]) + fabs(im[pivot_slot[q]]) : fabs(re[pivot_slot[q]]);
    pivot = fmin(pivot, size);
  }
  checks[0] = fmax(checks[0], growth);
  checks[1] = fmin(checks[1], pivot);
  if (complex_) {  /* packed as L's real parts, L's imaginary parts, U's real parts, U's imaginary parts */
    for (q = 0; q < N_L; q++) { out[q] = re[q]; out[N_L + q] = im[q]; }
    for (q = 0; q < N_U; q++) { out[2 * N_L + q] = re[N_L + q]; out[2 * N_L + N_U + q] = im[N_L + q]; }
  }
}

/* the sign of det of an (M_SIGN, M_SIGN) matrix (column-major), 0 where an entry is not finite or the
   matrix is singular: a triangular one's from its diagonal (g_z of a constraint explicit in its own
   variable: the LU below was 4 % of a 200-unknown reaction-diffusion solve), else LU with partial
   pivoting as LAPACK's dgetrf picks its rows (the first largest |entry|), 0 where a pivot is 0 */
static double dm_sign_of_det(const double* a, double* w) {
  double sign = 1.0;
  int i, j, k, lower = 1, upper = 1;
  for (j = 0; j < M_SIGN; j++) {
    for (i = 0; i < M_SIGN; i++) {
      double x = a[i + j * M_SIGN];
      if (!(fabs(x) < INFINITY)) return 0.0;
      if (x != 0.0) {
        if (i < j) lower = 0;
        if (i > j) upper = 0;
      }
    }
  }
  if (lower || upper) {
    for (k = 0; k < M_SIGN; k++) {
      if (a[k + k * M_SIGN] == 0.0) return 0.0;
      if (a[k + k * M_SIGN] < 0.0) sign = -sign;
    }
    return sign;
  }
  for (i = 0; i < M_SIGN * M_SIGN; i++) w[i] = a[i];
  for (k = 0; k < M_SIGN; k++) {
    int p = k;
    double big = fabs(w[k + k * M_SIGN]);
    for (i = k + 1; i < M_SIGN; i++) {
      if (fabs(w[i + k * M_SIGN]) > big) { big = fabs(w[i + k * M_SIGN]); p = i; }
    }
    if (!(big > 0.0) || !(big < INFINITY)) return 0.0;
    if (p != k) {
      for (j = 0; j < M_SIGN; j++) {
        double x = w[k + j * M_SIGN];
        w[k + j * M_SIGN] = w[p + j * M_SIGN];
        w[p + j * M_SIGN] = x;
      }
      sign = -sign;
    }
    if (w[k + k * M_SIGN] < 0.0) sign = -sign;
    for (i = k + 1; i < M_SIGN; i++) {
      double f = w[i + k * M_SIGN] / w[k + k * M_SIGN];
      for (j = k + 1; j < M_SIGN; j++) w[i + j * M_SIGN] = w[i + j * M_SIGN] - f * w[k + j * M_SIGN];
    }
  }
  return sign;
}

#ifndef casadi_int
#define casadi_int long long int
#endif
static const casadi_int sparsity_sign_in[3] = {M_SIGN * M_SIGN, 1, 1};
static const casadi_int sparsity_sign_out[3] = {1, 1, 1};

int sign_det(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  if (res[0]) res[0][0] = dm_sign_of_det(arg[0], w);
  return 0;
}
casadi_int sign_det_n_in(void) { return 1; }
casadi_int sign_det_n_out(void) { return 1; }
const casadi_int* sign_det_sparsity_in(casadi_int i) { return i == 0 ? sparsity_sign_in : 0; }
const casadi_int* sign_det_sparsity_out(casadi_int i) { return i == 0 ? sparsity_sign_out : 0; }
int sign_det_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {
  if (sz_arg) *sz_arg = 1;
  if (sz_res) *sz_res = 1;
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = M_SIGN * M_SIGN + 1;
  return 0;
}

static const casadi_int sparsity_in[3] = {1 + N_J, 1, 1};
static const casadi_int sparsity_out[3] = {N_OUT, 1, 1};

int static_factors(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  const double* x = arg[0];
  double* out = res[0];
  double checks[2] = {0.0, INFINITY};
  int s;
  if (!out) return 0;
  for (s = 0; s < N_SHIFTS; s++) dm_system(x + 1, x[0], s, out + shift_offset[s], w, checks);
  out[N_OUT - 2] = checks[0];
  out[N_OUT - 1] = checks[1];
  return 0;
}
casadi_int static_factors_n_in(void) { return 1; }
casadi_int static_factors_n_out(void) { return 1; }
const casadi_int* static_factors_sparsity_in(casadi_int i) { return i == 0 ? sparsity_in : 0; }
const casadi_int* static_factors_sparsity_out(casadi_int i) { return i == 0 ? sparsity_out : 0; }
int static_factors_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {
  if (sz_arg) *sz_arg = 1;
  if (sz_res) *sz_res = 1;
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = 2 * N_SLOT;
  return 0;
}

/* A x = b with one system's packed factors (.sparse's StaticLU.solve_function: the same operations
   in the same order): L y = Pr b, U x' = y (in place: x'[i] needs y[i] and x'[j > i]), x = Pc x';
   a null input reads as zeros, a null output is skipped */
static const double dm_zeros[N_ZEROS] = {0.0};

static int dm_solve_real(const double* factors, const double* b, double* x) {
  double y[N_D];
  const double* L = factors ? factors : dm_zeros;
  const double* U = L + N_L;
  int i, q;
  if (!x) return 0;
  if (!b) b = dm_zeros;
  for (i = 0; i < N_D; i++) {
    double v = b[row_in[i]];
    for (q = l_begin[i]; q < l_begin[i + 1]; q++) v = v - L[q] * y[l_col[q]];
    y[i] = v;
  }
  for (i = N_D - 1; i >= 0; i--) {
    double v = y[i];
    for (q = u_begin[i] + 1; q < u_begin[i + 1]; q++) v = v - U[q] * y[u_col[q]];
    y[i] = v / U[u_begin[i]];
  }
  for (i = 0; i < N_D; i++) x[i] = y[col_out[i]];
  return 0;
}

/* complex: factors (L re, L im, U re, U im), b and x as (re (N_D), im (N_D)) */
static int dm_solve_complex(const double* factors, const double* b, double* x) {
  double y0[N_D], y1[N_D];
  const double* F = factors ? factors : dm_zeros;
  const double *L0 = F, *L1 = F + N_L, *U0 = F + 2 * N_L, *U1 = F + 2 * N_L + N_U;
  int i, q;
  if (!x) return 0;
  if (!b) b = dm_zeros;
  for (i = 0; i < N_D; i++) {
    double v0 = b[row_in[i]], v1 = b[N_D + row_in[i]];
    for (q = l_begin[i]; q < l_begin[i + 1]; q++) {
      double a0 = L0[q], a1 = L1[q], c0 = y0[l_col[q]], c1 = y1[l_col[q]];
      v0 = v0 - (a0 * c0 - a1 * c1);
      v1 = v1 - (a0 * c1 + a1 * c0);
    }
    y0[i] = v0;
    y1[i] = v1;
  }
  for (i = N_D - 1; i >= 0; i--) {
    double v0 = y0[i], v1 = y1[i], d0 = U0[u_begin[i]], d1 = U1[u_begin[i]], den;
    for (q = u_begin[i] + 1; q < u_begin[i + 1]; q++) {
      double a0 = U0[q], a1 = U1[q], c0 = y0[u_col[q]], c1 = y1[u_col[q]];
      v0 = v0 - (a0 * c0 - a1 * c1);
      v1 = v1 - (a0 * c1 + a1 * c0);
    }
    den = d0 * d0 + d1 * d1;
    y0[i] = (v0 * d0 + v1 * d1) / den;
    y1[i] = (v1 * d0 - v0 * d1) / den;
  }
  for (i = 0; i < N_D; i++) {
    x[i] = y0[col_out[i]];
    x[N_D + i] = y1[col_out[i]];
  }
  return 0;
}

static const casadi_int sparsity_solve_in[2][3] = {{N_L + N_U, 1, 1}, {N_D, 1, 1}};
static const casadi_int sparsity_solve_complex_in[2][3] = {{2 * (N_L + N_U), 1, 1}, {2 * N_D, 1, 1}};
static const casadi_int sparsity_solve_out[3] = {N_D, 1, 1};
static const casadi_int sparsity_solve_complex_out[3] = {2 * N_D, 1, 1};

/* the factors and the determinant's sign as plain C calls, their work on the stack: for code that
   casadi's generator writes around them (factor_call, sign_call) */
static int dm_factors(const double* x, double* out) {
  double work[2 * N_SLOT];
  const double* arg[1];
  double* res[1];
  if (!x) return 1;  /* (casadi passes a null input for structural zeros: never [h, J], whose h is a number) */
  arg[0] = x;
  res[0] = out;
  return static_factors(arg, res, 0, work, 0);
}

static int dm_sign(const double* a, double* out) {
  double work[M_SIGN * M_SIGN + 1];
  const double* arg[1];
  double* res[1];
  if (!a) a = dm_zeros;  /* (a null input: zeros, a singular matrix) */
  arg[0] = a;
  res[0] = out;
  return sign_det(arg, res, 0, work, 0);
}

int static_solve(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  return dm_solve_real(arg[0], arg[1], res[0]);
}
casadi_int static_solve_n_in(void) { return 2; }
casadi_int static_solve_n_out(void) { return 1; }
const casadi_int* static_solve_sparsity_in(casadi_int i) { return i < 2 ? sparsity_solve_in[i] : 0; }
const casadi_int* static_solve_sparsity_out(casadi_int i) { return i == 0 ? sparsity_solve_out : 0; }

int static_solve_complex(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  return dm_solve_complex(arg[0], arg[1], res[0]);
}
casadi_int static_solve_complex_n_in(void) { return 2; }
casadi_int static_solve_complex_n_out(void) { return 1; }
const casadi_int* static_solve_complex_sparsity_in(casadi_int i) { return i < 2 ? sparsity_solve_complex_in[i] : 0; }
const casadi_int* static_solve_complex_sparsity_out(casadi_int i) { return i == 0 ? sparsity_solve_complex_out : 0; }

/* the transformed systems' right-hand sides from the stage residual r (TR_D rows, stage by stage):
   the states' rows through T^-1 A^-1 over -h, the constraints' through T^-1; out[b]: block b's
   columns one after the other (a complex block: its real part's, then its imaginary part's).  Each
   entry summed from 0 over the stages in order, as casadi's dense product; the loops run along the
   rows, where the entries are contiguous */
static int dm_transform_in(const double* r, const double* h, double** out) {
  int b, c, i, j;
  if (!r) r = dm_zeros_tr;
  for (b = 0; b < TR_BLOCKS; b++) {
    if (!out[b]) continue;
    for (c = 0; c < tr_width[b]; c++) {
      int k = tr_column[b] + c;
      double* o = out[b] + c * TR_D;
      for (i = 0; i < TR_D; i++) o[i] = 0.0;
      for (j = 0; j < TR_S; j++) {
        const double* rj = r + j * TR_D;
        double a = tr_in_states[k * TR_S + j], g = tr_in_constraints[k * TR_S + j];
        for (i = 0; i < TR_N; i++) o[i] = o[i] + rj[i] * a;
        for (i = TR_N; i < TR_D; i++) o[i] = o[i] + rj[i] * g;
      }
      for (i = 0; i < TR_N; i++) o[i] = -(o[i] / h[0]);
    }
  }
  return 0;
}

/* the increment dW (TR_D rows, stage by stage) through T from the blocks' solutions x[b] (each entry
   summed from 0 in order, as casadi's dense product), and the root mean square of dW / scale (its
   squares summed in order, as casadi's dot product) */
static int dm_transform_out(const double** x, const double* scale, double* dW, double* norm) {
  double total = 0.0;
  int i, j, k;
  if (!dW || !scale) return 1;
  for (k = 0; k < TR_S; k++) {
    double* o = dW + k * TR_D;
    for (i = 0; i < TR_D; i++) o[i] = 0.0;
    for (j = 0; j < TR_S; j++) {
      const double* xj = x[tr_block_of[j]] ? x[tr_block_of[j]] + tr_part_of[j] * TR_D : dm_zeros_tr;
      double a = tr_out[k * TR_S + j];
      for (i = 0; i < TR_D; i++) o[i] = o[i] + xj[i] * a;
    }
  }
  for (i = 0; i < TR_D * TR_S; i++) {
    double v = dW[i] / scale[i];
    total += v * v;
  }
  if (norm) norm[0] = sqrt(total / (double)(TR_D * TR_S));
  return 0;
}
"""


def kernel_source(lu, transform, factors, m: int) -> str:
    """The C source of four functions of casadi's external-function interface: ``static_factors``,
    the packed :class:`.increments.StaticFactors` ``factors`` (the systems of ``transform``'s blocks,
    then the error estimate's where it is no block's) from ``[h, J's nonzeros]``; ``sign_det``, the
    sign of the determinant of an (m, m) matrix (:func:`.linalg.dense_sign_det`'s); ``static_solve``
    and ``static_solve_complex``, :meth:`.sparse.StaticLU.solve_function`'s (``dm_solve_real`` and
    ``dm_solve_complex`` inside, for :func:`solve_call`).  Every name it defines that casadi's code
    generator does not (``dm_``, arrays, sizes) may share a source with that generator's code."""
    program = factor_program(lu)
    shifts = [lam for _, lam in transform.blocks]
    offsets = list(factors.offsets)
    if transform.error_block is None:
        shifts.append(complex(1.0 / transform.gamma0))
        offsets.append(factors.error_offset)
    sizes = {
        "N_J": len(program["j_slot"]),
        "N_DIAG": len(program["d_slot"]),
        "N_MATRIX": len(program["m_slot"]),
        "N_DIV": len(program["div_slot"]),
        "N_PIVOT": len(program["pivot_slot"]),
        "N_L": lu.L_size,
        "N_U": lu.U_size,
        "N_SLOT": lu.L_size + lu.U_size,
        "N_SHIFTS": len(shifts),
        "N_OUT": factors.size,
        "M_SIGN": max(m, 1),
        "N_D": lu.D,
        "N_ZEROS": max(2 * max(lu.L_size + lu.U_size, lu.D), m * m),
    }
    source = ["/* daemodel: radau's fixed-pivot sparse factors (generated; numbers only) */\n"]
    source += ["#include <math.h>\n"] + [f"#define {key} {value}\n" for key, value in sizes.items()]
    source += [_array(name, values) for name, values in {**program, **solve_program(lu)}.items()]
    source += [
        _array("shift_re", [lam.real for lam in shifts], "double"),
        _array("shift_im", [lam.imag for lam in shifts], "double"),
        _array("shift_complex", [int(bool(lam.imag)) for lam in shifts]),
        _array("shift_offset", offsets),
    ]
    return "".join(source) + transform_arrays(transform, lu.n, lu.D) + _KERNEL


def factor_kernel(lu, transform, factors, m: int, compiler: str):
    """The casadi functions ``static_factors`` (one input ``[h, J's nonzeros]``, one output: the
    packed factors, growth and smallest pivot) and ``sign_det`` (of an (m, m) matrix's column-major
    values; m = 0: None) compiled by ``compiler`` from :func:`kernel_source`, and what the disk cache
    of compiled libraries did (:mod:`daemodel.cache`: "hit", "miss", ...).

    The library is compiled in a private temporary directory (mode 0700) and kept in the cache, or
    loaded from it.  Raises :class:`~daemodel.errors.CompileError` with the compiler's message where
    it fails.
    """
    from daemodel.cache import Build, cached_library

    what = "radau's machine code: compiling the sparse factors"
    fix = "solve with jit=False (the same results to rounding, slower steps)"
    build = Build(compiler, KERNEL_FLAGS, what, fix, libraries=("-lm",), timeout=KERNEL_COMPILE_TIMEOUT)
    names = ["static_factors", *(["sign_det"] if m else [])]
    code = cached_library(kernel_source(lu, transform, factors, m), names, build)
    return code.functions["static_factors"], code.functions.get("sign_det"), code.outcome


def factor_call(lu, factors):
    """casadi function of ``static_factors``' signature (``[h, J's nonzeros]`` to the packed ``factors``,
    :class:`.increments.StaticFactors`) whose code calls the kernel's (``dm_factors``): for casadi's code
    generator inside a function compiled with :func:`kernel_source` in the same source (the compiled
    run, :mod:`.loop`, in machine code).  It has no code of its own to run: called outside machine
    code, it fails."""
    return _call("factor_call", "return dm_factors(x, out);", [1 + len(lu.rows)], factors.size)


def sign_call(m: int):
    """casadi function of ``sign_det``'s signature (an (m, m) matrix's column-major values to the sign
    of its determinant) whose code calls the kernel's (``dm_sign``); as :func:`factor_call`."""
    return _call("sign_call", "return dm_sign(x, out);", [m * m], 1)


def _call(name: str, body: str, sizes_in: list, size_out: int):
    """A code-only casadi function of one dense input ``x`` and one output ``out`` (see :func:`factor_call`)."""
    import casadi

    return casadi.Function.jit(
        name,
        body,
        ["x"],
        ["out"],
        [casadi.Sparsity.dense(size) for size in sizes_in],
        [casadi.Sparsity.dense(size_out)],
        {"jit": False, "buffered": False},  # (no compiling here; the pointers as the caller holds them, no copies)
    )


def solve_call(lu, complex_: bool):
    """casadi function of :meth:`.sparse.StaticLU.solve_function`'s signature (``[packed factors, b]``
    to ``x``) whose code calls the kernel's loop (``dm_solve_real``, ``dm_solve_complex``): for casadi's
    code generator inside a function compiled with :func:`kernel_source` in the same source, where it
    replaces the unrolled solves (the chain of 20 pendulums: 2/3 of the compiled step's 18,750 lines).
    It has no code of its own to run: called outside machine code, it fails."""
    import casadi

    scale = 2 if complex_ else 1
    return casadi.Function.jit(
        "static_solve_complex" if complex_ else "static_solve",
        f"return dm_solve_{'complex' if complex_ else 'real'}(factors, b, x);",
        ["factors", "b"],
        ["x"],
        [casadi.Sparsity.dense(lu.size(complex_)), casadi.Sparsity.dense(scale * lu.D)],
        [casadi.Sparsity.dense(scale * lu.D)],
        {"jit": False, "buffered": False},  # (no compiling here; the pointers as the caller holds them, no copies)
    )


def transform_arrays(transform, n: int, D: int) -> str:
    """The sizes and arrays of the kernel's ``dm_transform_in`` and ``dm_transform_out`` for ``transform``
    (:class:`.transform.StageTransform`) on n states of D unknowns: its matrices and block layout."""
    s = len(transform.T)
    column, width, block_of, part_of = [], [], [], []
    for index, (k, lam) in enumerate(transform.blocks):
        column.append(k)
        width.append(2 if lam.imag else 1)
        block_of += [index] * width[-1]
        part_of += list(range(width[-1]))
    sizes = {"TR_S": s, "TR_N": n, "TR_D": D, "TR_BLOCKS": len(transform.blocks)}
    source = [f"#define {key} {value}\n" for key, value in sizes.items()]
    source += [
        _array("tr_in_states", np.asarray(transform.T_inv_A_inv, dtype=float).ravel(), "double"),
        _array("tr_in_constraints", np.asarray(transform.T_inv, dtype=float).ravel(), "double"),
        _array("tr_out", np.asarray(transform.T, dtype=float).ravel(), "double"),
        _array("tr_column", column),
        _array("tr_width", width),
        _array("tr_block_of", block_of),
        _array("tr_part_of", part_of),
        f"static const double dm_zeros_tr[{s * D + s * n}] = {{0.0}};\n",
    ]
    return "".join(source)


def transform_calls(transform, n: int, D: int):
    """casadi functions whose code calls the kernel's loops ``dm_transform_in`` and ``dm_transform_out``
    (sized by :func:`transform_arrays`; code only, as :func:`solve_call`: for machine code whose source
    holds :func:`kernel_source`'s):

    ``transform_in``: ``[r (s D + s n: the stage residual's output), h]`` -> each block's right-hand side
    (D, or 2D for a complex block: its real part, then its imaginary part); ``transform_out``: each
    block's solution in that layout and the error scale (s D, stage by stage) -> the increment (s D)
    and its scaled root mean square."""
    import casadi

    s, widths = len(transform.T), [2 if lam.imag else 1 for _, lam in transform.blocks]
    blocks = [f"b{index}" for index in range(len(widths))]
    dense = casadi.Sparsity.dense
    options = {"jit": False, "buffered": False}  # (no compiling here; the pointers as the caller holds them)
    body_in = f"double* o[{len(blocks)}] = {{{', '.join(blocks)}}}; return dm_transform_in(r, h, o);"
    transform_in = casadi.Function.jit(
        "transform_in", body_in, ["r", "h"], blocks, [dense(s * D + s * n), dense(1)],
        [dense(w * D) for w in widths], options,
    )  # fmt: skip
    body_out = f"const double* x[{len(blocks)}] = {{{', '.join(blocks)}}}; return dm_transform_out(x, scale, dW, norm);"
    transform_out = casadi.Function.jit(
        "transform_out", body_out, [*blocks, "scale"], ["dW", "norm"], [*(dense(w * D) for w in widths), dense(s * D)],
        [dense(s * D), dense(1)], options,
    )  # fmt: skip
    return transform_in, transform_out
