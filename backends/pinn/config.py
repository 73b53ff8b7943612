"""``PINNConfig``: every setting of the Radau-PINN, frozen and checked (no torch import here)."""

from __future__ import annotations

import dataclasses
import difflib
import functools
from dataclasses import dataclass

from daemodel.backends.checks import check_dtype, check_stages, set_number

from daemodel.errors import InvalidOptionError, UnknownOptionError

ACTIVATIONS = ("tanh", "sigmoid", "sin", "gelu", "softplus")
ARCHITECTURES = ("per-variable", "shared")
OPTIMIZERS = ("lm", "lbfgs", "adam")
BATCH_MODES = ("independent", "shared")
SCHEDULES = ("constant", "exponential")
# An exponential schedule ends at this fraction of learning_rate unless final_learning_rate is given
# (1e-3 -> 1e-6: the decay measured on the paper's first Hessenberg segment, see docs/benchmarks/paper.md).
DEFAULT_DECAY = 1e-3
# Iteration caps when ``iterations`` is not given: LM and L-BFGS stop on ``tol`` long before.
DEFAULT_ITERATIONS = {"lm": 200, "lbfgs": 5000, "adam": 100_000}
# Default step of each optimizer (LM has none: its damping adapts).
DEFAULT_LEARNING_RATE = {"lm": None, "lbfgs": 1.0, "adam": 1e-3}
# Stop when every residual component is below this.  An index-2 algebraic variable moves by
# about residual / h (1e-11 left z 1e-8 from Newton's at h = 0.05); LM converges
# quadratically, so the extra digits cost about one iteration.
DEFAULT_TOL = 1e-12
# The paper's problems and their activations (Hessenberg: sigmoid; pendulum: sin).
PAPER_ACTIVATION = {"hessenberg": "sigmoid", "pendulum": "sin"}
# Jagtap et al.'s adaptive activation: phi(eta * l * x) with l initialised to 1/eta.
PAPER_ETA = 10.0


def named_settings(cls):
    """Make a misspelt or positional setting of a keyword-only dataclass a named error.

    The ``__init__`` that ``dataclass`` writes raises a bare TypeError for ``PINNConfig(widht=3)``;
    this wraps it (keeping its signature for ``help``) so that the mistake is an
    :class:`UnknownOptionError` that lists the settings, like an unknown option of ``solve``.
    """
    generated = cls.__init__
    fields = sorted(f.name for f in dataclasses.fields(cls))

    @functools.wraps(generated)
    def __init__(self, *args, **settings):
        if args:
            raise InvalidOptionError(
                f"{cls.__name__} takes its settings by name, e.g. {cls.__name__}(stages=3, h=0.05); "
                f"got {len(args)} positional argument{'s' if len(args) > 1 else ''}"
            )
        unknown = sorted(set(settings) - set(fields))
        if unknown:
            hints = [repr(m[0]) for u in unknown if (m := difflib.get_close_matches(u, fields, n=1))]
            raise UnknownOptionError(
                f"{cls.__name__} has no setting {', '.join(map(repr, unknown))}"
                + (f" (did you mean {', '.join(hints)}?)" if hints else "")
                + f"; its settings are {', '.join(fields)}"
            )
        generated(self, **settings)

    cls.__init__ = __init__
    return cls


