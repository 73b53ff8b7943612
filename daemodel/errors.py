"""Every exception daemodel raises, in two families.

* :class:`ModelError` (a :class:`ValueError`): a **user mistake** that no solver run can fix:
  a malformed equation, an unknown name, an option out of range, an inconsistent initial
  state, a file that is not what it claims.  The message names the culprit (equation,
  variable, option, file) and the fix.  Raised before any long computation where possible.
* :class:`SolverError` (a :class:`RuntimeError`): the input was well formed but a **method
  failed** on it: Newton did not converge, the step size underflowed, values went non-finite,
  a local error estimate exceeded its bound, or a user-settable budget (``max_steps``,
  IDAS's ``max_num_steps``) ran out.  The message names the method, the time, the step, the sample and,
  where known, the variable or equation, and what to change.

Both derive from :class:`DaemodelError`, so ``except DaemodelError`` catches everything
daemodel raises on purpose; anything else escaping the public API is a bug.  A Ray worker
that dies under a task (killed, out of memory) is a run that failed on well-formed input:
:class:`WorkerError`, a SolverError.
"""


class DaemodelError(Exception):
    """Base class of every error daemodel raises on purpose."""


class ModelError(DaemodelError, ValueError):
    """Base class of every error daemodel raises for a user mistake."""


class SolverError(DaemodelError, RuntimeError):
    """Base class of every failure of a method on well-formed input.  ``t`` is where the method stopped,
    where it says (casadi-idas: the time IDAS printed), else None."""

    def __init__(self, message: str, t: float | None = None):
        super().__init__(message)
        self.t = t


class InvalidNameError(ModelError):
    """A declared name is not a usable identifier, is reserved, or is declared twice."""


class NumericFunctionError(ModelError, TypeError):
    """``math.sin(x)`` or ``np.sin(x)`` on a declared symbol, which has no number until the solve
    (a TypeError too, as Python's and numpy's own refusals of the call are)."""


class UnknownSymbolError(ModelError):
    """An equation, initial value or output uses a name the model never declared."""


class ExpressionParseError(ModelError):
    """A string equation could not be parsed."""


class InvalidValueError(ModelError):
    """A parameter value, initial value or initial time is not a finite real number."""


class ODETargetError(ModelError):
    """``m.ode(x, ...)`` where ``x`` is not a declared differential variable."""


class DuplicateODEError(ModelError):
    """A differential variable received a second ODE."""


class MissingODEError(ModelError):
    """A differential variable has no ODE."""


class DerivativeInEquationError(ModelError):
    """A derivative appears on a right-hand side or in a constraint (not semi-explicit)."""


class UnbalancedSystemError(ModelError):
    """The number of algebraic variables differs from the number of constraints."""


class MissingParameterValueError(ModelError):
    """A parameter has no value at compile time."""


class MissingInitialValueError(ModelError):
    """A differential variable has no initial value."""


class SingularSystemError(ModelError):
    """The constraints do not determine the algebraic variables (singular iteration matrix)."""


class IndexTooHighError(ModelError):
    """A constraint needs more than two differentiations to determine an algebraic variable."""


class InconsistentInitialStateError(ModelError):
    """The initial differential state violates a constraint or a hidden constraint."""


class InconsistentAlgebraicValueError(ModelError):
    """A user-given initial algebraic value disagrees with the consistent one."""


class WrongBranchError(InconsistentAlgebraicValueError):
    """A user-given initial algebraic value is a root of the constraints, but of another branch
    than the one the guess selects (both values are named)."""


class FixedStateError(InconsistentInitialStateError):
    """``consistent(fix=...)`` cannot hold the named states: no state is left to move, or the
    constraints have no solution with those states held."""


class InitialisationError(ModelError):
    """The consistent initial values could not be computed (Newton did not converge)."""


class UnsupportedFunctionError(ModelError):
    """An equation uses a function that a code generator cannot translate."""


class UnknownOutputError(ModelError):
    """``compile(outputs=...)`` names something that is not a variable of the model."""


class ShapeError(ModelError):
    """An array passed to a generated function has the wrong trailing size."""


class ReductionError(ModelError):
    """``reduced(index=...)`` asks for an index the system cannot be reduced to."""


class StagesError(ModelError):
    """A Radau IIA tableau was asked for an invalid number of stages."""


class TimeSpanError(ModelError):
    """``t_span`` or ``t_eval`` is empty, reversed, not finite, or outside the interval."""


