"""Band LU factors of the shifted systems in C, for models whose band order is narrow (issue 44).

A chain or a 1-D grid, in its reverse Cuthill-McKee order (:func:`.linalg.band_order`), is a band matrix
a few entries wide.  SuperLU factors it at a fixed cost of ~100 ns a column (its symbolic analysis and
bookkeeping, redone at every factorisation: 10-12 ms at 10^5 unknowns, 8 ms of it for the identity);
LAPACK's band LU (``gbtrf``) at ~37 ns, but its triangular solves cost 2.5x SuperLU's (four BLAS calls
a column).  Here the band LU is one loop in C: LAPACK's ``gbtf2`` (partial pivoting in the band, the
first largest ``|a|`` -- ``|re| + |im|`` for complex entries, as ``izamax``), and ``gbtrs``'s solve,
with no call per column.  The source depends on four sizes only (unknowns, nonzeros, the band's widths),
so it compiles in a fraction of a second and the disk cache (:mod:`daemodel.cache`) keeps it.

Storage is LAPACK's: ``ab`` of ``LDAB = 2 kl + ku + 1`` rows by ``D`` columns (column-major), entry
``A[i, j]`` at row ``kl + ku + i - j``; the factors overwrite it, with the pivots beside them.  A complex
system's entries are interleaved (re, im): numpy's complex128 seen as float64.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
from daemodel.backends.radau.linalg import BandOrder, band_storage

# The band kernel is used where the band storage (LDAB rows) is at most this many entries a column: its
# elimination is dense in the band (kl (kl + ku) multiply-adds a column), where SuperLU's follows the
# nonzeros; reaction-diffusion's band order has LDAB 7 (kl = ku = 2), the chain's 19
BAND_KERNEL_MAX_LDAB = 40
# Factors' buffers kept for reuse, of each kind (real, complex), once their factors are dropped: a fresh
# buffer of 10-20 MB (10^5 unknowns) is new pages, and faulting them in took 2-3x the factorisation
# itself on a loaded machine (complex: 10.7-34 ms against 6.2 on reused memory).  At least this many;
# a solve reserves what one factorisation holds, made in its setup (BandKernel.reserve): the stepper drops
# its factors before it factors anew (.step.Stepper.current_lu), so the next ones are made in their buffers
BAND_SPARE_BUFFERS = 1
# Unknowns from which a band solve reads the caller's right-hand side and writes its solution where they lie
# (BandSolver): below, copies into and out of a thread's own arrays cost less than binding the caller's (two
# casadi bindings a call, ~2.4 us each); from 10^4 unknowns a copy is ~10 us, and the arrays 2 x 16 D bytes
BAND_SOLVE_IN_PLACE_MIN = 10_000
# C flags (the cache adds a shared library's): the loops are short, -O2 is enough
BAND_FLAGS = ("-O2", "-fno-math-errno")
# Seconds the compiler may take (the source is ~150 lines)
BAND_COMPILE_TIMEOUT = 120.0

_KERNEL = r"""
#ifndef casadi_int
#define casadi_int long long int
#endif
#define KV (KL + KU)
#define AT(r, j) ((r) + (casadi_int)LDAB * (j))
#define MIN(a, b) ((a) < (b) ? (a) : (b))

/* Each argument and result is declared as one entry: casadi keeps a dense vector's row indices (8 bytes an entry,
   30 MB for their six sizes at 10^5 unknowns, as long as the functions live); the sizes are this source's numbers,
   the buffers Python's (band.py: FunctionBuffer takes any buffer at least as large as declared) */
static const casadi_int sp_one[3] = {1, 1, 1};

/* The packed factors (C = 1 real, 2 complex doubles an entry):
   [values (C LDAB N_D: the band while factoring, then each column's nonzeros, L's then U's, diagonal first)]
   [pivots (N_D)] [info: 0, j + 1 at a zero pivot in column j, -1 at a value not finite]
   [bytes: each column's counts of L and U entries (2 N_D), then each entry's distance from the diagonal] */
/* The matrix into the zeroed band storage: its CSC values (arg 0) at their positions (arg 1); or (SHIFTED) sigma M - J
   from J's values (arg 0), their positions (arg 1), M's diagonal's positions (arg 2) and [Re sigma, Im sigma, J's and
   M's counts] (arg 3): -J placed, then sigma added at M's, the operations of .sparse.factor_shifts' numpy */
