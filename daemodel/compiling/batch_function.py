"""The batched numeric functions of a :class:`~daemodel.compiling.init.NumericSystem`: numpy's lambdified code
for batches, casadi's virtual machine for a few samples.  numpy pays ~1 us of dispatch per operation whatever
the batch, so one sample of the wheelset's determining equations (12 of them, ~1400 operations) took 1.3 ms
there against 6 us on a casadi function evaluated on bound buffers; the wheelset's solve evaluates such
functions at one sample ~20,000 times (the algebraic values after each event, the look-ahead's flow) and at
the two ends of each of its ~2,300 trial solves (the branch check).  Each is made at its first use (a locked
piece's functions are often only ever evaluated at one sample: their numpy code, 70 ms each to print, is
then never made); casadi's never for expressions it cannot express (the Heaviside of a Max's derivative),
which numpy evaluates at any batch."""

from __future__ import annotations

import threading
import time

import numpy as np
import sympy as sp

from daemodel.errors import UnsupportedFunctionError

# Up to this many samples casadi evaluates a function one sample at a time (~5-10 us each on the wheelset's
# equations), above it numpy on all at once (~0.6-1.3 ms, nearly whatever their number up to hundreds).
SAMPLE_ROWS = 4
# Above SAMPLE_ROWS and up to CASADI_ROWS_MAX samples, casadi still evaluates them one at a time where that
# costs less than numpy on all at once, by a model of the two costs in the casadi function's instructions I:
# a sample on casadi ~CASADI_ROW_US + CASADI_INSTRUCTION_US * I microseconds, numpy's call on all of them
# ~NUMPY_INSTRUCTION_US * I (one array operation an instruction: 0.2-0.45 us measured, the lower end taken).
# At 21 samples (idle 2-core machine), numpy against casadi: the pendulum's determining equation (I = 19)
# 5.7 against 21.8 us; the car axis's (174) 78 against 27.5; 20 and 40 pendulums' (904, 1,824) 283 and 567
# against 42.5 and 60, and the 20 pendulums' branch check (585) 196 against 35; reaction-diffusion's
# branch checks at 100 and 200 unknowns (51, 101: an entry each) 10.5 and 19.7 against 23.0 and 24.6 (stay
# on numpy).  The branch check and the algebraic variables solved again at the outputs evaluate at every
# output time.
CASADI_ROWS_MAX = 256
CASADI_ROW_US = 1.0
CASADI_INSTRUCTION_US = 0.001
NUMPY_INSTRUCTION_US = 0.2
# Functions of more expressions than this stay on numpy at any batch: their conversion to casadi, one
# expression at a time, grows with them (~25 us a node through casadi's Python binding: seconds for the
# 10^4-10^5 equations of a discretised PDE, whose numpy code, printed once per shape, evaluates in ms).
SAMPLE_EXPRESSIONS = 256


# Seconds each thread has spent making the functions' code at their first use, and those a clock has claimed.
_MADE = threading.local()


def generating_seconds() -> float:
    """Seconds this thread has spent making :class:`BatchFunction` code at its first use (numpy's lambdified
    code, casadi's function) that no clock has claimed yet (:func:`claim_generated`): one-off work that a
    solve counts as setup wherever it ran (the events' numpy code, 40 ms of the bouncing ball's first radau
    solve, was on its solve clock)."""
    return getattr(_MADE, "seconds", 0.0) - getattr(_MADE, "claimed", 0.0)


def claim_generated(since: float) -> float:
    """The seconds of code made since :func:`generating_seconds` read ``since`` that no clock inside has
    claimed, claimed now (a caller adds them to its setup; one around it does not count them again)."""
    seconds = generating_seconds() - since
    _MADE.claimed = getattr(_MADE, "claimed", 0.0) + seconds
    return seconds


def made_since(began: float) -> None:
    """Counts the seconds since ``began`` (a ``time.perf_counter()``) as code made at its first use
    (:func:`generating_seconds`): for other functions made so, such as :func:`.algebraic.affine_step`'s."""
    _MADE.seconds = getattr(_MADE, "seconds", 0.0) + time.perf_counter() - began


def on_casadi(rows: int, instructions: int) -> bool:
    """Whether ``rows`` samples of a function of ``instructions`` casadi instructions cost less one at a time on
    casadi than all at once on numpy (always up to :data:`SAMPLE_ROWS`; see :data:`CASADI_ROWS_MAX`)."""
    if rows <= SAMPLE_ROWS:
        return True
    casadi = rows * (CASADI_ROW_US + CASADI_INSTRUCTION_US * instructions)
    return rows <= CASADI_ROWS_MAX and casadi < NUMPY_INSTRUCTION_US * instructions


