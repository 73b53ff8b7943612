"""Progress of long work: bars, step loops that cannot finish, casadi's printed output."""

from __future__ import annotations

import io
import math
import sys
import threading

# Step loops give up early when the last PROGRESS_WINDOW steps project more than PROJECTION_FACTOR
# times the steps left in the budget: an endless t_span or a chattering switch fails in a second
# instead of spending the whole budget.  The projection lets h keep growing as it did over the
# window (a stiff transient's slow start is not judged at its pace), and a collapsing h (below
# COLLAPSE_FACTOR of the window's start: a blow-up) is left to the step-size failure that names it.
PROGRESS_WINDOW, PROJECTION_FACTOR, COLLAPSE_FACTOR = 100, 10, 0.1
# A held h is no pace: radau keeps h (and its factorisations) while the step its error estimate asks for stays
# within a band above h (.radau.control.KEEP_H_BAND: up to 1.5x compiled), so a stiff transient's fast mode
# decaying at the solve's start held h = 2.53e-6 flat for 260 attempts (a' = -b - a/10, b' = a - b/10,
# c' = -1000 c + a, s = 2, rtol 1e-9) and two flat windows projected 1.97e6 attempts: StepLimitError after
# 200 where the solve takes 4,701.  Where h is held (within HELD_H of the window's start: t's rounding moves it)
# the watch reads the growth the estimate asks for.
HELD_H = 1e-9


# Windows in a row that must each project past the budget before a loop gives up early.
HOPELESS_WINDOWS = 2
# A stiff layer (van der Pol crossing its fast jump) takes hundreds to thousands of accepted attempts at a step
# DIP_FACTOR or more below the largest one the loop has taken, and projects past the budget at that pace for
# many windows before h grows again.  Such a dip (h below DIP_FACTOR of the largest h, at least DIP_ACCEPTED of
# each window's attempts accepted: not chattering, which is mostly rejections) may take DIP_SHARE of the budget,
# at least DIP_WINDOWS windows, before the loop gives up; a dip longer than that (h collapsed for good, as with
# a newton_tol too loose for the stages) is judged as any other window.  Raising max_steps lets a longer layer
# through.  Three stages on van der Pol: one jump's dip took 5-18 windows at rtol 1e-6 to 1e-8 (eps = 1e-6 to
# 1e-10), 57 at 1e-10 and 183 at 1e-12 (eps = 1e-10: 18,300 of the solve's 40,680 attempts); a fixed 10
# windows stopped solves that finish in 5,505 attempts (eps = 1e-6 over [0, 11], rtol 1e-6) and 4,289
# (eps = 1e-10 over [0, 2], rtol 1e-8) whatever max_steps.  A runaway that looks like a dip (mostly accepted
# steps far below the earlier ones, for good) now spends up to DIP_SHARE of the budget before it is stopped: an
# oscillator whose frequency jumps from 1 to 1e6 at t = 30, over [0, 1000], 25,100 attempts (1,100 with 10).
DIP_FACTOR, DIP_ACCEPTED, DIP_WINDOWS, DIP_SHARE = 1e-3, 0.5, 10, 0.25


class ProgressWatch:
    """Whether a step loop can still reach ``t1`` within its budget, judged window by window.

    ``start`` is ``(t, count, h, extra)`` where the current window began (``extra``: whatever
    the caller wants back for its message, e.g. its accepted steps then).
    """

    def __init__(self, t: float, h: float, extra=None):
        self.start = (t, 0, h, extra)
        self.err = None  # the error estimate where the window began (where the caller tells it)
        self.strikes = 0  # windows in a row that projected past the budget
        # the largest step seen at a window's end, or mean step over a window (not ``h``: a first guess rejected
        # at once, h0 = 1e3 on an oscillator, made every later window a dip, 25,100 attempts where 300 tell)
        self.h_max = 0.0
        self.accepted = 0  # the caller's accepted steps when the window began (where it tells them)
        self.dip_began = None  # the count where the dip began (windows in a row, h below DIP_FACTOR of h_max)

    def hopeless(
        self,
        count: int,
        t: float,
        h: float,
        t1: float,
        budget: int,
        extra=None,
        accepted: int | None = None,
        err: float | None = None,
        exponent: float = 0.0,
    ) -> float | None:
        """Call once per step; ``count`` steps (or attempts) so far.  Returns the projected number of
        further steps when :data:`HOPELESS_WINDOWS` windows in a row project past
        :data:`PROJECTION_FACTOR` times the budget left, else None (starting a new window when one
        is complete).  Where the caller counts attempts, ``accepted`` (its accepted steps so far) lets
        a stiff layer's dip take :data:`DIP_SHARE` of ``budget`` (at least :data:`DIP_WINDOWS` windows)
        instead.  Where the caller holds h while its error estimate ``err`` falls (a controller that keeps h,
        and its factorisations, until the step it asks for is ``keep`` band's worth larger), the window's
        growth is the one its estimate asks for, ``(err then / err now)^exponent``, not h's 1."""
        t_w, count_w, h_w, _ = self.start
        steps = count - count_w
        if steps < PROGRESS_WINDOW or count >= budget:  # the budget's own error speaks at the end
            return None
        covered, left, growth = t - t_w, t1 - t, h / h_w
        held = abs(growth - 1) <= HELD_H  # (held: h moved only by t's rounding)
        if held and err is not None and self.err is not None and 0 < err < self.err:
            growth = (self.err / err) ** exponent
        if covered <= 0:
            needed = math.inf
        elif growth > 1:  # windows covering covered * growth^k: a geometric series up to t1
            needed = steps * math.log1p(left * (growth - 1) / covered) / math.log(growth)
        else:
            needed = steps * left / covered
        hopeless = growth >= COLLAPSE_FACTOR and needed > PROJECTION_FACTOR * (budget - count)
        self.strikes = self.strikes + 1 if hopeless else 0
        low = max(abs(h), abs(h_w)) < DIP_FACTOR * self.h_max
        self.dip_began = (count_w if self.dip_began is None else self.dip_began) if low else None
        allowance = max(DIP_WINDOWS * PROGRESS_WINDOW, DIP_SHARE * budget)
        dip = (
            accepted is not None
            and low
            and count - self.dip_began < allowance
            and accepted - self.accepted >= DIP_ACCEPTED * steps
        )
        if self.strikes >= HOPELESS_WINDOWS and not dip:
            return needed
        self.start, self.err = (t, count, h, extra), err
        self.h_max = max(self.h_max, abs(h), abs(covered) / steps)
        self.accepted = accepted or 0
        return None