#define VALUES(C)                                                                                        \
  for (q = 0; q < N_NZ; q++)                                                                             \
    for (c = 0; c < C; c++) ab[C * (casadi_int)((const INDEX*)arg[1])[q] + c] = arg[0][C * q + c];
#define SHIFTED(C)                                                                                       \
  {                                                                                                      \
    const INDEX *at_J = (const INDEX*)arg[1], *at_M = (const INDEX*)arg[2];                              \
    const double* s = arg[3];                                                                            \
    casadi_int n_J = (casadi_int)s[2], n_M = (casadi_int)s[3];                                           \
    for (q = 0; q < n_J; q++) ab[C * (casadi_int)at_J[q]] = -arg[0][q];                                  \
    for (q = 0; q < n_M; q++)                                                                            \
      for (c = 0; c < C; c++) ab[C * (casadi_int)at_M[q] + c] += s[c];                                   \
  }
#define FACTOR(NAME, C, ISZERO, ABS1, DIVIDE, UPDATE, FILL)                                               \
int NAME(const double** arg, double** res, casadi_int* iw, double* w, int mem) {                        \
  double* ab = res[0];                                                                                   \
  double* piv = ab + C * (casadi_int)LDAB * N_D;                                                        \
  unsigned char* count = (unsigned char*)(piv + N_D + 1);                                                \
  unsigned char* dist = count + 2 * (casadi_int)N_D;                                                     \
  casadi_int q, j, r, c, jp, km, ju = 0, info = 0, p = 0, e = 0;                                        \
  double column[C * LDAB], check = 0.0;                                                                  \
  if (!ab) return 0;                                                                                     \
  for (q = 0; q < C * (casadi_int)LDAB * N_D; q++) ab[q] = 0.0;                                         \
  FILL(C)                                                                                                \
  for (j = 0; j < N_D; j++) {                                                                            \
    double big = -1.0, t;                                                                                \
    km = MIN(KL, N_D - 1 - j);                                                                           \
    jp = 0;                                                                                              \
    for (r = 0; r <= km; r++) {                                                                          \
      const double* a = ab + C * AT(KV + r, j);                                                          \
      t = ABS1(a);                                                                                       \
      if (t > big) { big = t; jp = r; }                                                                  \
    }                                                                                                    \
    piv[j] = (double)(j + jp);                                                                           \
    if (!ISZERO(ab + C * AT(KV + jp, j))) {                                                              \
      ju = j + KU + jp < N_D - 1 ? (j + KU + jp > ju ? j + KU + jp : ju) : N_D - 1;                      \
      if (jp != 0)                                                                                       \
        for (c = j; c <= ju; c++)                                                                        \
          for (q = 0; q < C; q++) {                                                                      \
            casadi_int u = C * AT(KV + j - c, c) + q, v = C * AT(KV + j + jp - c, c) + q;                \
            t = ab[u]; ab[u] = ab[v]; ab[v] = t;                                                         \
          }                                                                                              \
      for (r = 1; r <= km; r++) DIVIDE(ab + C * AT(KV + r, j), ab + C * AT(KV, j));                      \
      for (c = j + 1; c <= ju; c++) {                                                                    \
        const double* u = ab + C * AT(KV + j - c, c);                                                    \
        if (!ISZERO(u))                                                                                  \
          for (r = 1; r <= km; r++) UPDATE(ab + C * AT(KV + j + r - c, c), ab + C * AT(KV + r, j), u);   \
      }                                                                                                  \
    } else if (!info) {                                                                                  \
      info = j + 1;                                                                                      \
    }                                                                                                    \
  }                                                                                                      \
  /* each column's nonzeros, in place (a column is read whole before it is written: p <= LDAB j) */     \
  for (j = 0; j < N_D; j++) {                                                                            \
    casadi_int lower = 0, upper = 0, top = MIN(KV, j);                                                   \
    km = MIN(KL, N_D - 1 - j);                                                                           \
    for (q = 0; q < C * LDAB; q++) column[q] = ab[C * AT(0, j) + q];                                     \
    for (r = 1; r <= km; r++)                                                                            \
      if (!ISZERO(column + C * (KV + r))) {                                                              \
        for (q = 0; q < C; q++) ab[C * p + q] = column[C * (KV + r) + q];                                \
        p++; dist[e++] = (unsigned char)r; lower++;                                                      \
      }                                                                                                  \
    for (r = 0; r <= top; r++)                                                                           \
      if (r == 0 || !ISZERO(column + C * (KV - r))) {                                                    \
        for (q = 0; q < C; q++) { ab[C * p + q] = column[C * (KV - r) + q]; check += 0.0 * ab[C * p + q]; } \
        p++; dist[e++] = (unsigned char)r; upper++;                                                      \
      }                                                                                                  \
    for (r = 1; r <= km; r++) check += 0.0 * column[C * (KV + r)];                                       \
    count[2 * j] = (unsigned char)lower;                                                                 \
    count[2 * j + 1] = (unsigned char)upper;                                                             \
  }                                                                                                      \
  piv[N_D] = check != check ? -1.0 : (double)info;                                                       \
  return 0;                                                                                              \
}

