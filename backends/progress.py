"""Progress of long work: bars, step loops that cannot finish, casadi's printed output."""

from __future__ import annotations

import io
import math
import sys

# Step loops give up early when the last PROGRESS_WINDOW steps project more than PROJECTION_FACTOR
# times the steps left in the budget: an endless t_span or a chattering switch fails in a second
# instead of spending the whole budget.  The projection lets h keep growing as it did over the
# window (a stiff transient's slow start is not judged at its pace), and a collapsing h (below
# COLLAPSE_FACTOR of the window's start: a blow-up) is left to the step-size failure that names it.
PROGRESS_WINDOW, PROJECTION_FACTOR, COLLAPSE_FACTOR = 100, 10, 0.1


# Windows in a row that must each project past the budget before a loop gives up early.
HOPELESS_WINDOWS = 2
# A stiff layer (van der Pol at eps = 1e-6 or 1e-8 crossing its fast jump) takes ~300 accepted attempts at a
# step DIP_FACTOR or more below the largest one the loop has taken, and projects past the budget at that
# pace for two windows before h grows again.  Such a dip (h below DIP_FACTOR of the largest h, at least
# DIP_ACCEPTED of the window's attempts accepted: not chattering, which is mostly rejections) is given
# DIP_WINDOWS windows in a row before the loop gives up; a dip longer than that (h collapsed for good, as
# with a newton_tol too loose for the stages) is judged as any other window.  With two, van der Pol at
# eps = 1e-6 and three stages stopped at t = 0.807 (h = 3.7e-8) a solve that finishes in 866 attempts.
DIP_FACTOR, DIP_ACCEPTED, DIP_WINDOWS = 1e-3, 0.5, 10


class ProgressWatch:
    """Whether a step loop can still reach ``t1`` within its budget, judged window by window.

    ``start`` is ``(t, count, h, extra)`` where the current window began (``extra``: whatever
    the caller wants back for its message, e.g. its accepted steps then).
    """

    def __init__(self, t: float, h: float, extra=None):
        self.start = (t, 0, h, extra)
        self.strikes = 0  # windows in a row that projected past the budget
        self.h_max = abs(h)  # the largest step seen at a window's end, or mean step over a window
        self.accepted = 0  # the caller's accepted steps when the window began (where it tells them)
        self.dips = 0  # windows in a row in a dip (h below DIP_FACTOR of h_max)

    def hopeless(
        self, count: int, t: float, h: float, t1: float, budget: int, extra=None, accepted: int | None = None
    ) -> float | None:
        """Call once per step; ``count`` steps (or attempts) so far.  Returns the projected number of
        further steps when :data:`HOPELESS_WINDOWS` windows in a row project past
        :data:`PROJECTION_FACTOR` times the budget left, else None (starting a new window when one
        is complete).  Where the caller counts attempts, ``accepted`` (its accepted steps so far) lets
        a stiff layer's dip take :data:`DIP_WINDOWS` windows instead."""
        t_w, count_w, h_w, _ = self.start
        steps = count - count_w
        if steps < PROGRESS_WINDOW or count >= budget:  # the budget's own error speaks at the end
            return None
        covered, left, growth = t - t_w, t1 - t, h / h_w
        if covered <= 0:
            needed = math.inf
        elif growth > 1:  # windows covering covered * growth^k: a geometric series up to t1
            needed = steps * math.log1p(left * (growth - 1) / covered) / math.log(growth)
        else:
            needed = steps * left / covered
        hopeless = growth >= COLLAPSE_FACTOR and needed > PROJECTION_FACTOR * (budget - count)
        self.strikes = self.strikes + 1 if hopeless else 0
        low = max(abs(h), abs(h_w)) < DIP_FACTOR * self.h_max
        self.dips = self.dips + 1 if low else 0
        dip = (
            accepted is not None
            and low
            and self.dips <= DIP_WINDOWS
            and accepted - self.accepted >= DIP_ACCEPTED * steps
        )
        if self.strikes >= (DIP_WINDOWS if dip else HOPELESS_WINDOWS):
            return needed
        self.start = (t, count, h, extra)
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
    """

    def __enter__(self) -> io.StringIO:
        self.text = io.StringIO()
        self.saved = sys.stdout, sys.stderr
        sys.stdout = sys.stderr = self.text
        return self.text

    def __exit__(self, *exception) -> None:
        sys.stdout, sys.stderr = self.saved


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