@named_settings
@dataclass(frozen=True, kw_only=True)
class PINNConfig:
    """Settings of ``method="pinn"``: the network, the loss, the optimizer and the segments.

    The defaults are the fast mode: float64, Levenberg-Marquardt on the Newton corrections of
    the stage equations (see :mod:`daemodel.backends.pinn.train`), warm start from the previous
    segment, stopping when every residual is below ``tol``.
    :meth:`paper` gives the paper's recipe (Adam, 100k iterations per segment).  Settings are
    given by name; a name it does not have is an :class:`UnknownOptionError` that lists them.

    Attributes
    ----------
    stages : int
        Radau IIA stages v (order 2v-1).
    h : float
        Segment length: one network per segment; the last one is shortened to end at t1, and a
        span shorter than h (a piece between two events) is one segment of its own length.  A
        solve given neither ``h`` nor a config takes its h from the problem instead
        (:class:`~daemodel.backends.pinn.backend.PINNOptions`).
    width, depth : int
        Hidden width and number of hidden layers of each network.  Networks whose training would
        not fit in memory are refused before they are built (a
        :class:`~daemodel.errors.ResourceLimitError` naming width, depth and the estimate).
    activation : str
        One of ``tanh``, ``sigmoid``, ``sin``, ``gelu``, ``softplus``.
    eta : float
        Scale of the adaptive activation: the first hidden layer is ``phi(eta * l * x W + b)``
        with a trainable slope ``l`` that starts at ``1 / eta``.
    architecture : str
        ``"per-variable"`` (the paper's approach 2: one network per differential variable, two
        for the algebraic variables, stages and end values) or ``"shared"`` (approach 1: one
        network for all outputs).
    increment : bool
        Predict the differential outputs as ``y_n + h * N(y_n)`` instead of ``N(y_n)``; the
        network then learns an O(1) slope rather than the state itself.  A fresh network then
        starts at rest: every stage at the start value, the algebraic ones at the consistent
        ``z_n`` the compiler finds from ``m.guess`` (Newton's constant guess), not at random
        values.  Off in :meth:`paper`.
    weight_f, weight_g, weight_s : float
        The loss weights W_f, W_g, W_s.
    optimizer : str
        ``"lm"`` (Levenberg-Marquardt), ``"lbfgs"`` or ``"adam"``.
    iterations : int, optional
        Cap on iterations per segment (default: 200 for lm, 5000 for lbfgs, 100000 for adam).
    tol : float or None
        Stop a segment when every residual component is at most ``tol``, the rows of F (units of
        y) and S (units of z) relative to ``max(1, |value|)`` of their variable, the constraint
        rows as they are; a segment that ends its iterations above it says so in its stats (the
        answer's status is the certificate's verdict, see ``method="pinn"``).  None is a
        fixed budget: all ``iterations`` (the paper's recipe), or fewer when LM or L-BFGS can no
        longer decrease the loss.  Surrogates use it, since over a box of inputs the residuals
        cannot all vanish.
    learning_rate : float, optional
        Adam's or L-BFGS's step (default 1e-3 and 1.0).
    schedule : str
        Adam's learning rate over the iterations: ``"constant"`` (the paper's), or
        ``"exponential"``: from ``learning_rate`` down to ``final_learning_rate`` at the last
        iteration, by the same factor every iteration.
    final_learning_rate : float, optional
        The exponential schedule's last rate (default ``learning_rate * 1e-3``).
    samples : int
        Training inputs per segment and trajectory: the segment's start plus ``samples - 1``
        points drawn uniformly in a box of half-width ``radius`` around it.
    radius : float
        Half-width of that box (relative to ``max(1, |y_n|)`` per variable).
    warm_start : bool
        Start each segment from the previous segment's trained network.
    predictor : bool
        Start each segment's stage values where radau's Newton starts them: on the previous
        segment's collocation polynomial (through its start and the stages its networks
        predicted), extrapolated over this segment; the output biases are shifted to put them
        there.  It uses the PINN's own previous stages, no classical solution.  Where each set
        of networks has one input (a trajectory, or independent networks for a batch); the
        first segment, and a segment whose extrapolation leaves f's domain, start at rest.
        Measured on the models of ``benchmarks/pinn_models.py``: iterations fall 40-57 % (a
        3-bus grid 79 -> 41, akzo-nobel 79 -> 34, the transistor amplifier 89 -> 51, every
        other default on).  Off in :meth:`paper`.
    batch : str
        How a batch of samples (initial states or parameter values) trains: ``"independent"``
        (default) gives every sample its own networks, all trained at once as one block-diagonal
        Levenberg-Marquardt problem, so each sample reaches its own Radau solution as a single
        trajectory does; ``"shared"`` trains one set of networks whose inputs are the states and
        the parameters that vary (a surrogate over the batch; ``Surrogate.train`` always shares).
    dtype : "float64" or "float32"
    device : str
        A torch device ("cpu", "cuda", ...).
    seed : int
        Seeds the initial weights and the samples: equal seeds give equal results.
    """

    stages: int = 3
    h: float = 0.05
    width: int = 20
    depth: int = 2
    activation: str = "tanh"
    eta: float = 1.0
    architecture: str = "per-variable"
    increment: bool = True
    weight_f: float = 1.0
    weight_g: float = 1.0
    weight_s: float = 1.0
    optimizer: str = "lm"
    iterations: int | None = None
    tol: float | None = DEFAULT_TOL
    learning_rate: float | None = None
    schedule: str = "constant"
    final_learning_rate: float | None = None
    samples: int = 1
    radius: float = 0.0
    warm_start: bool = True
    predictor: bool = True
    batch: str = "independent"
    dtype: str = "float64"
    device: str = "cpu"
    seed: int = 0

    def __post_init__(self) -> None:
        check_stages(self.stages)
        set_number(self, "h")
        for name in ("width", "depth", "samples"):
            set_number(self, name, integer=True)
        set_number(self, "iterations", integer=True, allow_none=True)
        for name in ("eta", "weight_f", "weight_g", "weight_s"):
            set_number(self, name)
        set_number(self, "tol", allow_none=True)
        set_number(self, "learning_rate", allow_none=True)
        set_number(self, "final_learning_rate", allow_none=True)
        set_number(self, "radius", positive=False)
        set_number(self, "seed", positive=False, integer=True)
        if self.radius < 0:
            raise InvalidOptionError(f"radius must be >= 0; got {self.radius!r}")
        for name, allowed in (
            ("activation", ACTIVATIONS),
            ("architecture", ARCHITECTURES),
            ("optimizer", OPTIMIZERS),
            ("batch", BATCH_MODES),
            ("schedule", SCHEDULES),
        ):
            if getattr(self, name) not in allowed:
                raise InvalidOptionError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        for name in ("increment", "warm_start", "predictor"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidOptionError(f"{name} must be True or False; got {getattr(self, name)!r}")
        if self.samples > 1 and self.radius == 0:
            raise InvalidOptionError(
                f"samples = {self.samples} with radius = 0 would train on {self.samples} copies of one point; "
                "give radius > 0 or samples = 1"
            )
        if self.optimizer == "lm" and self.learning_rate is not None:
            raise InvalidOptionError("optimizer 'lm' has no learning_rate (its damping adapts); leave it None")
        if self.optimizer != "adam" and (self.schedule != "constant" or self.final_learning_rate is not None):
            raise InvalidOptionError(
                f"schedule and final_learning_rate set Adam's learning rate; optimizer {self.optimizer!r} has none "
                "to schedule: use optimizer='adam', or leave them"
            )
        if self.schedule == "constant" and self.final_learning_rate is not None:
            raise InvalidOptionError("final_learning_rate ends an exponential schedule: give schedule='exponential'")
        object.__setattr__(self, "dtype", check_dtype(self.dtype))
        if not isinstance(self.device, str):
            object.__setattr__(self, "device", str(self.device))
        if self.iterations is None:
            object.__setattr__(self, "iterations", DEFAULT_ITERATIONS[self.optimizer])
        if self.learning_rate is None:
            object.__setattr__(self, "learning_rate", DEFAULT_LEARNING_RATE[self.optimizer])
        if self.schedule == "exponential" and self.final_learning_rate is None:
            object.__setattr__(self, "final_learning_rate", self.learning_rate * DEFAULT_DECAY)

    def learning_rate_at(self, iteration: int) -> float:
        """Adam's learning rate at ``iteration`` (0-based) of a segment under :attr:`schedule`."""
        if self.schedule == "constant" or self.iterations <= 1:
            return self.learning_rate
        fraction = min(iteration, self.iterations - 1) / (self.iterations - 1)
        return self.learning_rate * (self.final_learning_rate / self.learning_rate) ** fraction

    @classmethod
    def paper(cls, problem: str, **changes) -> PINNConfig:
        """The paper's settings for ``problem`` ("hessenberg" or "pendulum"), with ``changes``.

        Three stages, h = 0.05, approach 2, five hidden layers of 100, the problem's
        activation with Jagtap's adaptive slope (eta = 10), Adam at 1e-3 for 100,000
        iterations per segment, a fresh network per segment, outputs predicted directly.
        The paper does not say how many training inputs a segment has, nor whether a segment's
        network starts afresh; we train each at its start value alone, from fresh weights.  The
        paper's rate is constant; ``schedule="exponential"`` is ours.  We keep float64 so its
        errors compare with the classical solvers'.
        """
        if problem not in PAPER_ACTIVATION:
            raise InvalidOptionError(
                f"the paper's problems are {', '.join(PAPER_ACTIVATION)}; got {problem!r}"
                " (for another model, start from PINNConfig(...) instead)"
            )
        settings = {
            "stages": 3,
            "h": 0.05,
            "width": 100,
            "depth": 5,
            "activation": PAPER_ACTIVATION[problem],
            "eta": PAPER_ETA,
            "architecture": "per-variable",
            "increment": False,
            "optimizer": "adam",
            "iterations": 100_000,
            "tol": None,
            "learning_rate": 1e-3,
            "samples": 1,
            "radius": 0.0,
            "warm_start": False,
            "predictor": False,
        }
        return cls(**{**settings, **changes})

    def replace(self, **changes) -> PINNConfig:
        """A copy with ``changes`` applied (and checked); an unknown name is an :class:`UnknownOptionError`."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if "optimizer" in changes:
            # Optimizer-dependent defaults follow the new optimizer unless given explicitly.
            for name, table in (("iterations", DEFAULT_ITERATIONS), ("learning_rate", DEFAULT_LEARNING_RATE)):
                if values[name] == table[self.optimizer]:
                    values[name] = None
        if self.schedule == "exponential" and self.final_learning_rate == self.learning_rate * DEFAULT_DECAY:
            values["final_learning_rate"] = None  # the default follows learning_rate and the schedule
        return PINNConfig(**{**values, **changes})