#define R_ISZERO(a) ((a)[0] == 0.0)
#define R_ABS1(a) fabs((a)[0])
#define R_DIVIDE(a, d) ((a)[0] /= (d)[0])
#define R_UPDATE(a, l, u) ((a)[0] -= (l)[0] * (u)[0])
#define C_ISZERO(a) ((a)[0] == 0.0 && (a)[1] == 0.0)
#define C_ABS1(a) (fabs((a)[0]) + fabs((a)[1]))
static void c_divide(double* a, const double* d) {
  double m = d[0] * d[0] + d[1] * d[1], ir = d[0] / m, ii = -d[1] / m, ar = a[0], ai = a[1];
  a[0] = ar * ir - ai * ii;
  a[1] = ar * ii + ai * ir;
}
static void c_update(double* a, const double* l, const double* u) {
  a[0] -= l[0] * u[0] - l[1] * u[1];
  a[1] -= l[0] * u[1] + l[1] * u[0];
}
FACTOR(band_factor, 1, R_ISZERO, R_ABS1, R_DIVIDE, R_UPDATE, VALUES)
FACTOR(band_factor_complex, 2, C_ISZERO, C_ABS1, c_divide, c_update, VALUES)
FACTOR(band_factor_shifted, 1, R_ISZERO, R_ABS1, R_DIVIDE, R_UPDATE, SHIFTED)
FACTOR(band_factor_shifted_complex, 2, C_ISZERO, C_ABS1, c_divide, c_update, SHIFTED)

/* x = A^-1 b, b and x in the unknowns' own order (order[k]: the unknown at the band's k-th place) */
static void solve_real(const double* f, const double* b, const INDEX* order, double* x, double* out) {
  const double* piv = f + (casadi_int)LDAB * N_D;
  const unsigned char* count = (const unsigned char*)(piv + N_D + 1);
  const unsigned char* dist = count + 2 * (casadi_int)N_D;
  casadi_int i, j, k, p = 0;
  for (i = 0; i < N_D; i++) x[i] = b[(casadi_int)order[i]];
  for (j = 0; j < N_D; j++) {
    casadi_int l = (casadi_int)piv[j], lower = count[2 * j];
    double t;
    if (l != j) { t = x[l]; x[l] = x[j]; x[j] = t; }
    t = x[j];
    for (k = 0; k < lower; k++) x[j + dist[p + k]] -= f[p + k] * t;
    p += lower + count[2 * j + 1];
  }
  for (j = N_D - 1; j >= 0; j--) {
    casadi_int upper = count[2 * j + 1];
    double t;
    p -= upper;
    t = x[j] / f[p];
    x[j] = t;
    for (k = 1; k < upper; k++) x[j - dist[p + k]] -= f[p + k] * t;
    p -= count[2 * j];
  }
  for (i = 0; i < N_D; i++) out[(casadi_int)order[i]] = x[i];
}