class StepSizeError(ModelError):
    """A step size is not positive, larger than the interval, or shorter than float64 resolves t where it is
    taken: given (a fixed grid's h) or asked for by the error estimate (adaptive radau's steps from t0 = 1e14,
    below the step size underflow's threshold 1e-14 |t|); the fix is then to count time from near the start."""


class UnknownMethodError(ModelError):
    """``solve(method=...)`` names no registered backend."""


class DuplicateMethodError(ModelError):
    """``compare()`` or ``bench`` given the same method twice in ``methods``: each method runs once, its
    settings (as many as wanted) in ``sweep``."""


class MethodNameError(InvalidNameError):
    """``dm.methods.register(name, ...)`` with a name that is not a plain method name (a letter, then
    letters, digits, ``-`` or ``_``), or that is taken (a built-in method, one registered earlier, or an
    installed entry point) without ``replace=True``."""


class MethodClassError(ModelError, TypeError):
    """``dm.methods.register(name, cls)`` with a ``cls`` that does not keep the backend contract: not a
    concrete subclass of :class:`daemodel.backends.base.AbstractBackend`, its ``name`` not the name it is
    registered under, ``Options`` not a dataclass, or ``max_index`` not 1, 2 or 3."""


class MethodPluginError(ModelError):
    """A method from the ``daemodel.methods`` entry-point group cannot be used: its module does not
    import, its class is missing or breaks the backend contract, or two distributions give the same
    name.  The message names the distribution, the entry point and the cause; the other methods work."""


class MethodPluginWarning(UserWarning):
    """An entry point of the ``daemodel.methods`` group is ignored: its name is not a plain method name,
    or it is a built-in method's (the built-in one is used)."""


class UnsupportedModelError(ModelError):
    """A method cannot solve this kind of model: e.g. one that solves the whole span at once
    (``solves_pieces = False``) given a model with events or switches, which are solved piece by piece."""


class UnknownOptionError(ModelError):
    """A keyword passed to ``solve`` is not an option of the chosen method."""


class InvalidOptionError(ModelError):
    """An option has a value the method cannot use (wrong type, range or precision)."""


class ConvergenceError(SolverError):
    """A solver failed: Newton did not converge, the step size underflowed, or values went non-finite."""


class BranchError(ConvergenceError):
    """A method's algebraic variables would leave the branch of roots chosen at t0: the determining
    equations' Jacobian in z changes sign on the way (the branch folds or meets another), or Newton
    jumped to another root far from the continuation of the last one."""


class StepLimitError(SolverError):
    """A user-settable step budget (``max_steps``, ``max_num_steps``) ran out before the end of ``t_span``.

    A Newton iteration that runs out of iterations is a :class:`ConvergenceError` instead: it did
    not converge, and more iterations rarely help."""


class EventLimitError(SolverError):
    """More events in one solve than ``max_events`` allows (chattering, Zeno)."""


class ZenoError(EventLimitError):
    """Events accumulate: their times converge to a point (a ball bouncing ever lower), or a reset leaves
    the state on its guard, so that the event would fire again at once.  ``t`` is the accumulation point
    (estimated) or the time where the state stays on the guard; the solution past it is not defined by the
    events."""

    def __init__(self, message: str, t: float | None = None):
        super().__init__(message)
        self.t = t


class SlidingModeError(EventLimitError):
    """A switch on the variables where neither branch can be continued: on each side the flow points
    back across the switching surface, so the solution slides along it (a Filippov sliding mode), which
    daemodel does not integrate.  ``t`` is where the sliding starts."""

    def __init__(self, message: str, t: float | None = None):
        super().__init__(message)
        self.t = t


class EventLocationError(SolverError):
    """An event's crossing could not be located to its tolerance."""


class TimeResolutionError(EventLocationError):
    """float64's spacing of t where the events happen is too coarse to tell what they do: a function reset onto
    its guard does not move back within the few spacings of t that an event's location resolves there (the ball
    at t0 = 1e15, spacing 0.125, its flights shorter than the 1.0 that its impacts' locations allow): a bounce
    and a ball at rest (Zeno) look alike.  ``t`` is the event's time; the fix is to count time from near the
    start (``t - t0`` in the model, t_span from 0)."""

    def __init__(self, message: str, t: float | None = None):
        super().__init__(message)
        self.t = t


class ResetConflictError(ModelError):
    """Events that fire at one instant reset the same state to different values: which one holds is not
    defined (each reset reads the values just before the instant)."""


class CompileError(SolverError):
    """The system's C compiler failed on code daemodel generated (radau's ``jit=True``)."""