class BatchFunction:
    """``F(t, Y (B, n), Z (B, m), P (B, k)) -> ndarray (B, len(exprs))``; ``t`` a number or (B,), and ``Z``,
    ``P`` of one row broadcast to ``Y``'s.  On casadi, one sample at a time, up to :data:`SAMPLE_ROWS`
    samples of at most :data:`SAMPLE_EXPRESSIONS` expressions and up to :data:`CASADI_ROWS_MAX` where that
    costs less (:func:`on_casadi`), else on numpy.

    Parameters
    ----------
    exprs : list of sympy.Expr
    symbols : tuple
        ``(t, y, z, p)``: the time and the variables, in the order of the columns of ``Y``, ``Z``, ``P``.
    lambdify : callable
        ``lambdify(exprs)``: the numpy function of ``(t, Y.T, Z.T, P.T)`` (made on first use: :meth:`numpy`).
    """

    def __init__(self, exprs, symbols: tuple, lambdify):
        self._exprs, self._symbols, self._lambdify = list(exprs), symbols, lambdify
        self._numpy = None
        self._casadi = None  # (casadi.Function of [t, y, z, p], dense; False where casadi cannot express it)
        self._instructions = 0  # (its instruction count: on_casadi)
        self._local = threading.local()  # (each thread's buffers: a call writes its inputs into them)

    def __call__(self, t, Y: np.ndarray, Z: np.ndarray, P: np.ndarray, contiguous: bool = True) -> np.ndarray:
        """The expressions' values at each row of ``(t, Y, Z, P)``, shape (rows, expressions); ``contiguous``
        False: perhaps a transposed view, not the C-ordered copy (the branch check's 4.4 MB at 10^5 unknowns)."""
        if not self._exprs:
            return np.zeros((len(Y), 0))
        if len(Y) <= CASADI_ROWS_MAX and len(self._exprs) <= SAMPLE_EXPRESSIONS:
            if self._casadi is None:
                began = time.perf_counter()
                self._casadi = self._convert()
                self._instructions = self._casadi.n_instructions() if self._casadi is not False else 0
                made_since(began)
            # (non-finite inputs go to numpy, whose arithmetic on them is the reference)
            if (
                self._casadi is not False
                and on_casadi(len(Y), self._instructions)
                and all(np.isfinite(v).all() for v in (t, Y, Z, P))
            ):
                return self._few(t, Y, Z, P)
        # t as a column like the others: numpy's select (Piecewise) refuses conditions of mixed shapes
        t = np.asarray(t, dtype=float)
        t = t if t.shape == (len(Y),) else np.broadcast_to(t, (len(Y),))  # (a column already: as it is)
        # (each a row, contiguous, converted to float by the assignment itself, then one transposed
        # copy: a column each, through np.asarray, took 36 us of the 60 H_z entries of a chain of 20
        # pendulums at 21 output times, in every solve's branch check, against 14)
        out = np.empty((len(self._exprs), len(Y)))
        for i, v in enumerate(self.numpy()(t, Y.T, Z.T, P.T)):  # (a constant broadcasts on assignment)
            out[i] = v
        return np.ascontiguousarray(out.T) if contiguous else out.T

    def numpy(self):
        """The lambdified numpy function, made now if not yet (a caller that wants it made in a setup, off the
        solve's clock, calls this there)."""
        if self._numpy is None and self._exprs:
            began = time.perf_counter()
            self._numpy = self._lambdify(self._exprs)
            made_since(began)
        return self._numpy

    def _few(self, t, Y: np.ndarray, Z: np.ndarray, P: np.ndarray) -> np.ndarray:
        """:meth:`__call__` on casadi, one sample at a time (its ``Max`` and ``Min`` pass a nan on, as numpy's do:
        :func:`daemodel.declaring.functions._maximum`; casadi's fmax made a reset to ``Max(-0.8*v, sqrt(h - 2))``
        at h = 0 3.54, not the nan that InvalidValueError names)."""
        local, B = self._local, len(Y)
        if not hasattr(local, "evaluate"):
            local.inputs = np.zeros(self._casadi.nnz_in(0))
            local.outputs = np.zeros(self._casadi.nnz_out(0))
            local.buffer, local.evaluate = self._casadi.buffer()
            local.buffer.set_arg(0, memoryview(local.inputs))
            local.buffer.set_res(0, memoryview(local.outputs))
        inputs, outputs, n, m = local.inputs, local.outputs, Y.shape[1], Z.shape[1]
        times = np.reshape(t, -1)
        out = np.empty((B, len(outputs)))
        for b in range(B):
            # (t, Z and P of one row stand for every sample, as numpy broadcasts them)
            inputs[0] = times[b if len(times) > 1 else 0]
            inputs[1 : 1 + n] = Y[b]
            inputs[1 + n : 1 + n + m] = Z[b if len(Z) > 1 else 0]
            inputs[1 + n + m :] = P[b if len(P) > 1 else 0]
            local.evaluate()
            out[b] = outputs
        return out

    def _convert(self):
        """The casadi function of the expressions, or False where one has no translation."""
        import casadi

        from daemodel.compiling.codegen import CasadiConverter

        t, y, z, p = self._symbols
        packed = casadi.SX.sym("x", 1 + len(y) + len(z) + len(p))
        convert = CasadiConverter(dict(zip((t, *y, *z, *p), casadi.vertsplit(packed), strict=True)))
        try:
            # (one at a time, the shared parts made once through the converter's memo: its stack() first sorts
            # the expressions by structure, a walk of every tree that cost 4 times the conversion here)
            out = [casadi.SX(convert(sp.sympify(e))) for e in self._exprs]
        except (UnsupportedFunctionError, TypeError):  # (no translation, or a number that is no float: zoo)
            return False
        return casadi.Function("few_samples", [packed], [casadi.densify(casadi.vertcat(*out))])