static void solve_complex(const double* f, const double* b, const INDEX* order, double* x, double* out) {
  const double* piv = f + 2 * (casadi_int)LDAB * N_D;
  const unsigned char* count = (const unsigned char*)(piv + N_D + 1);
  const unsigned char* dist = count + 2 * (casadi_int)N_D;
  casadi_int i, j, k, p = 0;
  for (i = 0; i < N_D; i++) {
    x[2 * i] = b[2 * (casadi_int)order[i]];
    x[2 * i + 1] = b[2 * (casadi_int)order[i] + 1];
  }
  for (j = 0; j < N_D; j++) {
    casadi_int l = (casadi_int)piv[j], lower = count[2 * j];
    double t[2];
    if (l != j) {
      t[0] = x[2 * l]; x[2 * l] = x[2 * j]; x[2 * j] = t[0];
      t[1] = x[2 * l + 1]; x[2 * l + 1] = x[2 * j + 1]; x[2 * j + 1] = t[1];
    }
    t[0] = x[2 * j];
    t[1] = x[2 * j + 1];
    for (k = 0; k < lower; k++) c_update(x + 2 * (j + dist[p + k]), f + 2 * (p + k), t);
    p += lower + count[2 * j + 1];
  }
  for (j = N_D - 1; j >= 0; j--) {
    casadi_int upper = count[2 * j + 1];
    p -= upper;
    c_divide(x + 2 * j, f + 2 * p);
    for (k = 1; k < upper; k++) c_update(x + 2 * (j - dist[p + k]), f + 2 * (p + k), x + 2 * j);
    p -= count[2 * j];
  }
  for (i = 0; i < N_D; i++) {
    out[2 * (casadi_int)order[i]] = x[2 * i];
    out[2 * (casadi_int)order[i] + 1] = x[2 * i + 1];
  }
}

int band_solve(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  if (res[0]) solve_real(arg[0], arg[1], (const INDEX*)arg[2], w, res[0]);
  return 0;
}

int band_solve_complex(const double** arg, double** res, casadi_int* iw, double* w, int mem) {
  if (res[0]) solve_complex(arg[0], arg[1], (const INDEX*)arg[2], w, res[0]);
  return 0;
}

#define SIGNATURE(name, n, work)                                                                         \
  casadi_int name##_n_in(void) { return n; }                                                             \
  casadi_int name##_n_out(void) { return 1; }                                                            \
  const casadi_int* name##_sparsity_in(casadi_int i) { return i < n ? sp_one : 0; }                      \
  const casadi_int* name##_sparsity_out(casadi_int i) { return i == 0 ? sp_one : 0; }                    \
  int name##_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {         \
    if (sz_arg) *sz_arg = n;                                                                              \
    if (sz_res) *sz_res = 1;                                                                              \
    if (sz_iw) *sz_iw = 0;                                                                                \
    if (sz_w) *sz_w = work;                                                                               \
    return 0;                                                                                             \
  }