class UnsafeCacheError(ModelError):
    """The folder of compiled libraries (``DAEMODEL_CACHE``) is not safe to load code from: it, or a
    file in it, is a link, writable by the group or others, or owned by another user.  A solve then
    compiles into a private temporary folder instead (:class:`CacheWarning`)."""


class CacheWarning(UserWarning):
    """The cache of compiled libraries was not used as it should be: its folder was refused
    (:class:`UnsafeCacheError`, said once per process and folder) or a library could not be stored
    in it (a full disk); the solve goes on with code compiled for this process alone."""


class LocalErrorBoundError(SolverError):
    """A fixed-step method's a-posteriori local error estimate exceeded its bound (the step is not trustworthy)."""


class SwitchError(ModelError):
    """A model's switches cannot be handled as asked: breakpoints that cannot be located or are too
    many, or that differ between the samples of a batch."""


class ResourceLimitError(ModelError):
    """A request would not fit in memory or time (a step grid, a sweep); refused before allocating."""


class OutsideTrainingBoxError(ModelError):
    """A surrogate was asked for states or parameters outside the box it was trained on."""


class OutsideTrainingBoxWarning(UserWarning):
    """A surrogate was asked for states or parameters outside the box it was trained on (by default a warning)."""


class LocalErrorWarning(UserWarning):
    """A fixed-step solution's local error estimate exceeds its bound (``estimate_bound``), or an
    adaptive radau solve was given a ``newton_tol`` looser than its stages' default (its estimate does
    not see the stage errors Newton leaves): the solution is flagged, not "success", and may keep fewer
    digits than the bound or the tolerances promise."""


class EventResolutionWarning(UserWarning):
    """An event's time is not resolved to the states' tolerance: float64's spacing of t there moves the
    states by more than it (an event near t = 1e8 at rtol 1e-9); the Solution's status is "flagged"."""


class TimeResolutionWarning(UserWarning):
    """float64's spacing of t, where f reads t, may move the states by more than their tolerance (y' = cos(t)
    from t0 = 1e13, spacing 2e-3): the Solution's status is "flagged" (:mod:`daemodel.solving.resolution`)."""


class OmittedPanelsWarning(UserWarning):
    """``Solution.plot()`` without ``names=`` drew the first variables only (a figure of sixty panels
    is unreadable); the warning and the figure's title name how many were left out."""


class UncertifiedWarning(UserWarning):
    """A Radau-PINN answer whose certificate does not put it within Radau's own error at the same h
    (its Solution's status is "flagged"; ``strict=True`` makes it a :class:`TrainingError`)."""


class ComparisonError(ModelError):
    """Two solutions (or a solution and a reference) cannot be compared: no common variables or times."""


class TrainingError(ConvergenceError):
    """Radau-PINN training failed: a loss term is NaN or exploded, or (``strict=True``) the answer is not certified."""


class WorkerError(SolverError):
    """A Ray worker stopped before returning its task's result (killed, out of memory, crashed)."""


class TimeLimitError(SolverError):
    """A task ran longer than its time limit (a Ray task's ``task_timeout``, a benchmark run's
    ``time_limit``) and was stopped."""


class SolutionFileError(ModelError):
    """A saved solution file or ensemble directory does not exist, is not daemodel's, or belongs to another model."""


class FileWriteError(ModelError, OSError):
    """A file could not be written (a full disk, a size limit, no permission); the file that was
    there before is intact and no partial file is left."""


class NetworkFileError(ModelError):
    """A saved network file does not exist, is not a daemodel network, or belongs to another model."""


class BenchError(ModelError):
    """A benchmark (``dm.bench``, ``daemodel bench``) asked for what cannot run: an unknown suite,
    a problem without a reference at its end, a setting its method refuses; or a file in its
    output folder that is not one of its results (the message names the file and the field)."""


class TargetError(ModelError):
    """A ``daemodel compare`` target is neither a known problem nor a usable model file."""


class SensitivityError(ModelError):
    """Derivatives of a solution cannot be taken as asked: a name that is not a parameter or free
    state, a method or solution without radau's step records, a singular step."""


class DataError(ModelError):
    """Measured data that a fit cannot use: times outside the model's span or not increasing, a series
    with no measurement, arrays of the wrong shape."""


class UnidentifiableError(ModelError):
    """The data do not determine some parameters of a fit: the outputs do not depend on them, or a
    change of several of them together leaves the outputs unchanged."""


class FittedConstraintError(ModelError):
    """A constraint without algebraic variables (index 2, or an index-3 one's position or velocity
    level) depends on a parameter being fitted: the known initial states satisfy it at one value only."""