# Seconds between progress lines when stderr is not a terminal (a log file, CI): a terminal
# redraws one line in place, a log would keep every redraw.
LOG_PROGRESS_SECONDS = 5.0


class captured_output:  # (lower case: used as the function it was, ``with captured_output() as text``)
    """Collect what casadi prints during a call instead of showing it (``as``: the text).

    casadi's Python module sends its C++ output streams to ``sys.stdout``/``sys.stderr``, so
    redirecting those catches IDAS's messages, the root finder's dumps and the inputs a failing
    call prints of every function it was nested in (the tests check the file descriptors too,
    with ``capfd``).  Both are set back on the way out, as ``contextlib.redirect_stdout`` and
    ``redirect_stderr`` would (a class: the generator of ``contextlib.contextmanager`` with those two
    inside cost a few microseconds of every compiled radau run's ~0.3 ms on a small model).

    Threads: while any thread captures, ``sys.stdout`` and ``sys.stderr`` are :class:`_ThreadStreams`, which send a
    capturing thread's writes to its own text and every other thread's to the streams they replaced; the last
    thread out sets those back.  (Each saving and restoring the streams it found left ``sys.stdout`` and
    ``sys.stderr`` a StringIO for good after concurrent solves, every later print lost, and a thread's text caught
    another's prints.)
    """

    def __enter__(self) -> io.StringIO:
        self.text, self.outer = io.StringIO(), getattr(_CAPTURING, "text", None)  # (outer: a capture it is inside)
        with _CAPTURE_LOCK:
            if _CAPTURE_STATE["depth"] == 0:
                _CAPTURE_STATE["saved"] = sys.stdout, sys.stderr
                sys.stdout, sys.stderr = _ThreadStreams(sys.stdout), _ThreadStreams(sys.stderr)
            _CAPTURE_STATE["depth"] += 1
        _CAPTURING.text = self.text
        return self.text

    def __exit__(self, *exception) -> None:
        _CAPTURING.text = self.outer
        with _CAPTURE_LOCK:
            _CAPTURE_STATE["depth"] -= 1
            if _CAPTURE_STATE["depth"] == 0:
                sys.stdout, sys.stderr = _CAPTURE_STATE["saved"]
                _CAPTURE_STATE["saved"] = None


# captured_output across threads: how many captures are open in all and the streams the first replaced; each
# thread's text (None outside a capture).
_CAPTURE_LOCK = threading.Lock()
_CAPTURE_STATE: dict = {"depth": 0, "saved": None}
_CAPTURING = threading.local()


class _ThreadStreams:
    """``sys.stdout`` or ``sys.stderr`` while a thread captures (:class:`captured_output`): a write goes to the
    writing thread's text where it captures, else to ``stream``, the one replaced (its other attributes too)."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> int:
        captured = getattr(_CAPTURING, "text", None)
        return (self.stream if captured is None else captured).write(text)

    def flush(self) -> None:
        if getattr(_CAPTURING, "text", None) is None and self.stream is not None:
            self.stream.flush()

    def __getattr__(self, name: str):
        return getattr(self.stream, name)


def stderr_is_terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def show_progress(progress: bool | None) -> bool:
    """``progress`` as given, or whether stderr is a terminal."""
    if progress is None:
        return stderr_is_terminal()
    return bool(progress)


def progress_bar(total: int, desc: str, unit: str):
    """A tqdm bar on stderr: redrawn in place on a terminal, a line every
    :data:`LOG_PROGRESS_SECONDS` at most elsewhere."""
    from tqdm.auto import tqdm

    interval = 0.1 if stderr_is_terminal() else LOG_PROGRESS_SECONDS
    return tqdm(total=total, desc=desc, unit=unit, leave=False, mininterval=interval, file=sys.stderr)