SIGNATURE(band_factor, 2, 0)
SIGNATURE(band_factor_complex, 2, 0)
SIGNATURE(band_factor_shifted, 4, 0)
SIGNATURE(band_factor_shifted_complex, 4, 0)
SIGNATURE(band_solve, 3, N_D)
SIGNATURE(band_solve_complex, 3, 2 * N_D)
"""

NAMES = (
    "band_factor",
    "band_factor_complex",
    "band_factor_shifted",
    "band_factor_shifted_complex",
    "band_solve",
    "band_solve_complex",
)


def band_widths(indices: np.ndarray, indptr: np.ndarray) -> tuple[int, int]:
    """``(kl, ku)``: the lower and upper band widths of the CSC pattern ``(indices, indptr)``."""
    columns = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    offset = indices - columns  # (row - column)
    return int(max(offset.max(initial=0), 0)), int(max(-offset.min(initial=0), 0))


def band_entries(order: BandOrder | None, rows: np.ndarray, cols: np.ndarray, n: int, D: int) -> int | None:
    """The float64 entries one real system's :class:`BandKernel` factors take (LDAB x D, the pivots and
    the entries' positions; a complex system's values take twice LDAB x D) for the Jacobian pattern
    ``(rows, cols)`` (and M's diagonal over the ``n`` differential unknowns) in the band ``order``, or
    None where :func:`band_kernel` would take none (no order, or a band wider than
    :data:`BAND_KERNEL_MAX_LDAB`): what the memory guard counts."""
    if order is None:
        return None
    ldab = band_storage(order, rows, cols)
    return ldab * D + D + 1 + -(-(2 + ldab) * D // 8) if ldab <= BAND_KERNEL_MAX_LDAB else None


def band_source(D: int, nnz: int, kl: int, ku: int) -> str:
    """The C source of :data:`NAMES` (casadi's external-function interface) for ``D`` unknowns, ``nnz``
    matrix entries and the band widths ``kl``, ``ku``: numbers only."""
    ldab = 2 * kl + ku + 1
    sizes = {"N_D": D, "N_NZ": nnz, "KL": kl, "KU": ku, "LDAB": ldab}
    sizes["INDEX"] = "int" if band_index(D, ldab) == np.int32 else "long long int"
    head = ["/* daemodel: radau's band LU (generated; numbers only) */\n#include <math.h>\n"]
    return "".join(head + [f"#define {key} {value}\n" for key, value in sizes.items()]) + _KERNEL


def band_index(D: int, ldab: int):
    """The integer type of the kernel's positions in the band storage and of its order (its C ``INDEX``):
    int32 where the storage's LDAB x D entries are within its range, else int64."""
    return np.int32 if ldab * D <= np.iinfo(np.int32).max else np.int64


def _bound(function, inputs: list, output: np.ndarray):
    """casadi's FunctionBuffer of ``function`` on the numpy arrays ``inputs`` and ``output`` (no copies):
    its ``evaluate``; the arrays must outlive it (the caller keeps them)."""
    buffer, evaluate = function.buffer()
    for k, values in enumerate(inputs):
        buffer.set_arg(k, memoryview(values))
    buffer.set_res(0, memoryview(output))

    def call():
        evaluate()
        if buffer.ret() != 0:
            raise RuntimeError(f"casadi function {function.name()} failed (return code {buffer.ret()})")

    return call


class BandKernel:
    """The band LU of the shifted systems of one CSC layout (``indices``, ``indptr``: the matrix in its
    band order, :func:`.sparse.shifted_layout`), compiled by ``compiler``; ``order``: the band order
    (:class:`.linalg.BandOrder`: equation ``order.rows[k]`` is the k-th row, unknown ``order.columns[k]``
    the k-th column).  :meth:`factor` takes the matrix's CSC values.
    Raises :class:`~daemodel.errors.CompileError` where the compiler fails."""

    def __init__(self, order: BandOrder, indices: np.ndarray, indptr: np.ndarray, compiler: str):
        from daemodel.cache import Build, cached_library

        self.order, self.D, self.nnz = order, len(indptr) - 1, len(indices)
        self.kl, self.ku = band_widths(indices, indptr)
        self.ldab = 2 * self.kl + self.ku + 1
        what = "radau's machine code: compiling the band factors"
        fix = "solve with jit=False (SuperLU's factors: the same results to rounding)"
        build = Build(compiler, BAND_FLAGS, what, fix, libraries=("-lm",), timeout=BAND_COMPILE_TIMEOUT)
        library = cached_library(band_source(self.D, self.nnz, self.kl, self.ku), NAMES, build)
        self.outcome, self.functions = library.outcome, library.functions
        self._spare = {False: [], True: []}  # (buffers of dropped factors, up to _kept of each kind)
        self._kept = {False: BAND_SPARE_BUFFERS, True: BAND_SPARE_BUFFERS}
        index = band_index(self.D, self.ldab)  # (the C's INDEX: int32 where LDAB x D fits, half of float64's bytes)
        # (one entry more, never read: casadi takes a buffer of at least the 8 bytes of the one entry declared)
        self.positions = np.r_[self._places(indices, indptr), 0].astype(index)
        self.order_values = np.r_[order.columns, 0].astype(index)
        self._buffers = threading.local()  # (each thread's solvers: solver)
        # (the kernel reads b[columns[k]] into its k-th row, where equation rows[k]'s value belongs: b = rhs[match])
        self.match = order.match

    def _places(self, indices: np.ndarray, indptr: np.ndarray) -> np.ndarray:
        """The band storage's positions of the CSC layout's entries (int64: the columns' arange)."""
        columns = np.repeat(np.arange(self.D), np.diff(indptr))
        return self.kl + self.ku + indices - columns + self.ldab * columns

    def made_for(self, indices: np.ndarray, indptr: np.ndarray) -> bool:
        """Whether the CSC layout ``(indices, indptr)`` is the one this kernel was made for (its positions): a
        model's kernel is made once, from the first layout of its shifted systems (:func:`band_factors`)."""
        if len(indptr) - 1 != self.D or len(indices) != self.nnz or band_widths(indices, indptr) != (self.kl, self.ku):
            return False
        return bool(np.array_equal(self._places(indices, indptr), self.positions[:-1]))

    def solver(self, complex_: bool) -> BandSolver:
        """This thread's :class:`BandSolver` of the kernel's real or complex solve (made once a thread; a buffer made
        for each system's factors was, with its casadi work array of D values, 0.8-1.6 MB of casadi's heap a
        factorisation at 10^5 unknowns)."""
        solvers = getattr(self._buffers, "solvers", None)
        if solvers is None:
            solvers = self._buffers.solvers = {}
        if complex_ not in solvers:
            solvers[complex_] = BandSolver(self, complex_)
        return solvers[complex_]

    def gather(self, rhs: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``b[:] = rhs[match]`` (:attr:`match`): the right-hand side in the band's row order."""
        if rhs.dtype == b.dtype:
            return np.take(rhs, self.match, out=b)
        b[:] = rhs[self.match]  # (a real right-hand side on complex factors: np.take's out= takes its own dtype only)
        return b

    @property
    def entries(self) -> int:
        """The entries one system's factors hold: the band storage (LDAB x D)."""
        return self.ldab * self.D

    def factor(self, data: np.ndarray):
        """``(("sparse", BandLU), singular (1,))`` for the CSC values ``data`` (float or complex, in the
        layout's order), or ``(("singular",), [True])`` where a pivot is exactly zero or not finite."""
        complex_ = np.iscomplexobj(data)
        values = np.ascontiguousarray(data, dtype=complex if complex_ else float).view(float)
        if values.size != (2 if complex_ else 1) * self.nnz:  # (the C reads N_NZ of them: its interface, one entry)
            raise ValueError(f"the band factors take {self.nnz} matrix entries, got {data.size}")
        return self._factored("band_factor_complex" if complex_ else "band_factor", [values, self.positions], complex_)

    def factor_shifted(self, values: np.ndarray, sigma: complex, pos_J: np.ndarray, pos_M: np.ndarray):
        """:meth:`factor` of ``sigma M - J`` from J's nonzeros ``values`` placed at ``pos_J`` of the layout and
        sigma added at M's ``pos_M`` (:func:`.sparse.shifted_layout`'s), in the kernel's C: the values of
        :func:`.sparse.factor_shifts`' numpy, without its copies of -J and of each shift's values (2.4 and 4.8 MB
        at 10^5 unknowns of reaction-diffusion, s = 5)."""
        if values.size != pos_J.size:
            raise ValueError(f"the band factors take {pos_J.size} Jacobian entries, got {values.size}")
        at = self._shifted_positions(pos_J, pos_M)
        complex_ = sigma.imag != 0
        scalars = np.array([sigma.real, sigma.imag, pos_J.size, pos_M.size], dtype=float)
        name = "band_factor_shifted_complex" if complex_ else "band_factor_shifted"
        values = np.ascontiguousarray(values, dtype=float)
        if not values.size:  # (J without entries: casadi takes at least its one entry's 8 bytes; the C reads none)
            values = np.zeros(1)
        return self._factored(name, [values, *at, scalars], complex_)

    def _shifted_positions(self, pos_J: np.ndarray, pos_M: np.ndarray) -> tuple:
        """The band storage's positions of J's and M's entries (:meth:`factor_shifted`), made once per layout."""
        # (two trailing entries, never read: casadi takes a buffer of at least its one entry's 8 bytes, two int32s
        # where J or M has no entry)
        # (the tuple this call checked or made, not self._at read again: a solve in another thread may have put
        # another layout's there in between)
        at = getattr(self, "_at", (None, None))
        if at[0] is not pos_J or at[1] is not pos_M:  # (the layout's own arrays, kept here: identity is enough)
            at = self._at = (
                pos_J,
                pos_M,
                *(np.r_[self.positions[p], 0, 0].astype(self.positions.dtype) for p in (pos_J, pos_M)),
            )
        return at[2:]

    def _factored(self, name: str, inputs: list, complex_: bool):
        """The factors the kernel's ``name`` makes of ``inputs`` in a spare buffer (see :meth:`factor`)."""
        band = (2 if complex_ else 1) * self.ldab * self.D
        spare = self._spare[complex_]
        try:  # (none kept, or another thread took the last one since a check: a new buffer, not IndexError)
            packed = spare.pop()
        except IndexError:
            packed = np.empty(self._size(complex_))
        _bound(self.functions[name], inputs, packed)()
        if packed[band + self.D] != 0:  # (a zero pivot, or a value not finite)
            self._keep(packed, complex_)
            return ("singular",), np.array([True])
        lu = BandLU(self, packed, complex_)
        weakref.finalize(lu, self._keep, packed, complex_)  # (its buffer is reused once it is dropped)
        return ("sparse", lu), np.array([False])

    def _size(self, complex_: bool) -> int:
        """The float64 entries of one system's packed factors (:data:`_KERNEL`'s layout)."""
        return (2 if complex_ else 1) * self.ldab * self.D + self.D + 1 + -(-(2 + self.ldab) * self.D // 8)

    def reserve(self, counts: dict) -> None:
        """Keep ``counts[complex_]`` buffers of each kind ready, their pages written now (a solve's setup:
        what one factorisation holds; the stepper drops its factors before it factors anew), and keep as
        many once dropped: the first solve of a process faulted in ~56 MB of them at 10^5 unknowns (s = 5,
        two factorisations' then), and each later one half of that, in its integration."""
        for complex_, count in counts.items():
            self._kept[complex_] = max(self._kept[complex_], count)
            spare = self._spare[complex_]
            for _ in range(count - len(spare)):
                spare.append(np.zeros(self._size(complex_)))
                spare[-1].fill(0.0)  # (np.zeros leaves large arrays to the kernel's zero pages, faulted at first write)

    def _keep(self, packed: np.ndarray, complex_: bool) -> None:
        """Keep a dropped factors' buffer for the next factorisation (up to :meth:`reserve`'s counts, at least
        :data:`BAND_SPARE_BUFFERS`)."""
        if len(self._spare[complex_]) < self._kept[complex_]:
            self._spare[complex_].append(packed)


class BandSolver:
    """One thread's call of a :class:`BandKernel`'s real or complex solve (casadi's FunctionBuffer, the band order on
    its third argument, bound once).  Below :data:`BAND_SOLVE_IN_PLACE_MIN` unknowns its right-hand side and
    solution are its own arrays, bound once, and a solve copies in and out (two bindings a call cost more than the
    copies there: 28 against 19 us a complex solve at 10^3 unknowns); from it, a solve binds the caller's arrays, its
    right-hand side where the band needs no row order and its ``out``, and copies nothing (at 10^5 unknowns, s = 5,
    Newton's increment made 108 arrays of 0.8-1.6 MB a solve, and the copies were 3.2 MB of buffers)."""

    def __init__(self, kernel: BandKernel, complex_: bool):
        self.name = "band_solve_complex" if complex_ else "band_solve"
        self.buffer, self.evaluate = kernel.functions[self.name].buffer()
        self.buffer.set_arg(2, memoryview(kernel.order_values))  # (kept by the kernel)
        self.b = self.x = self._gathered = None
        self.D, self.dtype = kernel.D, np.dtype(complex if complex_ else float)
        if kernel.D < BAND_SOLVE_IN_PLACE_MIN:
            self.b, self.x = np.empty(kernel.D, dtype=self.dtype), np.empty(kernel.D, dtype=self.dtype)
            self.buffer.set_arg(1, memoryview(self.b.view(float)))
            self.buffer.set_res(0, memoryview(self.x.view(float)))

    @property
    def gathered(self) -> np.ndarray:
        """An array for a right-hand side in the band's row order (:meth:`BandKernel.gather`), made at first use, which
        the next solve overwrites (the solver's own :attr:`b` where it has one)."""
        if self.b is not None:
            return self.b
        if self._gathered is None:
            self._gathered = np.empty(self.D, dtype=self.dtype)
        return self._gathered

    def __call__(self, packed: memoryview, b: np.ndarray | None = None, out: np.ndarray | None = None) -> None:
        """Solve with the factors ``packed``: for :attr:`b` into :attr:`x` where it has them (few unknowns), else for
        ``b`` into ``out`` (both C-contiguous, of the factors' dtype).  Every array a call reads or writes is bound
        before it runs (the buffer keeps pointers, not arrays, between calls)."""
        buffer = self.buffer
        if (b is None) != (self.b is not None):
            raise ValueError(f"{self.name}: b and out are given to a solver without arrays of its own, and only to one")
        buffer.set_arg(0, packed)
        if b is not None:
            buffer.set_arg(1, memoryview(b.view(float)))
            buffer.set_res(0, memoryview(out.view(float)))
        self.evaluate()
        if buffer.ret() != 0:
            raise RuntimeError(f"casadi function {self.name} failed (return code {buffer.ret()})")


class BandLU:
    """One system's band factors (``packed``: :class:`BandKernel`'s output), solving with ``A`` (its
    unknowns in their own order: the band order is applied on the way in and out)."""

    def __init__(self, kernel: BandKernel, packed: np.ndarray, complex_: bool):
        self.kernel, self.complex, self.packed = kernel, complex_, packed
        self.dtype = np.dtype(complex if complex_ else float)
        self._packed = memoryview(packed)  # (bound for each solve: BandSolver)

    def solve(self, rhs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``x`` with ``A x = rhs``, ``rhs`` of shape (D,) (complex on a real system: by parts); in ``out`` where
        given (C-contiguous, of the solution's dtype), which may be ``rhs`` itself: the kernel reads the right-hand
        side whole before it writes the solution (:class:`BandSolver`: from BAND_SOLVE_IN_PLACE_MIN unknowns it
        reads ``rhs`` where it lies, where the band needs no row order, and writes ``out``, with no copies)."""
        kernel, D = self.kernel, self.kernel.D
        if np.iscomplexobj(rhs) and not self.complex:
            return solved_in(self.solve(rhs.real) + 1j * self.solve(rhs.imag), out)
        if rhs.shape != (D,):
            raise ValueError(f"the band factors solve for right-hand sides of shape ({D},), got {rhs.shape}")
        if out is not None and (
            out.dtype != self.dtype or out.shape != (D,) or not (out.flags.c_contiguous and out.flags.writeable)
        ):
            raise ValueError(f"a solve's out= is {out.dtype} {out.shape}, its solution {self.dtype} ({D},)")
        solver = kernel.solver(self.complex)  # (the band order applied inside, on the way in and out)
        if solver.b is not None:  # (few unknowns: in its own arrays, copied in and out)
            if kernel.match is None:
                solver.b[:] = rhs
            else:
                kernel.gather(rhs, solver.gathered)
            solver(self._packed)
            return solver.x.copy() if out is None else solved_in(solver.x, out)
        out = np.empty(D, dtype=self.dtype) if out is None else out
        if kernel.match is not None:
            b = kernel.gather(rhs, solver.gathered)
        else:
            b = rhs if rhs.dtype == self.dtype and rhs.flags.c_contiguous else np.ascontiguousarray(rhs, self.dtype)
        solver(self._packed, b, out)
        return out


def solved_in(x: np.ndarray, out: np.ndarray | None) -> np.ndarray:
    """``x``, or ``out`` with its values where given (of ``x``'s dtype and shape: a solution is not cast)."""
    if out is None:
        return x
    if out.dtype != x.dtype or out.shape != x.shape:
        raise ValueError(f"a solve's out= is {out.dtype} {out.shape}, its solution {x.dtype} {x.shape}")
    np.copyto(out, x)
    return out


def band_kernel(order, indices, indptr, compiler: str | None) -> BandKernel | None:
    """The :class:`BandKernel` of a layout in its band ``order``, or None: without an order or a
    compiler, where the band is wider than :data:`BAND_KERNEL_MAX_LDAB` (SuperLU factors it), or where
    the compiler fails (SuperLU then, as with ``jit=False``)."""
    from daemodel.errors import CompileError

    if order is None or compiler is None:
        return None
    kl, ku = band_widths(indices, indptr)
    if 2 * kl + ku + 1 > BAND_KERNEL_MAX_LDAB:
        return None
    try:
        return BandKernel(order, indices, indptr, compiler)
    except CompileError:
        return None


def band_factors(compiled, order, layout: tuple, outcomes: list):
    """The factoriser of a model's shifted systems for :func:`.linalg.sparse_lu`: its :class:`BandKernel`
    (:func:`band_kernel`, made once per model) where there is one, else ``order`` itself (SuperLU in
    the band order, or in its own where ``order`` is None); what the disk cache did is added to
    ``outcomes`` ("memory" where this process made it before)."""
    from daemodel.backends.radau.compiled import find_compiler

    if order is None:
        return order
    made = []

    def build():
        made.append(band_kernel(order, layout[0], layout[1], find_compiler()))
        return made[-1]

    kernel = compiled.cached("radau-band-kernel", build)
    if kernel is None:
        return order
    if not kernel.order.same(order):  # (another order than the model's own: not its kernel)
        return order
    if not made and not kernel.made_for(layout[0], layout[1]):  # (another pattern's layout: its positions are not
        return order  # these, and the C would place J's values wrongly; SuperLU in the order then)
    outcomes.append(kernel.outcome if made else "memory")
    return kernel
