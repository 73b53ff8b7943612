"""Fuzz cases for daemodel's public API and command line, and the classifier that runs them.

Imported by ``tests/solving/test_fuzz.py`` and ``benchmarks/trust/fuzz_report.py``; it holds no tests.

A :class:`Case` is data: the calls that build a model (``steps``), one action (solve, compile,
compare, the CLI, ...), what the case expects, and, where a solution must be right, an
independent solution to hold it against (:class:`TreeODE`, :class:`Pendulum`, :class:`Exact`:
closed forms, or scipy's ``solve_ivp`` on an equivalent ODE evaluated here in numpy, never
through daemodel's code).  Only the public API is used (``dm.Model``, ``dm.solve``,
``dm.compare``, ``dm.PINNConfig``, ``dm.Surrogate``, ``daemodel.comparing.cli.main``, ``daemodel.errors``),
so the same cases run on the old code and on the new.

:func:`run_cases` runs cases in child processes forked from one fresh interpreter that has
imported daemodel (and inherits ``PYTHONPATH``, so it runs whichever daemodel is first there),
each in its own empty directory, under a wall-clock limit and a memory limit, and gives each
exactly one outcome of :data:`OUTCOMES`:

``code-executed``
    the case's canary file exists afterwards (checked first).  Hostile strings try to create it
    (``open(CANARY, "w")``, ``system("touch CANARY")``), so execution is seen, not printed.
``hang``
    the wall-clock limit passed.
``raw-exception``
    an exception whose class has no base in ``daemodel.errors`` escaped (type and message are
    recorded), or the child died (signal, exit without a result).
``refused-valid``
    a valid case raised a daemodel error (any class with a base in ``daemodel.errors``; on the old
    code ``ModelError``/``ConvergenceError``), exited the CLI with a non-zero status, or returned
    a solution whose ``status`` is neither ``"success"`` nor ``"flagged: ..."`` (an answer whose
    own estimate says it misses its accuracy, and says so, counts as ``ok``).
``silently-wrong``
    an invalid or hostile input was accepted (a hostile string must be refused by the ``m.ode`` /
    ``m.constraint`` call that receives it, not by a later step), or a solution disagrees with
    the independent one beyond the case's tolerance (``|value - ref| > tol * (1 + |ref|)``), is
    not finite, or does not cover the requested times.
``ok``
    everything else: a valid case's solution agrees; an invalid or hostile case was refused with
    a daemodel error (or a non-zero CLI status); an ``"either"`` case did one of both.

Expectations (``Case.expect``): ``"valid"`` (must solve within ``tol``), ``"invalid"`` (must raise
a daemodel error), ``"hostile"`` (must raise a daemodel error and create no file), ``"either"``
(an edge input for which refusing and solving correctly are both right).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field

import numpy as np

OUTCOMES = ("ok", "code-executed", "raw-exception", "hang", "silently-wrong", "refused-valid")
EXPECTS = ("valid", "invalid", "hostile", "either")
CATEGORIES = (
    "issue",
    "expr-valid",
    "expr-edge",
    "expr-hostile",
    "options",
    "dae-index1",
    "dae-index2",
    "dae-pendulum",
    "model-edge",
    "api-edge",
    "known-bad",
    "cli",
)
# Every string of a case that contains this is rewritten, in the child, to the absolute path of
# the case's canary file.
CANARY = "@CANARY@"
HERE = os.path.dirname(os.path.abspath(__file__))
# Defaults of the runner: seconds per case, and address space a child may add to what the
# preloaded interpreter already maps (a case that asks for a 1e11-step grid must fail, not swap).
DEFAULT_TIMEOUT = 20.0
DEFAULT_MEMORY_GIB = 4.0
# Independent solutions: solve_ivp's tolerances (well below every case tolerance).
REF_RTOL, REF_ATOL = 1e-11, 1e-12
# A generated problem is kept only if its solution stays in this box and is cheap (non-stiff).
TAME_MAX_Y, TAME_MAX_Z, TAME_MAX_NFEV = 30.0, 100.0, 60_000


# ================================================================================================
# Cases
# ================================================================================================
@dataclass
class Case:
    """One fuzz case.

    Attributes
    ----------
    category : str
        One of :data:`CATEGORIES`.
    description : str
        One line for a report.
    expect : str
        One of :data:`EXPECTS`.
    steps : tuple of (str, tuple, dict)
        Calls that build the model: ``("Model", (name,), {})`` then ``(method, args, kwargs)`` on it.
    action : str
        Key of :data:`ACTIONS`.
    args : dict
        The action's arguments (``t_span``, ``method``, ``options``, ``y0``, ``argv``, ...).
    reference : Reference or list of Reference, optional
        The independent solution (a list for a batch, one per sample).
    tol : float
        Relative tolerance against the reference.
    check : str
        Key of :data:`CHECKS` applied to what the action returned.
    id : str
    timeout : float, optional
        Seconds before the case counts as a hang (default: the run's).
    """

    category: str
    description: str
    expect: str
    steps: tuple = ()
    action: str = "solve"
    args: dict = field(default_factory=dict)
    reference: object = None
    tol: float = 1e-6
    check: str = "solution"
    id: str = ""
    timeout: float | None = None
    # times where the reference is not compared: a jump in t, where the solution gives the value after
    # it (daemodel.solving.switches) and the reference the model's value at that instant (sign(0) = 0)
    skip_times: tuple = ()

    def __post_init__(self) -> None:
        if self.expect not in EXPECTS:
            raise ValueError(f"expect must be one of {EXPECTS}; got {self.expect!r}")
        if self.category not in CATEGORIES:
            raise ValueError(f"category must be one of {CATEGORIES}; got {self.category!r}")

    def program(self) -> str:
        """The case as Python-like source, to reproduce it by hand."""
        lines = []
        for name, args, kwargs in self.steps:
            call = ", ".join([*(_short_repr(a) for a in args), *(f"{k}={_short_repr(v)}" for k, v in kwargs.items())])
            lines.append(f"m = dm.Model({call})" if name == "Model" else f"m.{name}({call})")
        a = dict(self.args)
        if self.action == "solve":
            target = f"m.compile({_kw(a.pop('compile'))})" if "compile" in a else "m"
            then = a.pop("then", None)
            a.pop("expect_times", None)
            options = a.pop("options", {})
            t_span = a.pop("t_span", None)
            lines.append(f"sol = dm.solve({target}, {_short_repr(t_span)}, {_kw({**a, **options})})")
            if then:
                lines.append(f"sol.{then[0]}({', '.join(_short_repr(x) for x in then[1:])})")
        elif self.action == "cli":
            for fname, content in a.get("files", {}).items():
                lines.append(f"# file {fname}:\n{content}")
            lines.append(f"daemodel.comparing.cli.main({a.get('argv')!r})")
        else:
            lines.append(f"{self.action}({_kw(a)})")
        return "\n".join(lines)


def _short_repr(value, limit: int = 400) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit // 2] + f"...<{len(text)} chars>..." + text[-limit // 4 :]


def _kw(d: dict) -> str:
    return ", ".join(f"{k}={_short_repr(v)}" for k, v in d.items())


@dataclass(frozen=True)
class Lazy:
    """A value built in the child: ``eval(code)`` with ``np``, ``sp`` (sympy), ``math``, ``fuzz_cases``.

    For values that must not exist in the parent (sympy objects, PINNConfig with bad fields).
    """

    code: str

    def __repr__(self) -> str:
        return self.code


@dataclass(frozen=True)
class PinnSpec:
    """``dm.PINNConfig(**kwargs)``, built in the child so that its errors belong to the case."""

    kwargs: dict

    def __repr__(self) -> str:
        return f"dm.PINNConfig({_kw(self.kwargs)})"


class Refused(Exception):
    """The CLI exited with a non-zero status: a refusal, like a daemodel error."""


def bad_reference(t):
    """A reference that names no variable of any model (for compare/errors cases)."""
    return {"not_a_variable": np.asarray(t, dtype=float) * 0.0}


# ================================================================================================
# Expression trees: one tree, two printers (daemodel's string syntax, and numpy evaluation)
# ================================================================================================
# ("num", value, text) ("var", name) ("add", (a, ...)) ("mul", (a, ...)) ("sub", a, b) ("div", a, b)
# ("pow", a, num) ("neg", a) ("fn", name, (args...)) ("pw", ((value, cond), ...), default)
# conditions: ("cmp", op, a, b) ("and", c, c) ("or", c, c)
def num(value, text: str | None = None):
    value = float(value)
    if text is None:
        text = repr(value)
    if text.startswith("-"):
        text = f"({text})"
    return ("num", value, text)


def var(name: str):
    return ("var", name)


TIME = ("var", "t")


def add(*a):
    return ("add", tuple(a))


def mul(*a):
    return ("mul", tuple(a))


def sub(a, b):
    return ("sub", a, b)


def div(a, b):
    return ("div", a, b)


def power(a, k):
    return ("pow", a, k)


def neg(a):
    return ("neg", a)


def fn(name: str, *args):
    return ("fn", name, tuple(args))


# The generators nest expressions up to 400 deep (gen_expr_edge), and show / evaluate recurse
# two frames a level: room for that, far below what the C stack allows.
EXPRESSION_RECURSION_LIMIT = 10_000


def show(e) -> str:
    """The tree as a daemodel expression string."""
    kind = e[0]
    if kind == "num":
        return e[2]
    if kind == "var":
        return e[1]
    if kind == "add":
        return "(" + " + ".join(show(a) for a in e[1]) + ")"
    if kind == "mul":
        return "(" + "*".join(show(a) for a in e[1]) + ")"
    if kind == "sub":
        return f"({show(e[1])} - {show(e[2])})"
    if kind == "div":
        return f"({show(e[1])}/{show(e[2])})"
    if kind == "pow":
        return f"({show(e[1])})**{show(e[2])}"
    if kind == "neg":
        return f"(-{show(e[1])})"
    if kind == "fn":
        return f"{e[1]}({', '.join(show(a) for a in e[2])})"
    if kind == "pw":
        pairs = ", ".join(f"({show(v)}, {_show_cond(c)})" for v, c in e[1])
        return f"Piecewise({pairs}, ({show(e[2])}, True))"
    raise ValueError(kind)


def _show_cond(c) -> str:
    if c[0] == "cmp":
        return f"{show(c[2])} {c[1]} {show(c[3])}"
    op = "&" if c[0] == "and" else "|"
    return f"({_show_cond(c[1])}) {op} ({_show_cond(c[2])})"


def _max(*a):
    return functools.reduce(np.maximum, a)


def _min(*a):
    return functools.reduce(np.minimum, a)


def _erf(x):
    from scipy.special import erf

    return erf(x)


NUMPY_FUNCTIONS = {
    "sin": np.sin,
    "cos": np.cos,
    "tan": np.tan,
    "exp": np.exp,
    "log": np.log,
    "sqrt": np.sqrt,
    "tanh": np.tanh,
    "sinh": np.sinh,
    "cosh": np.cosh,
    "atan": np.arctan,
    "asinh": np.arcsinh,
    "Abs": np.abs,
    "sign": np.sign,
    "atan2": np.arctan2,
    "Max": _max,
    "Min": _min,
    "erf": _erf,
}


def evaluate(e, env: dict):
    """The tree's value with numpy; ``env`` maps names (and ``t``) to floats or arrays."""
    kind = e[0]
    if kind == "num":
        return e[1]
    if kind == "var":
        return env[e[1]]
    if kind == "add":
        total = 0.0
        for a in e[1]:
            total = total + evaluate(a, env)
        return total
    if kind == "mul":
        total = 1.0
        for a in e[1]:
            total = total * evaluate(a, env)
        return total
    if kind == "sub":
        return evaluate(e[1], env) - evaluate(e[2], env)
    if kind == "div":
        return evaluate(e[1], env) / evaluate(e[2], env)
    if kind == "pow":
        return np.power(evaluate(e[1], env), evaluate(e[2], env))
    if kind == "neg":
        return -evaluate(e[1], env)
    if kind == "fn":
        return NUMPY_FUNCTIONS[e[1]](*(evaluate(a, env) for a in e[2]))
    if kind == "pw":
        out = evaluate(e[2], env)
        for value, cond in reversed(e[1]):
            out = np.where(_cond(cond, env), evaluate(value, env), out)
        return out
    raise ValueError(kind)


def _cond(c, env):
    if c[0] == "cmp":
        a, b = evaluate(c[2], env), evaluate(c[3], env)
        return {"<": np.less, ">": np.greater, "<=": np.less_equal, ">=": np.greater_equal}[c[1]](a, b)
    f = np.logical_and if c[0] == "and" else np.logical_or
    return f(_cond(c[1], env), _cond(c[2], env))


class ExprGen:
    """Random expression trees over ``names`` that stay finite for bounded arguments.

    Domains are built in: ``log(1 + u**2)``, ``sqrt(2 + cos(u))``, ``u/(2 + v**2)``,
    ``atan2(u, 1.5 + cos(v))``, ``tan(0.7*tanh(u))``, ``exp(tanh(u))``.  ``kink`` records a
    continuous but non-smooth function (Abs, Max, Min, a continuous Piecewise); ``jump`` a
    discontinuity in time (``sign(t - c)``, ``Piecewise((a, t < c), ...)``), small in size.
    """

    UNARY = ("sin", "cos", "tanh", "atan", "exp", "log", "sqrt", "tan", "asinh", "erf", "sinh", "cosh")

    def __init__(self, rng: random.Random, names, t_span=(0.0, 1.0), *, kinks=True, jumps=True):
        self.rng, self.names = rng, list(names)
        self.t_span = t_span
        self.allow_kinks, self.allow_jumps = kinks, jumps
        self.kink = self.jump = False
        self.jump_times = []  # (where the jumps are: a value exactly there may be either side's)

    def number(self):
        r, rng = self.rng.random(), self.rng
        if r < 0.5:
            v = round(rng.uniform(-2, 2), 2)
            return num(v, f"{v}")
        if r < 0.65:
            v = rng.randint(-3, 3)
            return num(v, f"{v}")
        if r < 0.8:
            p, q = rng.randint(1, 9), rng.randint(2, 9)
            return num(p / q, f"{p}/{q}")
        if r < 0.9:
            return num(math.pi, "pi")
        m, k = rng.randint(1, 9), rng.randint(1, 3)
        return num(m * 10.0**-k, f"{m}e-{k}")

    def leaf(self):
        r = self.rng.random()
        if r < 0.6 and self.names:
            return var(self.rng.choice(self.names))
        if r < 0.7:
            return TIME
        return self.number()

    def coefficient(self, low=0.2, high=1.5):
        v = round(self.rng.uniform(low, high), 2)
        return num(v, f"{v}")

    def expr(self, depth: int):
        rng = self.rng
        if depth <= 0 or rng.random() < 0.15:
            return self.leaf()
        d = depth - 1
        ops = ["add", "sub", "mul", "div", "unary", "unary", "pow", "atan2"]
        if self.allow_kinks:
            ops += ["Abs", "Max", "Min", "pw_cont", "sign_mul", "relu"]
        if self.allow_jumps and rng.random() < 0.3:
            ops += ["sign_t", "pw_t"]
        op = rng.choice(ops)
        if op == "add":
            return add(*(self.expr(d) for _ in range(rng.randint(2, 3))))
        if op == "sub":
            return sub(self.expr(d), self.expr(d))
        if op == "mul":
            return mul(self.coefficient(), self.expr(d), self.expr(d))
        if op == "div":
            if rng.random() < 0.5:
                return div(self.expr(d), add(num(2, "2"), power(self.expr(d), num(2, "2"))))
            return div(self.expr(d), add(num(1.5, "1.5"), fn("cos", self.expr(d))))
        if op == "pow":
            u = self.expr(d)
            k, value = rng.choice([("2", 2.0), ("3", 3.0), ("-1", -1.0), ("0.5", 0.5), ("1.5", 1.5), ("-1/2", -0.5)])
            if k in ("2", "3"):
                return power(fn("tanh", u) if k == "3" else u, num(value, k))
            return power(add(num(1, "1"), power(u, num(2, "2"))), num(value, k))
        if op == "atan2":
            return fn("atan2", self.expr(d), add(num(1.5, "1.5"), fn("cos", self.expr(d))))
        if op == "unary":
            name = rng.choice(self.UNARY)
            u = self.expr(d)
            if name == "exp":
                inner = rng.choice([fn("tanh", u), fn("sin", u), neg(power(u, num(2, "2")))])
                return fn("exp", inner)
            if name == "log":
                return fn("log", rng.choice([add(num(1, "1"), power(u, num(2, "2"))), add(num(2, "2"), fn("sin", u))]))
            if name == "sqrt":
                return fn("sqrt", rng.choice([add(num(1, "1"), power(u, num(2, "2"))), add(num(2, "2"), fn("cos", u))]))
            if name == "tan":
                return fn("tan", mul(num(0.7, "0.7"), fn("tanh", u)))
            if name in ("sinh", "cosh"):
                return fn(name, fn("tanh", u))
            return fn(name, u)
        self.kink = self.kink or op in ("Abs", "Max", "Min", "pw_cont", "sign_mul", "relu")
        if op == "Abs":
            return fn("Abs", self.expr(d))
        if op in ("Max", "Min"):
            return fn(op, *(self.expr(d) for _ in range(rng.randint(2, 3))))
        if op == "pw_cont":  # continuous: both branches equal a where u = 0
            a, u = self.expr(d), self.expr(d)
            return ("pw", ((a, ("cmp", rng.choice([">", ">="]), u, num(0, "0"))),), add(a, mul(num(0.5, "0.5"), u)))
        if op == "relu":  # max(u, 0) with an integer branch
            u = self.expr(d)
            return ("pw", ((u, ("cmp", ">", u, num(0, "0"))),), num(0, "0"))
        if op == "sign_mul":  # sign(u)*u = |u|
            u = self.expr(d)
            return mul(fn("sign", u), u)
        self.jump = True
        t0, t1 = self.t_span
        c = round(rng.uniform(t0 + 0.15 * (t1 - t0), t1 - 0.15 * (t1 - t0)), 2)
        self.jump_times.append(c)
        if op == "sign_t":
            return mul(num(0.05, "0.05"), fn("sign", sub(TIME, num(c, f"{c}"))))
        a, b = self.expr(d), self.expr(d)
        return ("pw", ((a, ("cmp", "<", TIME, num(c, f"{c}"))),), add(a, mul(num(0.05, "0.05"), fn("tanh", b))))


# ================================================================================================
# Independent solutions
# ================================================================================================
class Reference:
    """``reference(t) -> dict name -> ndarray (T,)``, computed without daemodel."""

    names: tuple = ()

    def __call__(self, t):
        raise NotImplementedError


@dataclass
class Exact(Reference):
    """Closed forms: ``trees`` maps each name to a tree in ``t``."""

    trees: dict

    @property
    def names(self):
        return tuple(self.trees)

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        return {
            k: np.broadcast_to(np.asarray(evaluate(e, {"t": t}), dtype=float), t.shape) for k, e in self.trees.items()
        }


class TooCostly(RuntimeError):
    """An independent solution that would take more evaluations than it is allowed."""


class NoTameProblem(RuntimeError):
    """A generator found no tame problem in its bounded number of attempts."""


@dataclass
class TreeODE(Reference):
    """``y' = rhs(t, y, z, p)`` with ``z`` given by ``zrules`` from ``(t, y, p)``, solved by scipy.

    zrules (evaluated in order; each sees t, the states, the parameters and earlier z):

    * ``("explicit", z, e)``: ``z = e``
    * ``("cubic", z, e)``: the real root of ``z**3 + z = e``
    * ``("log", z, e)``: ``z = log(e)`` (from ``exp(z) = e``)
    * ``("monotone", z, e, k)``: the root of ``z + k*sin(z) = e`` (bisection, ``k < 1``)
    * ``("linear", zs, A, es)``: ``A z = es``
    * ``("index2", zs, M, C, fs, dpsis)``: ``z = M^-1 (dpsi - C f)`` (``y' = f + B z``, ``C y = psi``, ``M = C B``)
    * ``("index2_nl", z, c, cb, fs, dpsi, k)``: ``u = c.y``, ``z = (dpsi / (1 + k cos u) - c.f) / cb``
      (``y' = f + b z``, ``u + k sin u = psi``, ``cb = c.b``)
    """

    states: tuple
    rhs: tuple
    algebraics: tuple
    zrules: tuple
    params: dict
    y0: tuple
    t_span: tuple
    integrator: str = "DOP853"
    _solution: object = field(default=None, repr=False, compare=False)

    @property
    def names(self):
        return (*self.states, *self.algebraics)

    def __getstate__(self):  # the scipy solution is recomputed where it is needed
        return {**self.__dict__, "_solution": None}

    def _env(self, t, y):
        env = {"t": t, **self.params}
        env.update(zip(self.states, y, strict=True))
        for rule in self.zrules:
            kind = rule[0]
            if kind == "explicit":
                env[rule[1]] = evaluate(rule[2], env)
            elif kind == "cubic":
                a = evaluate(rule[2], env)
                s = np.sqrt(a * a / 4 + 1 / 27)
                env[rule[1]] = np.cbrt(a / 2 + s) + np.cbrt(a / 2 - s)
            elif kind == "log":
                env[rule[1]] = np.log(evaluate(rule[2], env))
            elif kind == "monotone":
                a, k = np.asarray(evaluate(rule[2], env), dtype=float), rule[3]
                lo, hi = a - k - 1e-3, a + k + 1e-3
                if a.ndim == 0:  # one time (inside solve_ivp): the same steps on scalars, 6x faster
                    a, lo, hi = float(a), float(lo), float(hi)
                    for _ in range(64):
                        mid = 0.5 * (lo + hi)
                        if mid + k * float(np.sin(mid)) > a:
                            hi = mid
                        else:
                            lo = mid
                    env[rule[1]] = np.float64(0.5 * (lo + hi))
                    continue
                for _ in range(64):
                    mid = 0.5 * (lo + hi)
                    up = mid + k * np.sin(mid) > a
                    hi, lo = np.where(up, mid, hi), np.where(up, lo, mid)
                env[rule[1]] = 0.5 * (lo + hi)
            elif kind == "linear":
                _, zs, A, es = rule
                rhs = np.array([np.broadcast_to(evaluate(e, env), np.shape(t)) for e in es], dtype=float)
                z = np.linalg.solve(np.asarray(A, dtype=float), rhs)
                env.update(zip(zs, z, strict=True))
            elif kind == "index2":
                _, zs, M, C, fs, dpsis = rule
                f = np.array([np.broadcast_to(evaluate(e, env), np.shape(t)) for e in fs], dtype=float)
                dpsi = np.array([np.broadcast_to(evaluate(e, env), np.shape(t)) for e in dpsis], dtype=float)
                z = np.linalg.solve(np.asarray(M, dtype=float), dpsi - np.asarray(C, dtype=float) @ f)
                env.update(zip(zs, z, strict=True))
            elif kind == "index2_nl":
                _, zname, c, cb, fs, dpsi, k = rule
                u = sum(ci * env[s] for ci, s in zip(c, self.states, strict=True))
                cf = sum(ci * evaluate(e, env) for ci, e in zip(c, fs, strict=True))
                env[zname] = (evaluate(dpsi, env) / (1 + k * np.cos(u)) - cf) / cb
            else:
                raise ValueError(kind)
        return env

    def solve(self, max_nfev: int | None = None):
        """scipy's solution; with ``max_nfev``, a :class:`TooCostly` error once the right-hand side has
        been evaluated more often than that (scipy has no such limit: where the step size collapses,
        near a blow-up or a jump in y, it would go on for hours, making its steps ever shorter)."""
        if self._solution is None:
            from scipy.integrate import solve_ivp

            calls = 0

            def f(t, y):
                nonlocal calls
                calls += 1
                if max_nfev is not None and calls > max_nfev:
                    raise TooCostly(f"independent solution needs more than {max_nfev} evaluations")
                env = self._env(t, y)
                return np.array([np.broadcast_to(evaluate(e, env), ()) for e in self.rhs], dtype=float)

            sol = solve_ivp(
                f,
                self.t_span,
                np.asarray(self.y0, dtype=float),
                method=self.integrator,
                rtol=REF_RTOL,
                atol=REF_ATOL,
                dense_output=True,
            )
            if sol.status != 0:
                raise RuntimeError(f"independent solution failed: {sol.message}")
            self._solution = sol
        return self._solution

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        y = self.solve().sol(t)
        env = self._env(t, y)
        return {k: np.broadcast_to(np.asarray(env[k], dtype=float), t.shape) for k in self.names}

    def tame(self) -> bool:
        """Solvable, bounded and cheap (a generated problem is kept only then)."""
        try:
            with np.errstate(all="ignore"):
                # scipy counts every call of the right-hand side in nfev, so stopping one call past
                # the limit rejects exactly the problems the nfev test below would reject
                sol = self.solve(max_nfev=TAME_MAX_NFEV)
                t = np.linspace(*self.t_span, 201)
                values = self(t)
        except (RuntimeError, ValueError, FloatingPointError, np.linalg.LinAlgError):
            return False
        if sol.nfev > TAME_MAX_NFEV:
            return False
        ys = np.array([values[s] for s in self.states])
        zs = np.array([values[z] for z in self.algebraics]) if self.algebraics else np.zeros(1)
        return bool(
            np.all(np.isfinite(ys))
            and np.all(np.isfinite(zs))
            and np.abs(ys).max() < TAME_MAX_Y
            and np.abs(zs).max() < TAME_MAX_Z
        )


@dataclass
class Pendulum(Reference):
    """The planar pendulum ``y1' = y3, y2' = y4, y3' = -y1 y5, y4' = -y2 y5 - lam`` on a circle of
    radius L, through its angle: ``phi'' = -lam cos(phi) / L``, ``y5 = phi'^2 - lam sin(phi) / L``."""

    phi0: float
    omega0: float
    lam: float
    length: float
    t_span: tuple
    names: tuple = ("y1", "y2", "y3", "y4", "y5")
    _solution: object = field(default=None, repr=False, compare=False)

    def __getstate__(self):
        return {**self.__dict__, "_solution": None}

    def __call__(self, t):
        from scipy.integrate import solve_ivp

        if self._solution is None:
            lam, L = self.lam, self.length
            self._solution = solve_ivp(
                lambda _, u: [u[1], -lam * np.cos(u[0]) / L],
                self.t_span,
                [self.phi0, self.omega0],
                method="DOP853",
                rtol=1e-12,
                atol=1e-12,
                dense_output=True,
            )
        t = np.asarray(t, dtype=float)
        phi, w = self._solution.sol(t)
        L = self.length
        values = (
            L * np.cos(phi),
            L * np.sin(phi),
            -L * w * np.sin(phi),
            L * w * np.cos(phi),
            w * w - self.lam * np.sin(phi) / L,
        )
        return dict(zip(self.names, values, strict=True))


# ================================================================================================
# The child: build, act, check
# ================================================================================================
def _substitute(value, path: str):
    if isinstance(value, str):
        return value.replace(CANARY, path)
    if isinstance(value, tuple):
        return tuple(_substitute(v, path) for v in value)
    if isinstance(value, list):
        return [_substitute(v, path) for v in value]
    if isinstance(value, dict):
        return {_substitute(k, path): _substitute(v, path) for k, v in value.items()}
    if isinstance(value, PinnSpec):
        return PinnSpec(_substitute(value.kwargs, path))
    if isinstance(value, Lazy):
        return Lazy(_substitute(value.code, path))
    return value


def _resolve(value):
    """Build Lazy and PinnSpec values (in the child)."""
    if isinstance(value, Lazy):
        import sympy as sp

        return eval(value.code, {"np": np, "sp": sp, "math": math, "fuzz_cases": sys.modules[__name__]})
    if isinstance(value, PinnSpec):
        import daemodel as dm

        return dm.PINNConfig(**_resolve(value.kwargs))
    if isinstance(value, tuple):
        return tuple(_resolve(v) for v in value)
    if isinstance(value, list):
        return [_resolve(v) for v in value]
    if isinstance(value, dict):
        return {k: _resolve(v) for k, v in value.items()}
    return value


# Where the child is: "build" while the model's declarations run, "action" after them (a hostile
# string must be refused by the declaration that receives it, not by a later step).
_STAGE = ["build"]


def _build(case: Case):
    import daemodel as dm

    _STAGE[0] = "build"
    model = None
    for name, args, kwargs in case.steps:
        args, kwargs = _resolve(args), _resolve(kwargs)
        if name == "Model":
            model = dm.Model(*args, **kwargs)
        else:
            getattr(model, name)(*args, **kwargs)
    _STAGE[0] = "action"
    return model


def _act_build(case, workdir):
    return _build(case)


def _act_compile(case, workdir):
    return _build(case).compile(**_resolve(case.args.get("compile", {})))


def _act_solve(case, workdir):
    import daemodel as dm

    model = _build(case)
    a = _resolve(case.args)
    target = model.compile(**a["compile"]) if "compile" in a else model
    kwargs = {k: a[k] for k in ("method", "y0", "z0", "parameters") if k in a}
    sol = dm.solve(target, a["t_span"], **kwargs, **a.get("options", {}))
    then = a.get("then")
    if then:
        return getattr(sol, then[0])(*then[1:])
    return sol


def _act_compare(case, workdir):
    import daemodel as dm

    model = _build(case)
    a = _resolve(case.args)
    result = dm.compare(model, a["t_span"], a.get("methods"), **a.get("kwargs", {}))
    result.table()
    if "save" in a:
        result.save(a["save"])
    return result


def _act_cli(case, workdir):
    import contextlib
    import io

    from daemodel.comparing.cli import main

    for name, content in case.args.get("files", {}).items():
        path = os.path.join(workdir, name)
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        with open(path, "wb") as f:
            f.write(content.encode() if isinstance(content, str) else content)
    for name in case.args.get("dirs", ()):
        os.makedirs(os.path.join(workdir, name), exist_ok=True)
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = main(list(case.args["argv"]))
    except SystemExit as exit_:
        status = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 2)
    if status:
        raise Refused(f"exit status {status}: {err.getvalue().strip().splitlines()[-1:] or ''}")
    return status


def _act_pinnconfig(case, workdir):
    import daemodel as dm

    return dm.PINNConfig(**_resolve(case.args["kwargs"]))


def _act_surrogate_train(case, workdir):
    import daemodel as dm

    a = _resolve(case.args)
    return dm.Surrogate.train(_build(case), a["t_span"], **a.get("kwargs", {}))


def _act_surrogate_load(case, workdir):
    import daemodel as dm

    for name, content in case.args.get("files", {}).items():
        with open(os.path.join(workdir, name), "wb") as f:
            f.write(content.encode() if isinstance(content, str) else content)
    return dm.Surrogate.load(case.args["path"], _build(case))


ACTIONS = {
    "build": _act_build,
    "compile": _act_compile,
    "solve": _act_solve,
    "compare": _act_compare,
    "cli": _act_cli,
    "pinnconfig": _act_pinnconfig,
    "surrogate_train": _act_surrogate_train,
    "surrogate_load": _act_surrogate_load,
}


def _check_none(case, value):
    return True, ""


def _check_cli(case, value):
    out = case.args.get("out")
    if out and not (os.path.isdir(out) and os.listdir(out)):
        return False, f"exit status 0 but nothing written to {out}"
    return True, ""


def _check_solution(case, sol):
    """A finite solution on the requested times that agrees with the reference within ``case.tol``."""
    t = np.asarray(sol.t, dtype=float)
    a = case.args
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        return False, f"bad time grid (shape {t.shape})"
    if np.any(np.diff(t) < 0):
        return False, "times decrease"
    wanted = a.get("expect_times")
    if wanted is not None:
        wanted = np.asarray(wanted, dtype=float).reshape(-1)
        if t.shape != wanted.shape or np.max(np.abs(t - wanted)) > 1e-9 * max(1.0, np.max(np.abs(wanted))):
            return False, f"times {t[:3]}... (T={t.size}) differ from t_eval (T={wanted.size})"
    else:
        t0, t1 = (float(v) for v in a["t_span"])
        slack = 1e-9 * max(1.0, abs(t0), abs(t1))
        if abs(t[0] - t0) > slack or abs(t[-1] - t1) > slack:
            return False, f"solution covers [{t[0]:.6g}, {t[-1]:.6g}], not t_span = ({t0:.6g}, {t1:.6g})"
    refs = case.reference
    batch = isinstance(refs, list)
    names = (refs[0] if batch else refs).names if refs is not None else tuple(sol.names)
    expected = [r(t) for r in refs] if batch else ([refs(t)] if refs is not None else None)
    worst, where = 0.0, ""
    for name in names:
        values = np.asarray(sol[name], dtype=float)
        if not np.all(np.isfinite(values)):
            return False, f"non-finite values of {name!r}"
        if expected is None:
            continue
        got = values if batch else values[None, ...]
        if got.shape != (len(expected), t.size):
            return (
                False,
                f"{name!r} has shape {values.shape}; expected {(len(expected), t.size) if batch else (t.size,)}",
            )
        for b, ref in enumerate(expected):
            r = np.asarray(ref[name], dtype=float)
            err = np.abs(got[b] - r) / (1 + np.abs(r))
            for jump in (*case.skip_times, *_switch_times(sol)):
                err[np.abs(t - jump) <= 1e-9 * max(1.0, abs(jump))] = 0.0
            k = int(np.argmax(err))
            if err[k] > worst:
                worst = float(err[k])
                where = (
                    f"{name!r} at t={t[k]:.4g}"
                    + (f" sample {b}" if batch else "")
                    + f": {got[b, k]:.10g} vs {r[k]:.10g}"
                )
    if worst > case.tol:
        return False, f"scaled error {worst:.2e} > tol {case.tol:.1e} ({where})"
    return True, f"scaled error {worst:.1e}" if expected is not None else ""


CHECKS = {"solution": _check_solution, "none": _check_none, "cli": _check_cli}


def is_daemodel_error(error: BaseException) -> bool:
    """Whether ``error``'s class has a base defined in ``daemodel.errors``."""
    return any(getattr(k, "__module__", "") == "daemodel.errors" for k in type(error).__mro__)


def _first_line(text: str, limit: int = 300) -> str:
    line = (str(text).strip().splitlines() or [""])[0]
    return line if len(line) <= limit else line[:limit] + "..."


def _where(error: BaseException) -> str:
    frames = traceback.extract_tb(error.__traceback__)
    ours = [f for f in frames if "daemodel" in f.filename or "/backends/" in f.filename]
    frame = (ours or frames or [None])[-1]
    if frame is None:
        return ""
    parts = frame.filename.split(os.sep)
    short = os.sep.join(parts[-3:])
    return f"{short}:{frame.lineno} in {frame.name}"


def execute(case: Case, workdir: str) -> dict:
    """Run one case here (in the child); never raises.  Returns what happened, unclassified."""
    case = dataclasses.replace(
        case,
        steps=_substitute(case.steps, os.path.join(workdir, "canary")),
        args=_substitute(case.args, os.path.join(workdir, "canary")),
    )
    try:
        value = ACTIONS[case.action](case, workdir)
    except Refused as refusal:
        return {"kind": "refused", "type": "exit-status", "message": _first_line(refusal)}
    except BaseException as error:
        kind = "refused" if is_daemodel_error(error) else "raised"
        return {
            "kind": kind,
            "type": type(error).__name__,
            "message": _first_line(error),
            "where": _where(error),
            "stage": _STAGE[0],
        }
    status = getattr(value, "status", None)
    try:
        with np.errstate(all="ignore"):
            passed, detail = CHECKS[case.check](case, value)
    except BaseException as error:
        passed, detail = False, f"checking the result raised {type(error).__name__}: {_first_line(error)}"
    return {
        "kind": "returned",
        "passed": bool(passed),
        "detail": detail,
        "status": status if isinstance(status, str) else None,
    }


def classify(case: Case, raw: dict, canary: bool) -> tuple[str, str]:
    """``(outcome, why)`` from what happened (see the module docstring)."""
    if canary:
        return "code-executed", "the canary file exists"
    kind = raw["kind"]
    if kind == "timeout":
        return "hang", raw.get("detail", "")
    if kind in ("raised", "crash"):
        return "raw-exception", raw.get("message", "")
    if kind == "refused":
        if case.expect == "valid":
            return "refused-valid", raw.get("message", "")
        if case.expect == "hostile" and raw.get("stage") == "action":
            return "silently-wrong", f"the declaration accepted it; refused only later by {raw.get('type')}"
        return "ok", f"refused: {raw.get('type')}"
    # returned
    if case.expect in ("invalid", "hostile"):
        return "silently-wrong", "accepted an input that must be refused; " + raw.get("detail", "")
    if str(raw.get("status")).startswith("flagged"):
        # an answer whose own error estimate says it misses its accuracy, and says so: honest, not a
        # refusal (a fixed step across a switch keeps fewer digits than estimate_bound asks)
        return "ok", f"status {raw['status']!r}"
    if raw.get("status") not in (None, "success"):
        return ("refused-valid" if case.expect == "valid" else "ok"), f"status {raw['status']!r}"
    if not raw.get("passed"):
        return "silently-wrong", raw.get("detail", "")
    return "ok", raw.get("detail", "")


# ================================================================================================
# Running cases: a preloaded interpreter forks one child per case
# ================================================================================================
def _preload() -> dict:
    """Import daemodel and what its methods load on first use, so that each fork starts warm."""
    meta = {"python": sys.version.split()[0]}
    try:
        import daemodel

        meta["daemodel"] = os.path.dirname(os.path.abspath(daemodel.__file__))
    except BaseException as error:
        meta["import_error"] = f"{type(error).__name__}: {_first_line(error)}"
        return meta
    for module in (
        "daemodel.comparing.cli",
        "daemodel.backends.radau",
        "daemodel.backends.casadi.collocation",
        "daemodel.backends.casadi.idas",
        "daemodel.backends.reference",
        "daemodel.backends.pinn.backend",
        "daemodel.backends.pinn.surrogate",
        "daemodel.solving.surrogates",
        "torch",
        "casadi",
        "scipy.integrate",
        "scipy.optimize",
        "scipy.special",
        "sympy",
        "matplotlib.pyplot",
        "pandas",
    ):
        try:
            __import__(module)
        except BaseException as error:
            meta.setdefault("preload_errors", []).append(f"{module}: {type(error).__name__}")
    try:
        import daemodel.backends as backends

        meta["backends"] = os.path.dirname(os.path.abspath(backends.__file__))
    except BaseException:
        pass
    return meta


def _child(case: Case, workdir: str, memory_gib: float) -> None:
    """In the forked child: isolate, limit, execute, write ``result.json``, exit."""
    code = 0
    try:
        os.setsid()
        os.chdir(workdir)
        log = os.open(os.path.join(workdir, "log"), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(log, 1)
        os.dup2(log, 2)
        try:
            import resource

            with open("/proc/self/status") as f:
                vm = next((int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:")), 0)
            limit = int(vm + memory_gib * 2**30)
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        except (OSError, ValueError, ImportError, StopIteration):
            pass
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        raw = execute(case, workdir)
        with open(os.path.join(workdir, "result.tmp"), "w") as f:
            json.dump(raw, f, default=str)
        os.replace(os.path.join(workdir, "result.tmp"), os.path.join(workdir, "result.json"))
    except BaseException:
        code = 3
    finally:
        os._exit(code)


def _finish(case: Case, index: int, workdir: str, started: float, status, timed_out: bool, timeout: float) -> dict:
    canary = os.path.exists(os.path.join(workdir, "canary"))
    result_path = os.path.join(workdir, "result.json")
    if timed_out:
        raw = {"kind": "timeout", "detail": f"no result after {timeout:g} s"}
    elif os.path.exists(result_path):
        with open(result_path) as f:
            raw = json.load(f)
    else:
        tail = ""
        try:
            with open(os.path.join(workdir, "log"), errors="replace") as f:
                tail = " | ".join(f.read().strip().splitlines()[-3:])[-300:]
        except OSError:
            pass
        if status is not None and os.WIFSIGNALED(status):
            how = f"killed by signal {os.WTERMSIG(status)}"
        else:
            how = f"exited with status {os.WEXITSTATUS(status) if status is not None else '?'}"
        raw = {"kind": "crash", "type": "ChildDied", "message": f"child {how} without a result; log: {tail}"}
    outcome, why = classify(case, raw, canary)
    return {
        "index": index,
        "id": case.id,
        "category": case.category,
        "description": case.description,
        "expect": case.expect,
        "outcome": outcome,
        "why": why,
        "error_type": raw.get("type"),
        "message": raw.get("message"),
        "where": raw.get("where"),
        "detail": raw.get("detail"),
        "seconds": round(time.monotonic() - started, 3),
    }


def _serve(root: str, timeout: float, jobs: int, memory_gib: float) -> None:
    """The preloaded runner: fork a child per case of ``root/cases.pkl``, up to ``jobs`` at a time,
    and append one JSON line per case to ``root/results.jsonl`` (a meta line first)."""
    meta = _preload()
    with open(os.path.join(root, "cases.pkl"), "rb") as f:
        cases = pickle.load(f)
    out = open(os.path.join(root, "results.jsonl"), "a")
    out.write(json.dumps({"meta": meta}) + "\n")
    out.flush()
    pending = list(enumerate(cases))
    running: dict[int, tuple] = {}
    while pending or running:
        while pending and len(running) < jobs:
            index, case = pending.pop(0)
            workdir = tempfile.mkdtemp(prefix=f"case{index}-", dir=root)
            pid = os.fork()
            if pid == 0:
                _child(case, workdir, memory_gib)
            running[pid] = (index, case, workdir, time.monotonic())
        for pid in list(running):
            index, case, workdir, started = running[pid]
            done, status = os.waitpid(pid, os.WNOHANG)
            limit = case.timeout or timeout
            timed_out = not done and time.monotonic() - started > limit
            if timed_out:
                _kill_group(pid)
                _, status = os.waitpid(pid, 0)
            if done or timed_out:
                _kill_group(pid)  # workers the case left behind
                record = _finish(case, index, workdir, started, status, timed_out, limit)
                out.write(json.dumps(record, default=str) + "\n")
                out.flush()
                shutil.rmtree(workdir, ignore_errors=True)
                del running[pid]
        time.sleep(0.01)
    out.close()


def _kill_group(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def run_cases(
    cases, timeout: float = DEFAULT_TIMEOUT, jobs: int = 1, memory_gib: float = DEFAULT_MEMORY_GIB, on_result=None
) -> tuple[list[dict], dict]:
    """Run ``cases`` in children of one fresh interpreter; ``(results in case order, meta)``.

    The interpreter inherits this process's environment (``PYTHONPATH`` selects the daemodel
    under test) with one thread per BLAS/OpenMP library.  ``on_result(record)`` is called as
    each case finishes.
    """
    cases = list(cases)
    with tempfile.TemporaryDirectory(prefix="daemodel-fuzz-") as root:
        with open(os.path.join(root, "cases.pkl"), "wb") as f:
            pickle.dump(cases, f)
        env = dict(os.environ)
        env.update(
            OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MPLBACKEND="Agg", PYTHONHASHSEED="0"
        )
        code = (
            "import sys; sys.path.insert(0, sys.argv[1]); import fuzz_cases; "
            "fuzz_cases._serve(sys.argv[2], float(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5]))"
        )
        argv = [sys.executable, "-c", code, HERE, root, str(timeout), str(jobs), str(memory_gib)]
        errors = open(os.path.join(root, "runner.err"), "w+b")
        proc = subprocess.Popen(argv, env=env, cwd=root, stdout=subprocess.DEVNULL, stderr=errors)
        results: dict[int, dict] = {}
        meta: dict = {}
        path, offset = os.path.join(root, "results.jsonl"), 0

        def read_new():
            nonlocal offset, meta
            if not os.path.exists(path):
                return
            with open(path) as f:
                f.seek(offset)
                for line in f:
                    if not line.endswith("\n"):
                        break
                    offset += len(line.encode())
                    record = json.loads(line)
                    if "meta" in record:
                        meta = record["meta"]
                        continue
                    results[record["index"]] = record
                    if on_result is not None:
                        on_result(record)

        while proc.poll() is None:
            read_new()
            time.sleep(0.2)
        read_new()
        errors.seek(0)
        stderr = errors.read().decode(errors="replace")
        errors.close()
        if proc.returncode != 0:
            meta["runner_error"] = stderr.strip()[-2000:]
    out = []
    for index, case in enumerate(cases):
        out.append(
            results.get(index)
            or {
                "index": index,
                "id": case.id,
                "category": case.category,
                "description": case.description,
                "expect": case.expect,
                "outcome": "raw-exception",
                "why": "the runner died",
                "error_type": "HarnessError",
                "message": meta.get("runner_error", "")[-300:],
                "where": None,
                "detail": None,
                "seconds": 0.0,
            }
        )
    return out, meta


def run_case(case: Case, timeout: float = DEFAULT_TIMEOUT) -> dict:
    """Run one case in a child process; its record (``record["outcome"]`` is one of :data:`OUTCOMES`)."""
    return run_cases([case], timeout=timeout)[0][0]


# ================================================================================================
# Generators: pieces
# ================================================================================================
PLAIN = ("plain",)
# Identifiers that are legal names but collide with something somewhere (generated torch or casadi
# source, sympy's parser, Python builtins).  A model using them must solve correctly or refuse
# the name with a daemodel error.
TRICKY_NAMES = (
    "select",
    "where",
    "torch",
    "np",
    "math",
    "p",
    "y",
    "z",
    "out",
    "self",
    "cls",
    "stack",
    "cat",
    "ones",
    "zeros",
    "float",
    "int",
    "list",
    "dict",
    "len",
    "range",
    "sum",
    "max",
    "min",
    "print",
    "x0",
    "dt",
    "h",
    "T",
    "Y",
    "Z",
    "P",
    "I",
    "E",
    "S",
    "N",
    "O",
    "Q",
    "C",
    "e",
    "j",
    "inf",
    "nan",
    "oo",
    "zoo",
    "grad",
    "dtype",
    "device",
    "casadi",
    "sympy",
    "lambda_",
    "tensor",
    "result",
    "batch",
    "shape",
    "eye",
    "fmax",
    "if_else",
    "vertcat",
    "MX",
    "SX",
    "DM",
    "jacobian",
    "fn",
    "args",
    "kwargs",
    "Matrix",
    "Eq",
    "Lambda",
    "beta",
    "gamma",
    "zeta",
    "lambda1",
    "re",
    "im",
    "arg",
    "floor",
    "ceiling",
    "Mod",
    "And",
    "Or",
    "Not",
    "true",
    "false",
    "None1",
    "x_",
    "y__1",
)


def _names(rng: random.Random, n: int, m: int, k: int, tricky_p: float = 0.2):
    if rng.random() < tricky_p:
        pool = rng.sample(TRICKY_NAMES, n + m + k)
        return pool[:n], pool[n : n + m], pool[n + m :], True
    return [f"y{i + 1}" for i in range(n)], [f"z{j + 1}" for j in range(m)], [f"k{i + 1}" for i in range(k)], False


def _span(rng: random.Random):
    if rng.random() < 0.75:
        return (0.0, 1.0)
    t0 = rng.choice([0.0, 0.5, -1.0, 2.0])
    return (t0, t0 + rng.choice([0.5, 2.0]))


def _model_steps(name, states, algebraics, params, odes, constraints, initial, t0=0.0):
    steps = [("Model", (name,), {}), ("states", (" ".join(states),), {})]
    if algebraics:
        steps.append(("algebraics", (" ".join(algebraics),), {}))
    for p, v in params.items():
        steps.append(("parameter", (p, v), {}))
    for s, text in odes:
        steps.append(("ode", (s, text), {}))
    for text, cname in constraints:
        steps.append(("constraint", (text,), {} if cname is None else {"name": cname}))
    init = dict(initial)
    if t0 != 0.0:
        init["t"] = t0
    steps.append(("initial", (), init))
    return tuple(steps)


@dataclass
class _Problem:
    """A generated model with its independent solution."""

    desc: str
    steps: tuple
    reference: object
    t_span: tuple
    kink: bool = False
    jump: bool = False
    expect: str = "valid"  # "either" when the names are tricky
    batch_refs: list | None = None
    batch_y0: dict | None = None
    batch_params: dict | None = None
    jump_times: tuple = ()


def _expect(tricky: bool, jump: bool) -> str:
    """Valid, or "either" where refusing is also right: names that collide with something, or a
    jump in t (an adaptive code may give up there with an error; it must not return a wrong answer)."""
    return "either" if tricky or jump else "valid"


def _tol_fixed(h: float, s: int) -> float:
    # Collocation error: y order 2s-1, index-2 z order s; 30 h^s bounds both on these problems.
    return max(1e-7, 30.0 * h**s)


def _finish_tol(tol: float, prob: _Problem, fixed_h: float | None, float32: bool = False) -> float:
    if prob.kink:
        tol = max(tol, 10 * fixed_h**2) if fixed_h else max(tol, 1e-4)
    if prob.jump:
        tol = max(tol, 0.2 * fixed_h) if fixed_h else max(tol, 1e-3)
    if float32:
        tol = max(tol, 2e-3)
    return min(tol, 0.5)


def _valid_method(rng: random.Random, prob: _Problem, allow_pinn: bool = True):
    """A method with valid options and the tolerance its answer must meet: ``(method, options, tol, text)``."""
    span = prob.t_span[1] - prob.t_span[0]
    r = rng.random()
    if r < 0.3:
        s, h = rng.choice([2, 3, 3, 4, 5]), span * rng.choice([0.1, 0.05, 0.025, 0.02])
        return "radau", {"stages": s, "h": h}, _finish_tol(_tol_fixed(h, s), prob, h), f"radau s={s} h={h:g}"
    if r < 0.45:
        rtol = rng.choice([1e-5, 1e-6, 1e-8])
        opts = {"rtol": rtol, "atol": rtol * 1e-2}
        return "radau", opts, _finish_tol(max(1e-6, 1000 * rtol), prob, None), f"radau adaptive rtol={rtol:g}"
    if r < 0.63:
        s, h = rng.choice([2, 3, 4]), span * rng.choice([0.1, 0.05, 0.02])
        tol = _finish_tol(_tol_fixed(h, s), prob, h)
        return "casadi-collocation", {"stages": s, "h": h}, tol, f"casadi-collocation s={s} h={h:g}"
    if r < 0.8:
        rtol = rng.choice([1e-6, 1e-8, 1e-10])
        opts = {"rtol": rtol, "atol": rtol * 1e-2}
        return "casadi-idas", opts, _finish_tol(max(1e-6, 1000 * rtol), prob, None), f"casadi-idas rtol={rtol:g}"
    if r < 0.95 or not allow_pinn:
        return "reference", {}, _finish_tol(1e-6, prob, None), "reference (defaults)"
    h = span / 10
    cfg = PinnSpec({"stages": 3, "h": h})
    return "pinn", {"config": cfg}, _finish_tol(10 * _tol_fixed(h, 3), prob, h), f"pinn s=3 h={h:g}"


def _problem_case(category: str, prob: _Problem, method: str, options: dict, tol: float, text: str, rng) -> Case:
    args = {"t_span": prob.t_span, "method": method, "options": options}
    reference = prob.reference
    desc = f"{text} on {prob.desc}" + (" [jump in t]" if prob.jump else "")
    if prob.batch_refs is not None and rng.random() < 0.5:
        if prob.batch_y0:
            args["y0"] = prob.batch_y0
        if prob.batch_params:
            args["parameters"] = prob.batch_params
        reference = prob.batch_refs
        desc = f"{text}, batch of {len(prob.batch_refs)}, on {prob.desc}"
    if "t_eval" in options:
        args["expect_times"] = options["t_eval"]
    case = Case(category, desc, prob.expect, prob.steps, "solve", args, reference, tol)
    case.skip_times = prob.jump_times
    return case


def _switch_times(sol) -> list:
    """The times at which the solution switched (breakpoints, located events): its values there are
    those after the switch, the reference's the model's at that instant, which may be either side's."""
    times = []
    for record in (getattr(sol, "breakpoints", {}) or {}, *(getattr(sol, "events", {}) or {}).values()):
        if "t" in record:
            times += [float(v) for v in np.asarray(record["t"], dtype=float).ravel() if np.isfinite(v)]
    return times


# ================================================================================================
# Generators: problems with independent solutions
# ================================================================================================
def gen_ode_problem(rng: random.Random, depth: int = 4, with_algebraic: bool = True) -> _Problem:
    """Random ODE (plus optionally explicit algebraic variables) with deep expressions."""
    for _ in range(40):
        n = rng.randint(1, 3)
        m = rng.randint(0, 1) if with_algebraic else 0
        k = rng.randint(0, 2)
        states, algs, params, tricky = _names(rng, n, m, k)
        pvals = {p: round(rng.uniform(0.5, 2.0), 2) for p in params}
        t_span = _span(rng)
        zrules, constraints = [], []
        gen = ExprGen(rng, [*states, *params], t_span)
        for z in algs:
            phi = gen.expr(rng.randint(1, depth))
            zrules.append(("explicit", z, phi))
            constraints.append((f"{z} = {show(phi)}" if rng.random() < 0.5 else f"{z} - {show(phi)}", None))
        gen.names = [*states, *algs, *params]
        rhs = []
        for s in states:
            decay = round(rng.uniform(0.3, 2.0), 2)
            rhs.append(add(mul(num(-decay), var(s)), mul(gen.coefficient(0.2, 1.0), gen.expr(depth))))
        y0 = tuple(round(rng.uniform(-1.5, 1.5), 3) for _ in states)
        ref = TreeODE(tuple(states), tuple(rhs), tuple(algs), tuple(zrules), pvals, y0, t_span)
        if ref.tame():
            break
    else:
        raise NoTameProblem("random ODE")
    steps = _model_steps(
        "expr",
        states,
        algs,
        pvals,
        [(s, show(e)) for s, e in zip(states, rhs, strict=True)],
        constraints,
        dict(zip(states, y0, strict=True)),
        t_span[0],
    )
    desc = f"random ODE ({n} states, {m} explicit algebraic{', tricky names' if tricky else ''}): " + "; ".join(
        f"{s}' = {show(e)}" for s, e in zip(states, rhs, strict=True)
    )
    return _Problem(
        desc, steps, ref, t_span, gen.kink, gen.jump, _expect(tricky, gen.jump), jump_times=tuple(gen.jump_times)
    )


def gen_index1(rng: random.Random, depth: int = 2) -> _Problem:
    """Index 1: ``0 = z - phi``, ``z**3 + z - phi``, ``exp(z) - (2 + tanh(phi))``,
    ``z + 0.5 sin z - phi`` or a 2x2 linear system; the ODEs use z."""
    for _ in range(40):
        n, m, k = rng.randint(1, 3), rng.randint(1, 2), rng.randint(0, 1)
        states, algs, params, tricky = _names(rng, n, m, k)
        pvals = {p: round(rng.uniform(0.5, 2.0), 2) for p in params}
        t_span = _span(rng)
        gen = ExprGen(rng, [*states, *params], t_span)
        zrules, constraints, kinds = [], [], []
        if m == 2 and rng.random() < 0.35:
            for _ in range(100):
                A = [[round(rng.uniform(-2, 2), 1) for _ in range(2)] for _ in range(2)]
                if abs(np.linalg.det(A)) > 0.5 and np.linalg.cond(A) < 20:
                    break
            else:
                A = [[1.0, 0.5], [-0.5, 1.0]]
            phis = [gen.expr(depth) for _ in range(2)]
            zrules.append(("linear", tuple(algs), A, tuple(phis)))
            for i in range(2):
                text = f"{A[i][0]}*{algs[0]} + {A[i][1]}*{algs[1]} - {show(phis[i])}"
                constraints.append((text, f"lin{i + 1}"))
            kinds.append("linear 2x2")
        else:
            for z in algs:
                phi = gen.expr(depth)
                kind = rng.choice(["explicit", "cubic", "log", "monotone"])
                kinds.append(kind)
                if kind == "explicit":
                    zrules.append(("explicit", z, phi))
                    constraints.append((f"{z} = {show(phi)}", None))
                elif kind == "cubic":
                    zrules.append(("cubic", z, phi))
                    constraints.append((f"{z}**3 + {z} - {show(phi)}", None))
                elif kind == "log":
                    zrules.append(("log", z, add(num(2), fn("tanh", phi))))
                    constraints.append((f"exp({z}) - (2 + tanh({show(phi)}))", None))
                else:
                    zrules.append(("monotone", z, phi, 0.5))
                    constraints.append((f"{z} + 0.5*sin({z}) - {show(phi)}", None))
        gen.names = [*states, *algs, *params]
        rhs = []
        for s in states:
            decay = round(rng.uniform(0.3, 2.0), 2)
            coupling = mul(gen.coefficient(0.2, 1.0), var(rng.choice(algs)))
            rhs.append(add(mul(num(-decay), var(s)), coupling, mul(gen.coefficient(0.1, 0.8), gen.expr(depth))))
        y0 = tuple(round(rng.uniform(-1.5, 1.5), 3) for _ in states)
        ref = TreeODE(tuple(states), tuple(rhs), tuple(algs), tuple(zrules), pvals, y0, t_span)
        if ref.tame():
            break
    else:
        raise NoTameProblem("index-1 DAE")
    initial = dict(zip(states, y0, strict=True))
    if rng.random() < 0.2:  # also state the (exactly consistent) algebraic values
        z0 = ref(np.array([t_span[0]]))
        initial.update({z: float(z0[z][0]) for z in algs})
    odes = [(s, show(e)) for s, e in zip(states, rhs, strict=True)]
    steps = _model_steps("index1", states, algs, pvals, odes, constraints, initial, t_span[0])
    prob = _Problem(
        f"index-1 DAE ({n} states; {', '.join(kinds)}{'; tricky names' if tricky else ''}): "
        + "; ".join(c for c, _ in constraints),
        steps,
        ref,
        t_span,
        gen.kink,
        gen.jump,
        _expect(tricky, gen.jump),
        jump_times=tuple(gen.jump_times),
    )
    # a batch: other initial states (and parameter values), each with its own independent solution
    B = rng.randint(2, 3)
    ys = [tuple(round(rng.uniform(-1.5, 1.5), 3) for _ in states) for _ in range(B)]
    ps = [{p: round(rng.uniform(0.5, 2.0), 2) for p in params} for _ in range(B)]
    refs = [dataclasses.replace(ref, y0=y, params=p, _solution=None) for y, p in zip(ys, ps, strict=True)]
    if all(r.tame() for r in refs):
        prob.batch_refs = refs
        prob.batch_y0 = {s: np.array([y[i] for y in ys]) for i, s in enumerate(states)}
        prob.batch_params = {p: np.array([q[p] for q in ps]) for p in params} or None
    return prob


def _psi(rng: random.Random):
    """A smooth ``psi(t)`` and its derivative, as trees."""
    a0, a1 = round(rng.uniform(-1, 1), 2), round(rng.uniform(-1, 1), 2)
    a2, w, ph = round(rng.uniform(-1, 1), 2), round(rng.uniform(0.5, 3), 2), round(rng.uniform(0, 3), 2)
    a3, b = round(rng.uniform(-1, 1), 2), round(rng.uniform(0.2, 2), 2)
    arg = add(mul(num(w), TIME), num(ph))
    psi = add(num(a0), mul(num(a1), TIME), mul(num(a2), fn("sin", arg)), mul(num(a3), fn("exp", mul(num(-b), TIME))))
    dpsi = add(num(a1), mul(num(a2 * w), fn("cos", arg)), mul(num(-a3 * b), fn("exp", mul(num(-b), TIME))))
    return psi, dpsi


def gen_index2(rng: random.Random, depth: int = 2) -> _Problem:
    """Index 2: ``y' = f(t, y) + B z`` with ``0 = C y - psi(t)`` (C B nonsingular), or one nonlinear
    constraint ``0 = u + 0.3 sin(u) - psi(t)``, ``u = c.y``; z from the hidden constraint."""
    for _ in range(60):
        n, m, k = rng.randint(2, 4), 1, rng.randint(0, 1)
        if n >= 3 and rng.random() < 0.4:
            m = 2
        states, algs, params, tricky = _names(rng, n, m, k)
        pvals = {p: round(rng.uniform(0.5, 2.0), 2) for p in params}
        t_span = _span(rng)
        gen = ExprGen(rng, [*states, *params], t_span)
        B = np.round(np.array([[rng.uniform(-1.5, 1.5) for _ in range(m)] for _ in range(n)]), 1)
        C = np.round(np.array([[rng.uniform(-1.5, 1.5) for _ in range(n)] for _ in range(m)]), 1)
        M = C @ B
        if abs(np.linalg.det(M)) < 0.3 or np.linalg.cond(M) > 30 or not np.all(np.any(C != 0, axis=1)):
            continue
        fs = []
        for s in states:
            decay = round(rng.uniform(0.3, 2.0), 2)
            fs.append(add(mul(num(-decay), var(s)), mul(gen.coefficient(0.2, 1.0), gen.expr(depth))))
        rhs = [add(f, *(mul(num(B[i, j]), var(algs[j])) for j in range(m) if B[i, j] != 0)) for i, f in enumerate(fs)]
        nonlinear = m == 1 and rng.random() < 0.35
        psis = [_psi(rng) for _ in range(m)]
        y0 = np.array([round(rng.uniform(-1.5, 1.5), 3) for _ in states])
        t0 = t_span[0]
        if nonlinear:
            c, kk = C[0], 0.3
            target = float(evaluate(psis[0][0], {"t": t0}))
            u = target
            for _ in range(60):
                u -= (u + kk * math.sin(u) - target) / (1 + kk * math.cos(u))
            y0 = y0 + c * (u - c @ y0) / (c @ c)
            zrules = (("index2_nl", algs[0], tuple(c), float(c @ B[:, 0]), tuple(fs), psis[0][1], kk),)
            u_text = " + ".join(f"{c[i]}*{s}" for i, s in enumerate(states) if c[i] != 0)
            constraints = [(f"({u_text}) + 0.3*sin({u_text}) - {show(psis[0][0])}", "level")]
        else:
            psi0 = np.array([float(evaluate(p[0], {"t": t0})) for p in psis])
            y0 = y0 + C.T @ np.linalg.solve(C @ C.T, psi0 - C @ y0)
            zrules = (("index2", tuple(algs), M.tolist(), C.tolist(), tuple(fs), tuple(p[1] for p in psis)),)
            constraints = [
                (
                    " + ".join(f"{C[j, i]}*{s}" for i, s in enumerate(states) if C[j, i] != 0)
                    + f" - {show(psis[j][0])}",
                    f"level{j + 1}",
                )
                for j in range(m)
            ]
        ref = TreeODE(tuple(states), tuple(rhs), tuple(algs), zrules, pvals, tuple(float(v) for v in y0), t_span)
        if ref.tame():
            break
    else:
        raise NoTameProblem("index-2 DAE")
    odes = [(s, show(e)) for s, e in zip(states, rhs, strict=True)]
    initial = {s: float(v) for s, v in zip(states, ref.y0, strict=True)}
    steps = _model_steps("index2", states, algs, pvals, odes, constraints, initial, t_span[0])
    return _Problem(
        f"index-2 DAE ({n} states, {m} algebraic{', nonlinear level' if nonlinear else ''}"
        f"{', tricky names' if tricky else ''}): " + "; ".join(c for c, _ in constraints),
        steps,
        ref,
        t_span,
        gen.kink,
        gen.jump,
        _expect(tricky, gen.jump),
        jump_times=tuple(gen.jump_times),
    )


def gen_pendulum(rng: random.Random, index: int | None = None) -> _Problem:
    """The pendulum, velocity-level (index 2) or position-level (index 3), random angle, speed,
    gravity and radius; the reference integrates the angle."""
    index = index or rng.choice([2, 3])
    phi0, w0 = round(rng.uniform(-3, 3), 3), round(rng.uniform(-2, 2), 3)
    lam, L = round(rng.uniform(0.5, 3), 2), rng.choice([1.0, 1.0, 0.5, 2.0])
    t_span = (0.0, rng.choice([1.0, 2.0]))
    tricky = rng.random() < 0.2
    names = tuple(rng.sample(TRICKY_NAMES, 6)) if tricky else ("y1", "y2", "y3", "y4", "y5", "lam")
    y1, y2, y3, y4, y5, g = names
    odes = [(y1, y3), (y2, y4), (y3, f"-{y1}*{y5}"), (y4, f"-{y2}*{y5} - {g}")]
    constraint = f"{y1}*{y3} + {y2}*{y4}" if index == 2 else f"{y1}**2 + {y2}**2 - {L}**2"
    init = {
        y1: L * math.cos(phi0),
        y2: L * math.sin(phi0),
        y3: -L * w0 * math.sin(phi0),
        y4: L * w0 * math.cos(phi0),
    }
    steps = _model_steps("pendulum", [y1, y2, y3, y4], [y5], {g: lam}, odes, [(constraint, "rod")], init)
    ref = Pendulum(phi0, w0, lam, L, t_span, names[:5])
    prob = _Problem(
        f"pendulum index {index} (phi0={phi0}, omega0={w0}, lam={lam}, L={L}{', tricky names' if tricky else ''})",
        steps,
        ref,
        t_span,
        expect="either" if tricky else "valid",
    )
    B = rng.randint(2, 3)
    phis = [round(rng.uniform(-3, 3), 3) for _ in range(B)]
    ws = [round(rng.uniform(-2, 2), 3) for _ in range(B)]
    prob.batch_refs = [Pendulum(p, w, lam, L, t_span, names[:5]) for p, w in zip(phis, ws, strict=True)]
    prob.batch_y0 = {
        y1: np.array([L * math.cos(p) for p in phis]),
        y2: np.array([L * math.sin(p) for p in phis]),
        y3: np.array([-L * w * math.sin(p) for p, w in zip(phis, ws, strict=True)]),
        y4: np.array([L * w * math.cos(p) for p, w in zip(phis, ws, strict=True)]),
    }
    return prob


def small_model(k: float = 2.0, x0: float = 1.0, y0: float = 1.0, name: str = "small"):
    """``x' = -k x + w, y' = -y, 0 = w - 0.5 y``: ``(steps, Exact reference)``."""
    steps = _model_steps(
        name, ["x", "y"], ["w"], {"k": k}, [("x", "-k*x + w"), ("y", "-y")], [("w - 0.5*y", "half")], {"x": x0, "y": y0}
    )
    return steps, small_exact(k, x0, y0)


def small_exact(k: float = 2.0, x0: float = 1.0, y0: float = 1.0) -> Exact:
    c = 0.5 * y0 / (k - 1)
    et, ekt = fn("exp", neg(TIME)), fn("exp", mul(num(-k), TIME))
    return Exact({"x": add(mul(num(x0 - c), ekt), mul(num(c), et)), "y": mul(num(y0), et), "w": mul(num(0.5 * y0), et)})


# ================================================================================================
# Generators: random cases by category
# ================================================================================================
def gen_expr_valid(rng: random.Random) -> Case:
    prob = gen_ode_problem(rng, depth=rng.randint(2, 5))
    method, options, tol, text = _valid_method(rng, prob, allow_pinn=False)
    return _problem_case("expr-valid", prob, method, options, tol, text, rng)


def gen_dae(rng: random.Random, category: str) -> Case:
    if category == "dae-index1":
        prob = gen_index1(rng)
    elif category == "dae-index2":
        prob = gen_index2(rng)
    else:
        prob = gen_pendulum(rng)
    method, options, tol, text = _valid_method(rng, prob)
    return _problem_case(category, prob, method, options, tol, text, rng)


# ---- options -----------------------------------------------------------------------------------
NAN, INF = float("nan"), float("inf")
# value pools: (value, verdict) with verdict "v" valid, "i" invalid (must be refused), "e" either
_INVALID_NUMBERS = [
    (0, "i"),
    (-1e-6, "i"),
    (NAN, "i"),
    (INF, "i"),
    (-INF, "i"),
    ("1e-6", "i"),
    (True, "i"),
    ([1e-6], "i"),
    (None, "i"),
]


def _pool(rng: random.Random, valid, invalid, either=()):
    r = rng.random()
    if valid and (r < 0.65 or not (invalid or either)):
        return rng.choice(list(valid)), "v"
    if invalid and (r < 0.9 or not either):
        return rng.choice(list(invalid))
    return rng.choice(list(either)), "e"


def _t_eval(rng: random.Random, t_span):
    t0, t1 = t_span
    r = rng.random()
    if r < 0.7:
        n = rng.randint(2, 25)
        pts = sorted({round(rng.uniform(t0, t1), 6) for _ in range(n)})
        if rng.random() < 0.5:
            pts = sorted({t0, *pts, t1})
        return pts, "v"
    bad = [
        (sorted([t0, t1, (t0 + t1) / 2])[::-1], "i"),
        ([t0, t1 + 1.0], "i"),
        ([t0 - 1.0, t1], "i"),
        ([t0, NAN, t1], "i"),
        (["a", "b"], "i"),
        ([], "i"),
        ([t0, t0, t1], "i"),
        ("0.5", "i"),
        (t1, "e"),
        (np.array([[t0, t1]]), "e"),
        (np.linspace(t0, t1, 7), "v"),
    ]
    return rng.choice(bad)


def _option_space(method: str, rng: random.Random, t_span):
    """Per option name: a function drawing ``(value, verdict)``."""
    span = t_span[1] - t_span[0]
    h_valid = [span * f for f in (0.1, 0.05, 0.025, 0.02)] + [span / 3]
    h_invalid = [
        (0, "i"),
        (-0.1, "i"),
        (NAN, "i"),
        (INF, "i"),
        ("0.1", "i"),
        (2 * span, "i"),
        (True, "i"),
        (1e-11 * span, "i"),
        ([0.1], "i"),
    ]

    def stages():
        invalid = [(0, "i"), (-1, "i"), (8, "i"), (2.5, "i"), ("3", "i"), (True, "i"), (None, "i"), (100, "i")]
        return _pool(rng, [1, 2, 3, 4, 5, 6, 7], invalid, [np.int64(3)])

    rtol_inv = [
        (0, "i"),
        (-1e-6, "i"),
        (10, "i"),
        (1.0, "i"),
        (NAN, "i"),
        (INF, "i"),
        ("1e-6", "i"),
        (True, "i"),
        (1e-20, "i"),
        (None, "e"),
    ]
    atol_inv = [(0, "i"), (-1.0, "i"), (NAN, "i"), (INF, "i"), ("x", "i"), (True, "i")]

    def t_eval():
        return _t_eval(rng, t_span)

    if method == "radau":
        return {
            "stages": stages,
            "h": lambda: _pool(rng, h_valid, h_invalid, [span * (1 + 1e-13)]),
            "rtol": lambda: _pool(rng, [1e-3, 1e-5, 1e-6, 1e-8, 1e-10], rtol_inv, [1e-13, 0.05]),
            "atol": lambda: _pool(rng, [1e-6, 1e-8, 1e-10, 1e-12], atol_inv, [1.0, 1e-300]),
            "h0": lambda: _pool(rng, [1e-3, 1e-4], [(0, "i"), (-1e-3, "i"), (NAN, "i"), ("1e-3", "i")], [10 * span]),
            "t_eval": t_eval,
            # an expert knob: a tighter or looser Newton may fail (an error) but must not mislead
            "newton_tol": lambda: _pool(
                rng, [], [(0, "i"), (-1.0, "i"), (1e-20, "i"), (NAN, "i")], [1e-10, 1e-12, 1e-2]
            ),
            "max_newton_iterations": lambda: _pool(
                rng, [10, 20], [(0, "i"), (-1, "i"), (2.5, "i"), ("7", "i")], [1, 2]
            ),
            "max_steps": lambda: _pool(rng, [100_000], [(0, "i"), (-5, "i"), (1.5, "i"), ("10", "i")], [1, 3]),
            "reuse_jacobian": lambda: _pool(rng, [True, False], [("yes", "i"), (None, "i"), (2, "i")], [1, 0]),
            "dtype": lambda: _pool(
                rng,
                ["float64", "float32"],
                [("float16", "i"), ("int64", "i"), ("", "i"), (64, "i"), (None, "i"), ("bfloat16", "i")],
                ["torch.float32", "double"],
            ),
            "device": lambda: _pool(
                rng,
                ["cpu"],
                [
                    ("meta", "i"),
                    ("mps", "i"),
                    (5, "i"),
                    ("cuda", "i"),
                    ("cuda:0", "i"),
                    ("", "i"),
                    ("tpu", "i"),
                    (None, "i"),
                ],
                ["cpu:0", "CPU"],
            ),
        }
    if method == "casadi-collocation":
        return {"stages": stages, "h": lambda: _pool(rng, h_valid, h_invalid, [span * (1 + 1e-13)])}
    if method == "casadi-idas":
        return {
            "rtol": lambda: _pool(rng, [1e-4, 1e-6, 1e-8, 1e-10], [*rtol_inv, (1e-16, "i")], [1e-13, 0.05]),
            "atol": lambda: _pool(rng, [1e-6, 1e-8, 1e-10, 1e-12], atol_inv, [1.0]),
            "max_num_steps": lambda: _pool(
                rng, [10_000, 100_000], [(0, "i"), (-1, "i"), (2.5, "i"), ("5", "i")], [1, 3]
            ),
            "t_eval": t_eval,
        }
    if method == "reference":
        return {
            "rtol": lambda: _pool(rng, [1e-6, 1e-8, 1e-10, 1e-12], rtol_inv, [1e-14, 0.05]),
            "atol": lambda: _pool(rng, [1e-8, 1e-10, 1e-12], atol_inv, [1.0]),
            "integrator": lambda: _pool(
                rng,
                ["DOP853", "RK45", "Radau", "BDF", "LSODA"],
                [("rk4", "i"), ("", "i"), ("euler", "i"), (5, "i"), (None, "i")],
                ["dop853", "radau"],
            ),
            "t_eval": t_eval,
        }
    if method == "pinn":
        return {
            "config": lambda: _pinn_config(rng, span),
            # workers are Ray's; ray trains segments in parallel only from segment_starts
            "workers": lambda: _pool(rng, [], [(1, "i"), (0, "i"), ("2", "i"), (True, "i"), (2, "i")]),
            "engine": lambda: _pool(rng, ["local"], [("ray", "i"), ("dask", "i"), (None, "i")]),
            "progress": lambda: _pool(rng, [False, None], [("yes", "i"), (1, "i")]),
            "save": lambda: _pool(rng, ["net.pt"], [], ["missing/dir/net.pt"]),
        }
    raise ValueError(method)


def _pinn_config(rng: random.Random, span: float):
    kw, verdict = {"h": span / 10, "width": rng.choice([8, 16]), "depth": rng.choice([1, 2])}, "v"
    r = rng.random()
    if r < 0.6:
        kw["stages"] = rng.choice([2, 3])
        kw["activation"] = rng.choice(["tanh", "sigmoid", "sin", "gelu", "softplus"])
    else:
        key, value, verdict = rng.choice(
            [
                ("bogus", 1, "i"),
                ("h", 0, "i"),
                ("h", -0.1, "i"),
                ("width", 0, "i"),
                ("depth", -1, "i"),
                ("activation", "relu", "i"),
                ("optimizer", "sgd", "i"),
                ("dtype", "float16", "i"),
                ("device", "meta", "i"),
                ("device", "mps", "i"),
                ("device", 5, "i"),
                ("tol", -1.0, "i"),
                ("iterations", 0, "i"),
                ("samples", 2, "i"),
                ("learning_rate", 0.1, "i"),
                ("stages", 9, "i"),
                ("weight_f", NAN, "i"),
                ("eta", INF, "i"),
                ("architecture", "dense", "i"),
                ("increment", "yes", "i"),
                ("seed", 1.5, "i"),
                ("h", 2 * span, "i"),
                ("optimizer", "adam", "e"),
                ("tol", None, "e"),
                ("iterations", 3, "e"),
                ("architecture", "shared", "v"),
                ("increment", False, "v"),
                ("dtype", "float32", "e"),
            ]
        )
        kw[key] = value
        if key == "optimizer" and value == "adam":
            kw["iterations"] = 300
    if verdict == "v" and rng.random() < 0.1:
        return {"h": span / 10}, "i"  # a dict is not a PINNConfig
    return PinnSpec(kw), verdict


def gen_options(rng: random.Random) -> Case:
    """A known-solution problem and one method with 1-3 random options (valid, invalid or edge)."""
    method = rng.choices(["radau", "casadi-collocation", "casadi-idas", "reference", "pinn"], [5, 2, 3, 3, 1])[0]
    kind = rng.choice(["index1", "index2", "index1", "pendulum"])
    if kind == "index1":
        prob = gen_index1(rng, depth=1)
    elif kind == "index2":
        prob = gen_index2(rng, depth=1)
    else:
        prob = gen_pendulum(rng, 2)
    space = _option_space(method, rng, prob.t_span)
    keys = rng.sample(sorted(space), min(len(space), rng.randint(1, 3)))
    options, verdicts = {}, []
    for key in keys:
        value, verdict = space[key]()
        options[key] = value
        verdicts.append(verdict)
    if rng.random() < 0.08:
        bogus = rng.choice(
            ["stage", "tol", "steps", "verbose", "integrator", "max_num_steps", "config", "hmax", "rtol_"]
        )
        if bogus not in space:
            options[bogus] = 1
            verdicts.append("i")
    verdict = "i" if "i" in verdicts else ("e" if "e" in verdicts else "v")
    # rules between options, as documented
    if method == "radau" and verdict == "v":
        adaptive_keys = {"rtol", "atol", "h0"} & set(options)
        if "h" in options and adaptive_keys:
            verdict = "i"
        elif "h" not in options and options.get("dtype") == "float32":
            rtol = options.get("rtol", 1e-6)
            verdict = "i" if rtol < 1e-5 else "v"
    if method == "pinn":
        cfg = options.get("config")
        if verdict == "v" and ("workers" in options or options.get("engine", "local") != "local"):
            verdict = "i"
        if verdict == "v" and "save" in options and options["save"] != "net.pt":
            verdict = "e"
        if isinstance(cfg, PinnSpec) and cfg.kwargs.get("optimizer") == "adam":
            verdict = "e" if verdict == "v" else verdict
    newton_tol = options.get("newton_tol")
    if options.get("dtype") == "float32" and isinstance(newton_tol, float) and 0 < newton_tol < 1.2e-6:
        verdict = "i"  # documented: below 10 eps of float32
    tol = _options_tol(method, options, prob)
    expect = {"v": prob.expect, "i": "invalid", "e": "either"}[verdict]
    args = {"t_span": prob.t_span, "method": method, "options": options}
    t_eval = options.get("t_eval")
    if t_eval is not None and verdict != "i" and not isinstance(t_eval, str):
        arr = np.asarray(t_eval, dtype=float).reshape(-1)
        args["expect_times"] = arr.tolist()
    text = ", ".join(f"{k}={_short_repr(v, 60)}" for k, v in options.items())
    case = Case(
        "options", f"{method}({text}) on {prob.desc}"[:400], expect, prob.steps, "solve", args, prob.reference, tol
    )
    case.skip_times = prob.jump_times
    return case


def _options_tol(method, options, prob):
    span = prob.t_span[1] - prob.t_span[0]

    def num_or(key, default):
        v = options.get(key, default)
        return (
            v
            if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and v == v
            else default
        )

    float32 = options.get("dtype") in ("float32", "torch.float32")
    if method in ("radau", "casadi-collocation"):
        s = int(num_or("stages", 3)) if 1 <= num_or("stages", 3) <= 7 else 3
        h = options.get("h") if method == "radau" else options.get("h", span / 100)
        if isinstance(h, (int, float)) and not isinstance(h, bool) and 0 < h < INF:
            tol = _tol_fixed(min(h, span), s)
            if method == "radau" and options.get("newton_tol", 0) == 1e-2:
                tol = max(tol, 1e-2)
            return _finish_tol(tol, prob, min(h, span), float32)
        r, a = num_or("rtol", 1e-6), num_or("atol", 1e-8)
        return _finish_tol(max(1e-6, 1000 * max(min(r, 1e-2), min(a, 1e-2))), prob, None, float32)
    if method in ("casadi-idas", "reference"):
        d = 1e-8 if method == "casadi-idas" else 1e-12
        r, a = num_or("rtol", d), num_or("atol", d * 1e-2)
        return _finish_tol(max(1e-6, 1000 * max(r, a)), prob, None)
    cfg = options.get("config")
    h, s = span / 10, 3
    if isinstance(cfg, PinnSpec):
        h = cfg.kwargs.get("h", 0.05) if isinstance(cfg.kwargs.get("h", 0.05), float) else h
        s = cfg.kwargs.get("stages", 3) if isinstance(cfg.kwargs.get("stages", 3), int) else 3
    return _finish_tol(10 * _tol_fixed(max(h, 1e-3), s), prob, h, float32)


# ---- expression edges ---------------------------------------------------------------------------
def gen_expr_edge(rng: random.Random) -> Case:
    """Long sums, deep nesting, extreme numbers, on ``x' = ...`` from x = 1 over (0, 1)."""
    kind = rng.choice(["sum", "sum", "nest", "parens", "neg", "number"])
    if kind == "sum":
        count = rng.choice([50, 200, 500, 1000, 2000, 3000, 5000])
        terms = []
        for _ in range(count):
            c = round(rng.uniform(-1, 1), 2)
            terms.append(rng.choice([mul(num(c), var("x")), mul(num(c), fn("sin", TIME)), mul(num(c), var("x"), TIME)]))
        tree = add(neg(var("x")), div(add(*terms), num(count, str(count))))
        desc = f"sum of {count} terms"
    elif kind == "nest":
        depth = rng.choice([10, 30, 60, 100, 200, 400])
        name = rng.choice(["sin", "tanh", "atan", "cos"])
        inner = var("x")
        for _ in range(depth):
            inner = fn(name, inner)
        tree = sub(inner, var("x"))
        desc = f"{name} nested {depth} deep"
    elif kind == "parens":
        depth = rng.choice([10, 50, 100, 150, 250, 1000])
        return _edge_case(f"{'(' * depth}-x{')' * depth}", "either", neg(var("x")), f"{depth} nested parentheses")
    elif kind == "neg":
        depth = rng.choice([10, 99, 100, 101, 500])
        return _edge_case(
            "-" * depth + "x", "either", neg(var("x")) if depth % 2 else var("x"), f"{depth} unary minus signs"
        )
    else:
        text, expect, tree, desc = rng.choice(EXTREME_NUMBERS)
        return _edge_case(text, expect, tree, desc)
    return _edge_case(show(tree), "either", tree, desc)


EXTREME_NUMBERS = [
    ("-x + 1e-400*x", "either", neg(var("x")), "1e-400 underflows"),
    ("1e400*x", "invalid", None, "1e400 is not a float64"),
    ("-x + 1e400", "invalid", None, "1e400 constant"),
    ("-1e400*x", "invalid", None, "-1e400"),
    ("-x*1e308*1e-308", "either", neg(var("x")), "1e308*1e-308"),
    ("-x*1e-300", "valid", mul(num(-1e-300), var("x")), "1e-300"),
    ("-123456789012345678901234567890*x/123456789012345678901234567890", "either", neg(var("x")), "30-digit integers"),
    ("-0.1e1*x", "valid", neg(var("x")), "0.1e1"),
    ("-1_0*x/10", "either", neg(var("x")), "1_0 literal"),
    ("-0x10*x/16", "either", neg(var("x")), "hex literal"),
    ("-x + 1j", "invalid", None, "complex literal"),
    ("-x + sqrt(-1)", "invalid", None, "sqrt(-1) is imaginary"),
    ("-x + log(-1)", "invalid", None, "log(-1) is complex"),
    ("-x + log(0)", "invalid", None, "log(0) = -oo"),
    ("-x + 1/0", "invalid", None, "1/0"),
    ("-x + x/0", "invalid", None, "x/0"),
    ("-x + 0**-1", "invalid", None, "0**-1"),
    ("-x + acos(2)", "invalid", None, "acos(2) is complex"),
    ("-x + exp(800)", "either", None, "exp(800) overflows float64"),
    ("-x + 1e308*x*x", "either", None, "1e308 x^2 overflows"),
    ("-x**1.0000000001", "either", None, "x**1.0000000001"),
    ("-x + Rational(1, 3) - 1/3", "either", neg(var("x")), "Rational(1, 3) - 1/3"),
    ("-x + Integer(2) - 2", "either", neg(var("x")), "Integer(2) - 2"),
    ("x - x - x", "valid", neg(var("x")), "x - x - x"),
    ("-x*x/x", "valid", neg(var("x")), "x*x/x"),
    ("-x + 0*log(-1)", "either", neg(var("x")), "0*log(-1)"),
    ("-x + 2.5e-3 - 0.0025", "valid", neg(var("x")), "2.5e-3 - 0.0025"),
    ("-x + 1e-320", "either", neg(var("x")), "subnormal 1e-320"),
    ("-x*pi/pi", "valid", neg(var("x")), "pi/pi"),
    ("-x + 9007199254740993 - 9007199254740993", "either", neg(var("x")), "2**53 + 1"),
]


def _edge_case(text: str, expect: str, tree, desc: str) -> Case:
    steps = (("Model", ("edge",), {}), ("states", ("x",), {}), ("ode", ("x", text), {}), ("initial", (), {"x": 1.0}))
    ref = TreeODE(("x",), (tree,), (), (), {}, (1.0,), (0.0, 1.0)) if tree is not None else None
    args = {"t_span": (0.0, 1.0), "method": "radau", "options": {"stages": 3, "h": 0.05}}
    return Case("expr-edge", f"x' = {_short_repr(text, 80)} ({desc})", expect, steps, "solve", args, ref, 1e-6)


# ---- hostile strings ----------------------------------------------------------------------------
_OPEN = '["__builtins__"]["open"]("@CANARY@", "w")'
HOSTILE_PAYLOADS = [
    # the issue's own string, made to touch the canary
    (
        '[c for c in ().__class__.__base__.__subclasses__() if c.__name__ == "_wrap_close"][0].__init__.__globals__'
        '["system"]("touch @CANARY@")',
        "issue: subclasses -> _wrap_close -> os.system",
    ),
    (
        '{c.__name__: c for c in ().__class__.__base__.__subclasses__()}["_wrap_close"].__init__.__globals__'
        '["system"]("touch @CANARY@")',
        "dict comprehension -> os.system",
    ),
    ("x.__class__.__new__.__globals__" + _OPEN, "symbol -> class -> __new__ globals -> open"),
    ("pi.__class__.__new__.__globals__" + _OPEN + " and x", "pi -> globals -> open, 'and x'"),
    ("Symbol.__new__.__globals__" + _OPEN, "Symbol.__new__ globals -> open"),
    ("sin.eval.__func__.__globals__" + _OPEN, "sin.eval globals -> open"),
    ("t.__class__.__new__.__globals__" + _OPEN + ".close() or x", "t -> globals -> open, 'or x'"),
    (
        'x.__class__.__new__.__globals__["__builtins__"]["__import__"]("os").system("touch @CANARY@")',
        "__import__ via globals",
    ),
    ('x.__class__.__new__.__globals__["__builtins__"]["exec"]("open(\\"@CANARY@\\", \\"w\\")")', "exec via globals"),
    (
        'x + x.__class__.__new__.__globals__["__builtins__"]["eval"]("len(open(\\"@CANARY@\\", \\"w\\").name)")',
        "eval via globals inside a sum",
    ),
    ("Integer.__new__.__globals__" + _OPEN + " and x", "Integer.__new__ globals -> open"),
    ("(lambda: x.__class__.__new__.__globals__" + _OPEN + ")()", "lambda calling open"),
    ('f"{x.__class__.__new__.__globals__}"', "f-string with attribute access"),
    ("Max(x, pi.__class__.__new__.__globals__" + _OPEN + " and 1)", "payload inside Max"),
    ("sin(pi.__class__.__new__.__globals__" + _OPEN + " and x)", "payload inside sin"),
    ('__import__("os").system("touch @CANARY@")', "__import__"),
    ('open("@CANARY@", "w")', "open"),
    ('exec("open(\\"@CANARY@\\", \\"w\\")")', "exec"),
    ('eval("open(\\"@CANARY@\\", \\"w\\")")', "eval"),
    ('compile("1", "f", "eval")', "compile"),
    ('getattr(x, "__class__")', "getattr"),
    ("[x][0]", "subscript"),
    ("x[0]", "subscript on a symbol"),
    ("(lambda: x)()", "lambda"),
    ("lambda: x", "bare lambda"),
    ("[x for _ in (1, 2)][0]", "list comprehension"),
    ("(a := x) + a", "walrus"),
    ("x if t > 0 else 1", "conditional expression"),
    ("x and 1", "and"),
    ("x or 1", "or"),
    ("not x", "not"),
    ("[x]", "list"),
    ("(x, 1)", "tuple"),
    ("{x}", "set"),
    ('{"a": x}', "dict"),
    ("x.diff(t)", "method call diff"),
    ("x.subs(x, 1)", "method call subs"),
    ("x.name", "attribute"),
    ('"x"', "string literal"),
    ('b"x"', "bytes literal"),
    ('f"{x}"', "f-string"),
    ("__class__", "dunder name"),
    ("x.__dict__", "dunder attribute"),
    ("__builtins__", "__builtins__"),
    ("globals()", "globals()"),
    ("locals()", "locals()"),
    ("vars()", "vars()"),
    ("breakpoint()", "breakpoint()"),
    ("exit()", "exit()"),
    ("x; 1", "semicolon"),
    ("x\n+1", "newline"),
    ("x\r\n+1", "CRLF"),
    ("import os", "import statement"),
    ("yield x", "yield"),
    ("await x", "await"),
    ("print(x)", "print"),
    ("del x", "del"),
    ("x += 1", "augmented assignment"),
    ("assert x", "assert"),
    ("...", "Ellipsis"),
    ("*x", "star"),
    ("**x", "double star"),
    ("x @ x", "matmul"),
    ("x is x", "is"),
    ("x in (1,)", "in"),
]

# Strings that are not valid expressions of a DAE but are not Python constructs either: any
# daemodel error, at any step, is a right answer.
INVALID_EXPRESSIONS = [
    ("x()", "call a symbol"),
    ("t(1)", "call t"),
    ("pi()", "call pi"),
    ("sin()", "sin without argument"),
    ("sin(x, x)", "sin with two arguments"),
    ("sin", "bare function name"),
    ("sin(x)(1)", "call a call"),
    ("x == 1", "==: equality"),
    ("x > 0", "relational"),
    ("True", "True"),
    ("None", "None"),
    ("Max(x > 0, 1)", "issue: Max of a relational"),
    ("Piecewise((x, x > 0))", "Piecewise without a default"),
    ("Piecewise(x)", "Piecewise(x)"),
    ("Derivative(x, t)", "Derivative"),
    ("diff(x, t)", "diff"),
    ('Function("f")(x)', "Function"),
    ('Symbol("q")', "Symbol of an undeclared name"),
    ("Mod(x, 2)", "unsupported function"),  # (floor is a switch now: daemodel.solving.switches)
    ("oo", "oo"),
    ("zoo", "zoo"),
    ("nan", "nan name"),
    ("I", "I"),
    ("E", "E"),
    ("", "empty string"),
    ("   ", "blanks"),
    ("()", "empty parentheses"),
    ("x +", "dangling operator"),
    ("x )", "unbalanced parenthesis"),
    ("2x", "implicit multiplication"),
    ("x'", "prime"),
    ("α", "undeclared unicode name"),
    ("x\u200b", "zero-width space"),
    ("x\u00a0+ 1", "no-break space"),
    ("x\x00", "NUL"),
    ("x²", "superscript two"),
    ("√x", "square-root sign"),
    ("x = 1", "= in an ODE"),
]

# Unicode spellings that Python's tokenizer normalises to a declared name: accepting them as that
# name or refusing them are both right; executing anything is not.
# Harmless spellings (a comment, a line continuation) are in the same class.
UNICODE_EITHER = [
    ("ｘ", "fullwidth x", ("var", "x")),
    ("𝑥", "mathematical italic x", ("var", "x")),
    ("-ｘ", "minus fullwidth x", ("neg", ("var", "x"))),
    ("x # comment", "comment", ("var", "x")),
    ("x \\\n+ 1", "line continuation", ("add", (("var", "x"), ("num", 1.0, "1")))),
    ("(x\n+ 1)", "newline inside parentheses", ("add", (("var", "x"), ("num", 1.0, "1")))),
    ("\tx  ", "tabs and blanks around", ("var", "x")),
]


def _hostile_model(where: str, payload: str):
    """Steps of ``x' = ..., y' = -y, 0 = z - x`` with ``payload`` at ``where``."""
    ode_x, constraint = "-x", ("z - x", "link")
    if where == "ode":
        ode_x = payload
    elif where == "ode-sum":
        ode_x = f"-x + ({payload})"
    elif where == "constraint":
        constraint = (payload, "link")
    elif where == "constraint-rhs":
        constraint = (f"z = {payload}", "link")
    steps = [("Model", ("hostile",), {}), ("states", ("x y",), {}), ("algebraics", ("z",), {})]
    steps += [("ode", ("x", ode_x), {}), ("ode", ("y", "-y"), {})]
    steps += [("constraint", (constraint[0],), {"name": constraint[1]}), ("initial", (), {"x": 1.0, "y": 1.0})]
    return tuple(steps)


def hostile_cases() -> list[Case]:
    """Every payload in the ODE; the code-execution ones also in a sum, a constraint and after ``z =``."""
    out = []
    args = {"t_span": (0.0, 1.0), "method": "radau", "options": {"h": 0.1}}
    for payload, desc, expect in [
        *((p, d, "hostile") for p, d in HOSTILE_PAYLOADS),
        *((p, d, "invalid") for p, d in INVALID_EXPRESSIONS),
    ]:
        places = ["ode"]
        if CANARY in payload:
            places += ["ode-sum", "constraint", "constraint-rhs"]
        for where in places:
            out.append(
                Case(
                    "expr-hostile",
                    f"{desc} [{where}]: {_short_repr(payload, 120)}",
                    expect,
                    _hostile_model(where, payload),
                    "solve",
                    args,
                )
            )
    for payload, desc, tree in UNICODE_EITHER:
        ref = TreeODE(
            ("x", "y"), (tree, neg(var("y"))), ("z",), (("explicit", "z", var("x")),), {}, (1.0, 1.0), (0.0, 1.0)
        )
        out.append(
            Case(
                "expr-hostile",
                f"{desc}: {payload!r}",
                "either",
                _hostile_model("ode", payload),
                "solve",
                args,
                ref,
                1e-5,
            )
        )
    # injection through names: a model name pasted into generated source; constraint, state and
    # parameter names; keyword names
    inject = [
        'a"""\n    open("@CANARY@", "w")\n    """',
        "a'''\n    open('@CANARY@', 'w')\n    '''",
        'a"""\nimport os; os.system("touch @CANARY@")\n"""',
        'a\\"""\n    open("@CANARY@", "w")\n    """',
        '"""; open("@CANARY@", "w"); """',
        "x\n    open('@CANARY@', 'w')\n",
        'a"""\r\n    open(\'@CANARY@\', \'w\')\r\n    """',
        "'); open('@CANARY@', 'w'); ('",
        "x\x00y",
        "{0.__class__}",
        "%s%s%s%n",
    ]
    steps_small, ref_small = small_model()
    for i, name in enumerate(inject):
        steps = (("Model", (name,), {}), *steps_small[1:])
        for method, options in (
            ("radau", {"h": 0.05}),
            ("casadi-collocation", {"h": 0.05}),
            ("pinn", {"config": PinnSpec({"h": 0.1})}),
        ):
            if method == "pinn" and i > 1:
                continue
            out.append(
                Case(
                    "expr-hostile",
                    f"model name injection #{i} ({method}): {name!r}"[:200],
                    "either",
                    steps,
                    "solve",
                    {"t_span": (0.0, 1.0), "method": method, "options": options},
                    ref_small,
                    1e-4,
                )
            )
    for bad, expect in (
        ('g"""\n open("@CANARY@", "w")\n"""', "invalid"),
        ("a b", "invalid"),
        ("1a", "invalid"),
        ("lambda", "either"),
        ("", "invalid"),
        ("c\n", "either"),
        ("ω", "invalid"),
        ("g\n    open('@CANARY@', 'w')", "invalid"),
    ):
        steps = list(steps_small)
        steps[-2] = ("constraint", ("w - 0.5*y",), {"name": bad})
        out.append(
            Case(
                "expr-hostile",
                f"constraint name {bad!r}",
                expect,
                tuple(steps),
                "solve",
                {"t_span": (0.0, 1.0), "options": {"h": 0.1}},
                ref_small if expect == "either" else None,
                1e-4,
            )
        )
    for bad in ('x"""; open("@CANARY@", "w")', "x y'", "__class__", "import", "ｘ1"):
        steps = (("Model", ("n",), {}), ("states", ([bad],), {}))
        out.append(Case("expr-hostile", f"state name {bad!r}", "invalid", steps, "build"))
        steps = (("Model", ("n",), {}), ("parameter", (bad, 1.0), {}))
        out.append(Case("expr-hostile", f"parameter name {bad!r}", "invalid", steps, "build"))
    return out


def gen_hostile(rng: random.Random) -> Case:
    """A payload wrapped in random arithmetic context."""
    payload, desc = rng.choice([p for p in HOSTILE_PAYLOADS if CANARY in p[0]])
    wrap = rng.choice(
        [
            "-x + {}",
            "sin({})",
            "({})*0",
            "Max(x, {})",
            "exp(-({}))",
            "x*({})**2",
            "Piecewise(({}, t < 0.5), (x, True))",
            "-x + 0*({})",
            "atan2({}, 1)",
            "-(x) - ({})",
        ]
    )
    text = wrap.format(payload)
    where = rng.choice(["ode", "constraint", "constraint-rhs"])
    return Case(
        "expr-hostile",
        f"{desc} wrapped as {wrap!r} [{where}]",
        "hostile",
        _hostile_model(where, text),
        "solve",
        {"t_span": (0.0, 1.0), "method": "radau", "options": {"h": 0.1}},
    )


# ---- known-bad dynamics -------------------------------------------------------------------------
_FIXED = {"radau": {"h": 0.05}, "casadi-collocation": {"h": 0.05}}
_ANY_METHOD = [
    ("radau", {"h": 0.05}),
    ("radau", {}),
    ("casadi-collocation", {"h": 0.05}),
    ("casadi-idas", {}),
    ("reference", {}),
]


def _bad(desc, steps, t_span, method, options, expect="invalid", reference=None, tol=1e-4):
    text = ", ".join(f"{k}={v}" for k, v in options.items())
    return Case(
        "known-bad",
        f"{method}({text}): {desc}",
        expect,
        steps,
        "solve",
        {"t_span": t_span, "method": method, "options": options},
        reference,
        tol,
    )


def gen_known_bad(rng: random.Random) -> Case:
    kinds = ["singular", "sqrt", "blowup", "root-vanishes", "rootless", "index2-singular", "sign", "stiff", "long"]
    kind = rng.choice(kinds)
    method, options = rng.choice(_ANY_METHOD)
    a = rng.choice([0.5, 1.0, 2.0])
    if kind == "stiff":  # Robertson: the stiff methods must solve it; an explicit one may refuse, never mislead
        t1 = rng.choice([1.0, 40.0, 1e3])
        method, options, expect = rng.choice(
            [
                ("radau", {"rtol": 1e-6, "atol": 1e-10}, "valid"),
                ("casadi-idas", {"rtol": 1e-8, "atol": 1e-12}, "valid"),
                ("reference", {"integrator": "Radau"}, "valid"),
                ("reference", {"integrator": "BDF"}, "valid"),
                ("reference", {}, "either"),
                ("reference", {"integrator": "RK45"}, "either"),
            ]
        )
        text = ", ".join(f"{k}={v}" for k, v in options.items())
        return robertson_case(
            (0.0, t1), method, options, "known-bad", f"{method}({text}): Robertson to t = {t1:g}", expect
        )
    if kind == "long":  # x' = -x over a huge span: solve it (exp(-t)) or refuse it
        t1 = rng.choice([1e6, 1e50, 1e300])
        steps = _model_steps("decay", ["x"], [], {}, [("x", "-x")], [], {"x": 1.0})
        ref = Exact({"x": fn("exp", neg(TIME))})
        return _bad(f"x' = -x over (0, {t1:g})", steps, (0.0, t1), method, options, "either", ref, 1e-3)
    if kind == "singular":
        steps = _model_steps("sing", ["x", "y"], [], {}, [("x", f"-{a}"), ("y", "1/x")], [], {"x": 1.0, "y": 0.0})
        return _bad(f"x' = -{a}, y' = 1/x from x = 1: singular at t = {1 / a:g}", steps, (0.0, 2 / a), method, options)
    if kind == "sqrt":
        steps = _model_steps("sqrt", ["x", "y"], [], {}, [("x", f"-{a}"), ("y", "sqrt(x)")], [], {"x": 1.0, "y": 0.0})
        return _bad(f"x' = -{a}, y' = sqrt(x): x < 0 after t = {1 / a:g}", steps, (0.0, 2 / a), method, options)
    if kind == "blowup":
        steps = _model_steps("blow", ["x"], [], {}, [("x", "x**2")], [], {"x": a})
        return _bad(f"x' = x**2 from x = {a}: blows up at t = {1 / a:g}", steps, (0.0, 2 / a), method, options)
    if kind == "root-vanishes":
        steps = _model_steps(
            "vanish",
            ["s", "x"],
            ["z"],
            {},
            [("s", f"-{a}"), ("x", "z")],
            [("z**2 - s", "root")],
            {"s": 1.0, "x": 0.0, "z": 1.0},
        )
        return _bad(
            f"0 = z**2 - s, s' = -{a}: the root disappears at t = {1 / a:g}", steps, (0.0, 2 / a), method, options
        )
    if kind == "rootless":
        g, z0 = rng.choice(
            [
                ("exp(z)", -50.0),
                ("z**2 + 1", 0.0),
                ("sin(z) - 2", 0.0),
                ("exp(z) + x**2", -60.0),
                ("z**2 + x**2 + 1e-3", 0.0),
                ("cosh(z)", 0.0),
            ]
        )
        steps = _model_steps("rootless", ["x"], ["z"], {}, [("x", "-x + z")], [(g, "none")], {"x": 1.0, "z": z0})
        return _bad(f"0 = {g} has no root (z0 = {z0:g})", steps, (0.0, 1.0), method, options)
    if kind == "index2-singular":
        c = rng.choice([0.5, 0.7])
        steps = _model_steps("sing2", ["q"], ["z"], {}, [("q", f"z*({c} - t)")], [("q - sin(t)", "track")], {"q": 0.0})
        return _bad(
            f"q' = z*({c} - t), 0 = q - sin(t): z = cos t/({c} - t) blows up at t = {c}",
            steps,
            (0.0, 1.0),
            method,
            options,
        )
    steps = _model_steps("sign", ["x"], [], {}, [("x", "-sign(x)")], [], {"x": 1.0})
    ref = Exact({"x": fn("Max", sub(num(1), TIME), num(0))})
    return _bad(
        "x' = -sign(x) from 1: reaches 0 at t = 1 and stays (sliding)",
        steps,
        (0.0, 2.0),
        method,
        options,
        "either",
        ref,
        0.1,
    )


# ================================================================================================
# Fixed cases: the issue's own, model edges, API edges, the CLI
# ================================================================================================
def issue_cases() -> list[Case]:
    """The concrete cases named in the issue ("Trust")."""
    out = []
    C = "issue"
    steps_s, ref_s = small_model()
    span = (0.0, 1.0)
    x_payload = HOSTILE_PAYLOADS[0][0]
    out.append(
        Case(
            C,
            "issue (1): subclasses/_wrap_close/system string in m.ode",
            "hostile",
            _hostile_model("ode", x_payload),
            "solve",
            {"t_span": span, "options": {"h": 0.1}},
        )
    )
    name = 'a"""\n    import os; os.system("touch @CANARY@")\n    """'
    out.append(
        Case(
            C,
            "issue (1): model name pasted into generated torch source",
            "either",
            (("Model", (name,), {}), *steps_s[1:]),
            "solve",
            {"t_span": span, "options": {"h": 0.05}},
            ref_s,
            1e-4,
        )
    )
    sing = _model_steps("sing", ["x", "y"], [], {}, [("x", "-1"), ("y", "1/x")], [], {"x": 1.0, "y": 0.0})
    for method in ("radau", "casadi-collocation"):
        for h in (0.1, 0.3):
            out.append(
                Case(
                    C,
                    f"issue (2): {method} h={h} over the singularity of y' = 1/x (x' = -1, x(0) = 1) on (0, 2)",
                    "invalid",
                    sing,
                    "solve",
                    {"t_span": (0.0, 2.0), "method": method, "options": {"h": h}},
                )
            )
    rootless = _model_steps("rootless", ["x"], ["z"], {}, [("x", "-x + z")], [("exp(z)", "g")], {"x": 1.0, "z": -50.0})
    out.append(Case(C, "issue (2): 0 = exp(z) (no root) accepted with z0 = -50", "invalid", rootless, "compile"))
    for method in ("radau", "casadi-idas", "reference"):
        out.append(
            Case(
                C,
                f"issue (2): {method} rtol=10 accepted",
                "invalid",
                steps_s,
                "solve",
                {"t_span": span, "method": method, "options": {"rtol": 10.0}},
            )
        )
    vanish = _model_steps(
        "vanish",
        ["s", "x"],
        ["z"],
        {},
        [("s", "-1"), ("x", "z")],
        [("z**2 - s", "root")],
        {"s": 1.0, "x": 0.0, "z": 1.0},
    )
    for method, options in (("reference", {}), ("radau", {}), ("radau", {"h": 0.05}), ("casadi-idas", {})):
        out.append(
            Case(
                C,
                f"issue (3): {method} {options} with a disappearing root 0 = z**2 - s, s' = -1 on (0, 2)",
                "invalid",
                vanish,
                "solve",
                {"t_span": (0.0, 2.0), "method": method, "options": options},
            )
        )
    rob = robertson_case((0.0, 1e3), "reference", {}, C, "issue (3): DOP853 reference on stiff Robertson to t = 1e3")
    out.append(rob)
    sign = _model_steps("sign", ["x"], [], {}, [("x", "-sign(x)")], [], {"x": 1.0})
    out.append(
        Case(
            C,
            "issue (3): adaptive radau on x' = -sign(x) from 1 over (0, 2)",
            "either",
            sign,
            "solve",
            {"t_span": (0.0, 2.0), "method": "radau", "options": {}},
            Exact({"x": fn("Max", sub(num(1), TIME), num(0))}),
            0.05,
        )
    )
    pend_steps = _model_steps(
        "pendulum",
        ["y1", "y2", "y3", "y4"],
        ["y5"],
        {"lam": 1.0},
        [("y1", "y3"), ("y2", "y4"), ("y3", "-y1*y5"), ("y4", "-y2*y5 - lam")],
        [("y1*y3 + y2*y4", "velocity")],
        {"y1": 1.0, "y2": 0.0, "y3": 0.0, "y4": 1.0},
    )
    pend_ref = Pendulum(0.0, 1.0, 1.0, 1.0, (0.0, 1.0))
    for method in ("radau", "reference"):
        out.append(
            Case(
                C,
                f"issue (3): {method} on the pendulum over t_span (0, 1e300)",
                "invalid",
                pend_steps,
                "solve",
                {"t_span": (0.0, 1e300), "method": method},
            )
        )
    decay = _model_steps("decay", ["x"], [], {}, [("x", "-x")], [], {"x": 1.0})
    out.append(
        Case(
            C,
            "issue (3): radau adaptive on x' = -x over (0, 1e300)",
            "either",
            decay,
            "solve",
            {"t_span": (0.0, 1e300), "method": "radau"},
            Exact({"x": fn("exp", neg(TIME))}),
            1e-3,
        )
    )
    t_eval = np.linspace(0.0, 1.0, 11).tolist()
    out.append(
        Case(
            C,
            "issue (4): casadi-idas on the pendulum, t_eval of 11 points, rtol=1e-10",
            "valid",
            pend_steps,
            "solve",
            {
                "t_span": (0.0, 1.0),
                "method": "casadi-idas",
                "options": {"t_eval": t_eval, "rtol": 1e-10, "atol": 1e-12},
                "expect_times": t_eval,
            },
            pend_ref,
            1e-6,
        )
    )
    rlc, rlc_ref = rlc_model()
    t_eval2 = np.linspace(0.0, 2.0, 11).tolist()
    for method, options, tol in (
        ("casadi-idas", {}, 1e-5),
        ("radau", {"h": 0.05}, 1e-6),
        ("casadi-collocation", {"h": 0.05}, 1e-6),
        ("reference", {}, 1e-7),
        ("radau", {}, 1e-3),
        ("casadi-idas", {"t_eval": t_eval2}, 1e-5),
        ("reference", {"t_eval": t_eval2}, 1e-7),
    ):
        text = ", ".join(f"{k}={'11 points' if k == 't_eval' else v}" for k, v in options.items())
        a = {"t_span": (0.0, 2.0), "method": method, "options": options}
        if "t_eval" in options:
            a["expect_times"] = options["t_eval"]
        out.append(
            Case(
                C,
                f"issue (4): {method}({text}) on an RLC circuit (3 algebraic)",
                "valid",
                rlc,
                "solve",
                a,
                rlc_ref,
                tol,
            )
        )
    track = _model_steps("track", ["q"], ["z"], {}, [("q", "z")], [("q - sin(t)", "g")], {"q": 0.0})
    track_ref = Exact({"q": fn("sin", TIME), "z": fn("cos", TIME)})
    for method, options, tol in (
        ("casadi-idas", {}, 1e-5),
        ("radau", {"h": 0.05}, 1e-5),
        ("casadi-collocation", {"h": 0.05}, 1e-5),
        ("reference", {}, 1e-7),
        ("radau", {}, 1e-3),
        ("pinn", {"config": PinnSpec({"h": 0.1})}, 1e-4),
        ("casadi-idas", {"t_eval": t_eval}, 1e-5),
        ("radau", {"h": 0.05, "t_eval": t_eval}, 1e-5),
    ):
        text = ", ".join(f"{k}={'11 points' if k == 't_eval' else v}" for k, v in options.items())
        a = {"t_span": (0.0, 1.0), "method": method, "options": options}
        if "t_eval" in options:
            a["expect_times"] = options["t_eval"]
        out.append(
            Case(C, f"issue (4): {method}({text}) on q' = z, 0 = q - sin t", "valid", track, "solve", a, track_ref, tol)
        )
    # (5) raw exceptions
    out.append(_edge_issue("Max(x > 0, 1)", "invalid", None, "issue (5): Max of a relational"))
    n = 3000
    long_sum = " + ".join(["-x/3000"] * n)
    out.append(_edge_issue(long_sum, "either", neg(var("x")), "issue (5): a 3000-term string (RecursionError)"))
    # Piecewise with an integer branch: torch's dtype promotion (the Jacobian's branch is an integer)
    x = var("x")
    pw_int = "Piecewise((1, x > 0.5), (0, True)) - x"
    ref = TreeODE(
        ("x",), (sub(("pw", ((num(1), ("cmp", ">", x, num(0.5))),), num(0)), x),), (), (), {}, (1.0,), (0.0, 1.0)
    )
    out.append(_edge_issue(pw_int, "valid", ref, "issue (5): Piecewise with integer branches, fixed h", tol=1e-6))
    out.append(
        _edge_issue(pw_int, "valid", ref, "issue (5): Piecewise with integer branches, adaptive", tol=1e-4, options={})
    )
    pw_mixed = "Piecewise((x, x > 0.5), (0, True))"
    ref = TreeODE(("x",), (("pw", ((x, ("cmp", ">", x, num(0.5))),), num(0)),), (), (), {}, (1.0,), (0.0, 1.0))
    out.append(_edge_issue(pw_mixed, "valid", ref, "issue (5): Piecewise((x, x > 0.5), (0, True)) (dtype)", tol=1e-6))
    pw_t = "Piecewise((1, t < 0.52), (-1, True))"  # a jump: fixed steps are first order across it
    out.append(
        _edge_issue(
            pw_t,
            "valid",
            Exact({"x": fn("Min", TIME, sub(num(1.04), TIME))}),
            "issue (5): Piecewise in t with integer branches",
            tol=0.1,
            exact=True,
        )
    )
    abs2 = _model_steps("abs2", ["q"], ["z"], {}, [("q", "z")], [("Abs(q) - (1 + t)", "g")], {"q": 1.0})
    for method in ("radau", "casadi-idas"):
        out.append(
            Case(
                C,
                f"issue (5): Abs in an index-2 constraint, {method}",
                "either",
                abs2,
                "solve",
                {"t_span": (0.0, 1.0), "method": method, "options": {"h": 0.05} if method == "radau" else {}},
                Exact({"q": add(num(1), TIME), "z": num(1)}),
                1e-5,
            )
        )
    select = _model_steps(
        "select", ["select"], [], {}, [("select", "Piecewise((1, t < 0.52), (-1, True))")], [], {"select": 0.0}
    )
    out.append(
        Case(
            C,
            "issue (5): a state named 'select' with Piecewise",
            "either",
            select,
            "solve",
            {"t_span": (0.0, 1.0), "options": {"h": 0.05}},
            Exact({"select": fn("Min", TIME, sub(num(1.04), TIME))}),
            0.1,
        )
    )
    out.append(_edge_issue("1e400*x", "invalid", None, "issue (5): 1e400*x"))
    out.append(
        Case(
            C,
            'issue (5): y0={"x": "abc"}',
            "invalid",
            steps_s,
            "solve",
            {"t_span": span, "y0": {"x": "abc"}, "options": {"h": 0.1}},
        )
    )
    out.append(
        Case(
            C,
            "issue (5): y0=np.zeros((0, n))",
            "invalid",
            steps_s,
            "solve",
            {"t_span": span, "y0": np.zeros((0, 2)), "options": {"h": 0.1}},
        )
    )
    out.append(
        Case(
            C,
            "issue (5): y0=np.zeros((0, 4)) on the pendulum",
            "invalid",
            pend_steps,
            "solve",
            {"t_span": span, "y0": np.zeros((0, 4)), "options": {"h": 0.1}},
        )
    )
    for device in ("meta", "mps", 5):
        out.append(
            Case(
                C,
                f"issue (5): radau device={device!r}",
                "invalid",
                steps_s,
                "solve",
                {"t_span": span, "options": {"h": 0.1, "device": device}},
            )
        )
        out.append(
            Case(
                C,
                f"issue (5): pinn config device={device!r}",
                "invalid",
                steps_s,
                "solve",
                {"t_span": span, "method": "pinn", "options": {"config": PinnSpec({"device": device, "h": 0.1})}},
            )
        )
    for method in ("radau", "casadi-collocation"):
        out.append(
            Case(
                C,
                f"issue (5): {method} h=1e-11 (MemoryError)",
                "invalid",
                steps_s,
                "solve",
                {"t_span": span, "method": method, "options": {"h": 1e-11}},
            )
        )
    out.append(
        Case(C, "issue (5): PINNConfig(bogus=1)", "invalid", (), "pinnconfig", {"kwargs": {"bogus": 1}}, check="none")
    )
    out.append(
        Case(
            C,
            "issue (5): pinn save= a path in a nonexistent directory",
            "either",
            steps_s,
            "solve",
            {
                "t_span": span,
                "method": "pinn",
                "options": {"config": PinnSpec({"h": 0.1}), "save": "missing/dir/net.pt"},
            },
            ref_s,
            1e-4,
        )
    )
    out.append(
        Case(
            C,
            "issue (5): Comparison.save into a path under a regular file",
            "invalid",
            steps_s,
            "compare",
            {"t_span": span, "methods": ["radau"], "kwargs": {"points": 1}, "save": "/dev/null/out"},
            check="none",
        )
    )
    out.append(
        Case(
            C,
            "issue (5): CLI target with a syntax error",
            "invalid",
            (),
            "cli",
            {"files": {"broken.py": "def build_model(:\n"}, "argv": ["compare", "broken.py", "--no-progress"]},
            check="cli",
        )
    )
    return out


def _edge_issue(text, expect, ref, desc, tol=1e-6, exact=False, options=None):
    steps = (
        ("Model", ("edge",), {}),
        ("states", ("x",), {}),
        ("ode", ("x", text), {}),
        ("initial", (), {"x": 0.0 if exact else 1.0}),
    )
    options = {"h": 0.05} if options is None else options
    if isinstance(ref, tuple):  # a tree: the right-hand side of x' = ...
        ref = TreeODE(("x",), (ref,), (), (), {}, (0.0 if exact else 1.0,), (0.0, 1.0))
    return Case("issue", desc, expect, steps, "solve", {"t_span": (0.0, 1.0), "options": options}, ref, tol)


def rlc_model():
    """A series RLC circuit driven by sin t: ``q' = i, L i' = vL``; ``0 = vR - R i``,
    ``0 = vC - q/C``, ``0 = sin t - vR - vL - vC``."""
    R, L, Cap = 1.0, 0.5, 0.25
    steps = _model_steps(
        "rlc",
        ["q", "i"],
        ["vR", "vL", "vC"],
        {"R": R, "L": L, "Cap": Cap},
        [("q", "i"), ("i", "vL/L")],
        [("vR - R*i", "ohm"), ("vC - q/Cap", "capacitor"), ("sin(t) - vR - vL - vC", "kirchhoff")],
        {"q": 0.0, "i": 0.0},
    )
    rules = (
        ("explicit", "vR", mul(num(R), var("i"))),
        ("explicit", "vC", div(var("q"), num(Cap))),
        ("explicit", "vL", sub(sub(fn("sin", TIME), var("vR")), var("vC"))),
    )
    ref = TreeODE(("q", "i"), (var("i"), div(var("vL"), num(L))), ("vR", "vL", "vC"), rules, {}, (0.0, 0.0), (0.0, 2.0))
    return steps, ref


def robertson_case(t_span, method, options, category, desc, expect="either"):
    """Robertson's stiff kinetics with y3 algebraic (y1 + y2 + y3 = 1)."""
    steps = _model_steps(
        "robertson",
        ["y1", "y2"],
        ["y3"],
        {},
        [("y1", "-0.04*y1 + 1e4*y2*y3"), ("y2", "0.04*y1 - 1e4*y2*y3 - 3e7*y2**2")],
        [("y1 + y2 + y3 - 1", "mass")],
        {"y1": 1.0, "y2": 0.0},
    )
    y1, y2, y3 = var("y1"), var("y2"), var("y3")
    rhs = (
        add(mul(num(-0.04), y1), mul(num(1e4), y2, y3)),
        add(mul(num(0.04), y1), mul(num(-1e4), y2, y3), mul(num(-3e7), y2, y2)),
    )
    rules = (("explicit", "y3", sub(sub(num(1), y1), y2)),)
    ref = TreeODE(("y1", "y2"), rhs, ("y3",), rules, {}, (1.0, 0.0), t_span, integrator="Radau")
    return Case(
        category, desc, expect, steps, "solve", {"t_span": t_span, "method": method, "options": options}, ref, 1e-3
    )


def model_edge_cases() -> list[Case]:
    """Declarations, initial values, compile options."""
    out = []
    M = "model-edge"
    steps_s, ref_s = small_model()
    span = (0.0, 1.0)

    def solve_case(desc, expect, steps, reference=None, tol=1e-5, **args):
        a = {"t_span": span, "options": {"h": 0.05}, **args}
        out.append(Case(M, desc, expect, tuple(steps), "solve", a, reference, tol))

    base = list(steps_s[:-1])
    for value, expect in (
        (True, "invalid"),
        (False, "invalid"),
        ("1.5", "either"),
        (NAN, "invalid"),
        (INF, "invalid"),
        (-INF, "invalid"),
        (1j, "invalid"),
        (None, "invalid"),
        ([], "invalid"),
        ([1.0], "either"),
        (np.float64(1.0), "valid"),
        (np.array(1.0), "either"),
        (np.array([1.0, 2.0]), "invalid"),
        ("abc", "invalid"),
        ("nan", "invalid"),
        (1e308, "either"),
        (Lazy("sp.Integer(1)"), "valid"),
        (Lazy("sp.Symbol('x')"), "invalid"),
        (Lazy("sp.oo"), "invalid"),
        (Lazy("sp.nan"), "invalid"),
        (1, "valid"),
        (10**400, "invalid"),
    ):
        steps = [*base, ("initial", (), {"x": value, "y": 1.0})]
        ref = small_exact(2.0, 1.0, 1.0) if expect != "invalid" and _is_one(value) else None
        solve_case(f"m.initial(x={_short_repr(value, 40)})", expect, steps, ref if expect != "invalid" else None)
    for value, expect in (
        (True, "invalid"),
        ("2", "either"),
        (NAN, "invalid"),
        (INF, "invalid"),
        ("abc", "invalid"),
        (None, "either"),
        (1j, "invalid"),
        (Lazy("sp.Rational(2)"), "valid"),
    ):
        steps = [s if s[0] != "parameter" else ("parameter", ("k", value), {}) for s in steps_s]
        solve_case(f"m.parameter('k', {_short_repr(value, 40)})", expect, steps, ref_s if expect != "invalid" else None)
    for t0, expect in ((NAN, "invalid"), (INF, "invalid"), ("0", "either"), (True, "invalid"), (1e300, "either")):
        steps = [*base, ("initial", (), {"x": 1.0, "y": 1.0, "t": t0})]
        solve_case(f"m.initial(t={t0!r})", expect, steps)
    solve_case(
        "m.initial names an undeclared variable", "invalid", [*base, ("initial", (), {"x": 1.0, "y": 1.0, "q": 1.0})]
    )
    solve_case("m.initial(w=<inconsistent>)", "invalid", [*base, ("initial", (), {"x": 1.0, "y": 1.0, "w": 3.0})])
    solve_case("m.initial(w=<consistent>)", "valid", [*base, ("initial", (), {"x": 1.0, "y": 1.0, "w": 0.5})], ref_s)
    solve_case("missing initial value", "invalid", [*base, ("initial", (), {"x": 1.0})])
    solve_case("no m.initial at all", "invalid", base)
    # names
    for name, expect in (
        ("lambda", "invalid"),
        ("if", "invalid"),
        ("None", "invalid"),
        ("t", "invalid"),
        ("sin", "invalid"),
        ("pi", "invalid"),
        ("x y", "either"),
        ("", "invalid"),
        ("_x", "invalid"),
        ("1x", "invalid"),
        ("x'", "invalid"),
        ("ω", "invalid"),
        ("a" * 300, "either"),
        ("x-y", "invalid"),
        ("x.y", "invalid"),
        ("__init__", "invalid"),
        ("Piecewise", "invalid"),
        ("diff", "invalid"),
        ("Symbol", "invalid"),
    ):
        steps = (
            ("Model", ("n",), {}),
            ("states", ([name],), {}),
            ("ode", (name.split()[0] if name.strip() else "q", "-1"), {}),
            ("initial", (), {}),
        )
        out.append(Case(M, f"state name {name[:40]!r}", expect, steps, "compile", {}, check="none"))
    out.append(
        Case(M, "states('x x')", "invalid", (("Model", ("n",), {}), ("states", ("x x",), {})), "build", check="none")
    )
    out.append(Case(M, "states('')", "invalid", (("Model", ("n",), {}), ("states", ("",), {})), "build", check="none"))
    out.append(Case(M, "states(5)", "invalid", (("Model", ("n",), {}), ("states", (5,), {})), "build", check="none"))
    out.append(
        Case(M, "states(None)", "invalid", (("Model", ("n",), {}), ("states", (None,), {})), "build", check="none")
    )
    out.append(
        Case(
            M,
            "algebraic with the name of a state",
            "invalid",
            (("Model", ("n",), {}), ("states", ("x",), {}), ("algebraics", ("x",), {})),
            "build",
            check="none",
        )
    )
    for name in ("", "\n", "模型", "a" * 10_000, "a\\", 'he said "hi"', "tab\there", None, 5, b"bytes"):
        steps = (("Model", (name,), {}), *steps_s[1:])
        solve_case(f"model name {_short_repr(name, 40)}", "either", steps, ref_s, 1e-4)
    # equations
    for rhs, expect in (
        (1, "valid"),
        (None, "invalid"),
        ([1, 2], "invalid"),
        (Lazy("sp.Matrix([1, 2])"), "invalid"),
        (Lazy("sp.Symbol('x', positive=True)"), "either"),
        (Lazy("sp.Symbol('q')"), "invalid"),
        (Lazy("sp.Eq(sp.Symbol('x'), 1)"), "invalid"),
        (Lazy("sp.sympify('x > 0')"), "invalid"),
        (Lazy("sp.Function('f')(sp.Symbol('t'))"), "invalid"),
        (Lazy("sp.zoo"), "invalid"),
        (Lazy("sp.I"), "invalid"),
        (Lazy("sp.oo"), "invalid"),
        (Lazy("sp.Float('1e400')"), "invalid"),
        (Lazy("np.float64(1.0)"), "valid"),
        (Lazy("np.array([1.0])"), "either"),
        (1e400, "invalid"),
        (NAN, "invalid"),
        (True, "invalid"),
        ("1", "valid"),
        (Lazy("sp.Integral(sp.Symbol('x'), sp.Symbol('t'))"), "invalid"),
        (Lazy("sp.Sum(sp.Symbol('x'), (sp.Symbol('i'), 1, 3))"), "either"),
        (Lazy("sp.floor(sp.Symbol('x'))"), "either"),  # (floor is a switch now: daemodel.solving.switches)
        (Lazy("sp.Mod(sp.Symbol('x'), 2)"), "either"),
        (Lazy("sp.gamma(sp.Symbol('x') + 2)"), "either"),
        (Lazy("sp.re(sp.Symbol('x'))"), "either"),
    ):
        steps = (("Model", ("eq",), {}), ("states", ("x",), {}), ("ode", ("x", rhs), {}), ("initial", (), {"x": 0.0}))
        ref = Exact({"x": TIME}) if expect == "valid" else None
        out.append(
            Case(
                M,
                f"m.ode('x', {_short_repr(rhs, 60)})",
                expect,
                steps,
                "solve",
                {"t_span": span, "options": {"h": 0.05}},
                ref,
                1e-9,
            )
        )
    out.append(
        Case(
            M,
            "m.ode on an algebraic variable",
            "invalid",
            (*steps_s[:3], ("ode", ("w", "1"), {})),
            "build",
            check="none",
        )
    )
    out.append(
        Case(
            M, "m.ode on an undeclared name", "invalid", (*steps_s[:2], ("ode", ("q", "1"), {})), "build", check="none"
        )
    )
    out.append(Case(M, "second ODE for x", "invalid", (*steps_s[:-1], ("ode", ("x", "1"), {})), "build", check="none"))
    out.append(
        Case(
            M,
            "constraint name used twice",
            "invalid",
            (*steps_s[:-1], ("constraint", ("w",), {"name": "half"})),
            "build",
            check="none",
        )
    )
    out.append(
        Case(
            M,
            "constraint 'a = b = c'",
            "invalid",
            (*steps_s[:5], ("constraint", ("w = 0.5*y = 1",), {})),
            "build",
            check="none",
        )
    )
    out.append(
        Case(M, "constraint '= w'", "invalid", (*steps_s[:5], ("constraint", ("= w",), {})), "build", check="none")
    )
    out.append(
        Case(M, "constraint 'w =='", "invalid", (*steps_s[:5], ("constraint", ("w ==",), {})), "build", check="none")
    )
    # whole-system structure
    no_ode = (("Model", ("m",), {}), ("states", ("x",), {}), ("initial", (), {"x": 1.0}))
    out.append(Case(M, "state without an ODE", "invalid", no_ode, "compile", check="none"))
    out.append(Case(M, "empty model compiled", "either", (("Model", ("empty",), {}),), "compile", check="none"))
    out.append(Case(M, "empty model solved", "invalid", (("Model", ("empty",), {}),), "solve", {"t_span": span}))
    unbalanced = (*steps_s[:5], ("constraint", ("w - 0.5*y",), {}), ("constraint", ("w - x",), {}), steps_s[-1])
    out.append(Case(M, "two constraints for one algebraic", "invalid", unbalanced, "compile", check="none"))
    free = (
        ("Model", ("m",), {}),
        ("states", ("x",), {}),
        ("algebraics", ("z",), {}),
        ("ode", ("x", "-x"), {}),
        ("constraint", ("x - 1",), {}),
        ("initial", (), {"x": 1.0}),
    )
    out.append(Case(M, "constraint not involving the algebraic", "invalid", free, "compile", check="none"))
    index4 = _model_steps(
        "i4",
        ["a", "b", "c"],
        ["z"],
        {},
        [("a", "b"), ("b", "c"), ("c", "z")],
        [("a - sin(t)", "g")],
        {"a": 0.0, "b": 1.0, "c": 0.0},
    )
    out.append(
        Case(
            M,
            "index 4 (chain of three integrators)",
            "either",
            index4,
            "solve",
            {"t_span": span, "options": {"h": 0.05}},
            Exact({"a": fn("sin", TIME), "b": fn("cos", TIME), "c": neg(fn("sin", TIME)), "z": neg(fn("cos", TIME))}),
            1e-4,
        )
    )
    incons2 = _model_steps("inc2", ["q"], ["z"], {}, [("q", "z")], [("q - sin(t)", "g")], {"q": 0.5})
    out.append(Case(M, "index-2 constraint violated at t0", "invalid", incons2, "compile", check="none"))
    out.append(
        Case(
            M,
            "inconsistent index-2 state with compile(repair=True)",
            "either",
            incons2,
            "solve",
            {"t_span": span, "compile": {"repair": True}, "options": {"h": 0.05}},
            Exact({"q": fn("sin", TIME), "z": fn("cos", TIME)}),
            1e-5,
        )
    )
    # compile options
    for kwargs, expect in (
        ({"outputs": []}, "either"),
        ({"outputs": ["nope"]}, "invalid"),
        ({"outputs": "x"}, "either"),
        ({"outputs": [5]}, "invalid"),
        ({"outputs": ["x"]}, "valid"),
        ({"repair": "no"}, "invalid"),
        ({"repair": 1}, "either"),
        ({"repair": None}, "either"),
    ):
        out.append(Case(M, f"compile({_kw(kwargs)})", expect, steps_s, "compile", {"compile": kwargs}, check="none"))
    return out


def _is_one(value) -> bool:
    try:
        return not isinstance(value, (bool, str, Lazy)) and float(np.asarray(value).reshape(-1)[0]) == 1.0
    except (TypeError, ValueError, IndexError):
        return isinstance(value, Lazy) and value.code == "sp.Integer(1)"


def api_edge_cases() -> list[Case]:
    """``dm.solve``/``compare``/``Solution``/``Surrogate``/``PINNConfig`` arguments."""
    out = []
    A = "api-edge"
    steps_s, ref_s = small_model()
    span = (0.0, 1.0)

    def solve(desc, expect, reference=None, tol=1e-5, steps=steps_s, **args):
        a = {"t_span": span, "options": {"h": 0.05}, **args}
        out.append(Case(A, desc, expect, steps, "solve", a, reference, tol))

    for t_span, expect in (
        ("01", "invalid"),
        ((0,), "invalid"),
        ((0, 1, 2), "invalid"),
        ([0, 1], "valid"),
        (np.array([0.0, 1.0]), "valid"),
        ((0, "1"), "either"),
        ((0, True), "invalid"),
        ((0, NAN), "invalid"),
        ((0, INF), "invalid"),
        ((1, 0), "invalid"),
        ((0, 0), "invalid"),
        (None, "invalid"),
        (5, "invalid"),
        ({"a": 1}, "invalid"),
        ((0, 1j), "invalid"),
        ((np.float32(0), np.float32(1)), "valid"),
        ((0.0, 1.0 + 1e-15), "either"),
    ):
        good = expect != "invalid"
        solve(f"t_span={_short_repr(t_span, 40)}", expect, ref_s if good else None, t_span=t_span)
    for method in ("RADAU", None, 5, "", " radau", "radau ", "Radau", ["radau"]):
        solve(f"method={method!r}", "invalid", method=method)
    for y0, expect in (
        ([1.0], "invalid"),
        ([1.0, 1.0, 1.0], "invalid"),
        (np.zeros((0, 2)), "invalid"),
        ({"x": "abc"}, "invalid"),
        ({"x": "1.0"}, "either"),
        ({"x": NAN}, "invalid"),
        ({"x": INF}, "invalid"),
        ({"x": [1.0, 1.0], "y": [1.0, 1.0, 1.0]}, "invalid"),
        ({"nope": 1.0}, "invalid"),
        ({"x": True}, "invalid"),
        ([[[1.0, 1.0]]], "invalid"),
        ({"x": np.ones((2, 2))}, "invalid"),
        (5.0, "either"),
        ("abc", "invalid"),
        ({"x": []}, "invalid"),
        ({"x": None}, "invalid"),
        ({"w": 0.5}, "invalid"),
        ({"x": 1.0 + 0j}, "either"),
        ({"x": [NAN, 1.0]}, "invalid"),
    ):
        solve(f"y0={_short_repr(y0, 50)}", expect, ref_s if expect == "either" and _is_one(y0) else None, y0=y0)
    solve(
        "y0 array (2, 2): a batch",
        "valid",
        [small_exact(2.0, 1.0, 1.0), small_exact(2.0, 0.5, 2.0)],
        y0=np.array([[1.0, 1.0], [0.5, 2.0]]),
    )
    solve(
        "y0 dict of arrays: a batch",
        "valid",
        [small_exact(2.0, 1.0, 1.0), small_exact(2.0, -1.0, 0.5)],
        y0={"x": np.array([1.0, -1.0]), "y": np.array([1.0, 0.5])},
    )
    solve("y0 (n,) array", "valid", small_exact(2.0, 0.5, 2.0), y0=np.array([0.5, 2.0]))
    solve("parameters batch", "valid", [small_exact(2.0), small_exact(3.0)], parameters={"k": np.array([2.0, 3.0])})
    solve("parameters={'k': 3}", "valid", small_exact(3.0), parameters={"k": 3.0})
    for params, expect in (
        ({"nope": 1.0}, "invalid"),
        ({"k": "x"}, "invalid"),
        ({"k": NAN}, "invalid"),
        ({"k": [2.0, 3.0, INF]}, "invalid"),
        ([2.0, 3.0], "invalid"),
        ({"x": 1.0}, "invalid"),
        ("k", "invalid"),
        (np.zeros((0, 1)), "invalid"),
    ):
        solve(f"parameters={_short_repr(params, 50)}", expect, parameters=params)
    for z0, expect in (
        ({"w": 0.5}, "valid"),
        ({"w": 3.0}, "either"),
        ({"w": "a"}, "invalid"),
        ({"nope": 1}, "invalid"),
        ({"w": NAN}, "invalid"),
        ({"x": 1.0}, "invalid"),
        ({"w": 1e300}, "either"),
    ):
        solve(f"z0={_short_repr(z0, 50)}", expect, ref_s if expect != "invalid" else None, z0=z0)
    for bad in ("stage", "tol", "", "method", "t_eval_", "verbose"):
        solve(f"unknown option {bad!r}", "invalid", options={"h": 0.05, bad: 1})
    out.append(
        Case(A, "solve(None, ...): not a model", "invalid", (), "solve", {"t_span": span})
    )  # no steps: model is None
    # Solution API
    solve("sol['nope']", "invalid", then=("__getitem__", "nope"))
    solve("sol.errors(reference naming no variable)", "invalid", then=("errors", Lazy("fuzz_cases.bad_reference")))
    solve("sol.errors(5)", "invalid", then=("errors", 5))
    solve("sol.plot into a missing directory", "either", then=("plot", "missing/dir/p.png"))
    solve("sol.plot under a regular file", "invalid", then=("plot", "/dev/null/p.png"))
    solve("sol.to_pandas()", "valid", then=("to_pandas",))
    solve("sol.drift()", "valid", then=("drift",))
    for case in out[-7:]:
        case.check = "none"
    # compare
    for methods, kwargs, expect, desc in (
        (["radau"], {"points": 1}, "valid", "compare radau, 1 point"),
        ([], {}, "invalid", "compare with no methods"),
        (["nope"], {}, "invalid", "compare an unknown method"),
        (["radau"], {"points": 0}, "invalid", "compare points=0"),
        (["radau"], {"points": True}, "invalid", "compare points=True"),
        (["radau"], {"reference": 5}, "invalid", "compare reference=5"),
        (
            ["radau"],
            {"points": 1, "reference": Lazy("fuzz_cases.bad_reference")},
            "invalid",
            "compare reference naming nothing",
        ),
        (["radau"], {"sweep": {"pinn": [{}]}}, "invalid", "compare sweep for a method not compared"),
        (["radau"], {"sweep": {"radau": []}}, "invalid", "compare empty sweep"),
        (["radau"], {"sweep": {"radau": [{"h": -1}]}}, "either", "compare sweep with h=-1"),
        (["radau"], {"sweep": {"radau": [{"bogus": 1}]}}, "either", "compare sweep with an unknown option"),
        ("radau", {"points": 1}, "either", "compare methods='radau' (a string)"),
    ):
        out.append(
            Case(
                A,
                desc,
                expect,
                steps_s,
                "compare",
                {"t_span": span, "methods": methods, "kwargs": kwargs},
                check="none",
            )
        )
    out.append(
        Case(
            A,
            "Comparison.save into a missing directory",
            "either",
            steps_s,
            "compare",
            {"t_span": span, "methods": ["radau"], "kwargs": {"points": 1}, "save": "missing/deeper/dir"},
            check="none",
        )
    )
    # PINNConfig
    for kwargs, expect in (
        ({"bogus": 1}, "invalid"),
        ({"h": 0}, "invalid"),
        ({"h": NAN}, "invalid"),
        ({"width": 0}, "invalid"),
        ({"depth": -1}, "invalid"),
        ({"activation": "relu"}, "invalid"),
        ({"optimizer": "sgd"}, "invalid"),
        ({"dtype": "float16"}, "invalid"),
        ({"device": "meta"}, "either"),
        ({"device": 5}, "either"),
        ({"stages": 0}, "invalid"),
        ({"stages": "3"}, "invalid"),
        ({"tol": -1.0}, "invalid"),
        ({"samples": 2}, "invalid"),
        ({"h": 0.1}, "valid"),
        ({"width": 2.5}, "invalid"),
        ({"seed": "a"}, "invalid"),
        ({"iterations": -3}, "invalid"),
        ({"weight_g": INF}, "invalid"),
    ):
        out.append(Case(A, f"PINNConfig({_kw(kwargs)})", expect, (), "pinnconfig", {"kwargs": kwargs}, check="none"))
    # (config=None is the default since issue 43: the PINN's h then follows the problem, a pre-solve's steps)
    for config, expect in (({"h": 0.1}, "invalid"), (None, "either"), ("fast", "invalid")):
        solve(f"pinn config={config!r}", expect, method="pinn", options={"config": config})
    solve(
        "pinn executor='ray' without segment_starts",
        "invalid",
        method="pinn",
        options={"executor": "ray", "config": PinnSpec({"h": 0.1})},
    )
    solve(
        "pinn segment_starts of the wrong shape",
        "invalid",
        method="pinn",
        options={"segment_starts": np.zeros((3, 7)), "config": PinnSpec({"h": 0.1})},
    )
    solve("pinn, h=0.1", "valid", ref_s, 1e-4, method="pinn", options={"config": PinnSpec({"h": 0.1})})
    # Surrogate
    for kwargs, expect in (
        ({"box": {}}, "invalid"),
        ({"box": {"nope": (0, 1)}}, "invalid"),
        ({"box": {"x": (1, 0)}}, "invalid"),
        ({"box": {"x": (NAN, 1)}}, "invalid"),
        ({"box": {"x": (0.9, 1.1)}, "samples": 0}, "invalid"),
        ({"box": {"x": "ab"}}, "invalid"),
        ({"box": {"x": (0.9, 1.1)}, "config": 5}, "invalid"),
    ):
        out.append(
            Case(
                A,
                f"Surrogate.train({_kw(kwargs)})",
                expect,
                steps_s,
                "surrogate_train",
                {"t_span": span, "kwargs": kwargs},
                check="none",
            )
        )
    for files, path, desc in (
        ({}, "missing.pt", "a missing file"),
        ({"junk.pt": "not a network"}, "junk.pt", "a text file"),
        ({}, "/dev/null", "/dev/null"),
        ({}, ".", "a directory"),
    ):
        out.append(
            Case(
                A,
                f"Surrogate.load({desc})",
                "invalid",
                steps_s,
                "surrogate_load",
                {"files": files, "path": path},
                check="none",
            )
        )
    return out


CLI_MODEL = """
import numpy as np
import daemodel as dm

T_SPAN = (0.0, 1.0)


def build_model():
    m = dm.Model({name!r})
    m.states("x y")
    m.algebraics("w")
    m.parameter("k", 2.0)
    m.ode("x", {ode!r})
    m.ode("y", "-y")
    m.constraint("w - 0.5*y", name="half")
    m.initial(x=1.0, y=1.0)
    return m


def exact(t):
    t = np.asarray(t, dtype=float)
    return {{"x": 0.5 * np.exp(-2 * t) + 0.5 * np.exp(-t), "y": np.exp(-t), "w": 0.5 * np.exp(-t)}}
"""


def cli_cases() -> list[Case]:
    """``daemodel compare`` on problem names and model files, with good and bad arguments."""
    out = []
    good = CLI_MODEL.format(name="small", ode="-k*x + w")
    base = ["--methods", "radau", "--points", "1", "--no-progress", "--out", "out"]

    def cli(desc, expect, argv, files=None, out_dir=None, dirs=()):
        args = {"argv": argv, "files": files or {}, "dirs": dirs}
        if out_dir:
            args["out"] = out_dir
        out.append(Case("cli", desc, expect, (), "cli", args, check="cli"))

    cli("compare hessenberg --methods radau --points 1", "valid", ["compare", "hessenberg", *base], out_dir="out")
    cli("compare a model file with exact()", "valid", ["compare", "model.py", *base], {"model.py": good}, "out")
    cli(
        "compare a model file, radau and casadi-idas",
        "valid",
        ["compare", "model.py", "--methods", "radau,casadi-idas", "--points", "1", "--no-progress", "--out", "out"],
        {"model.py": good},
        "out",
    )
    cli("missing model file", "invalid", ["compare", "missing.py", *base])
    cli("syntax error in the model file", "invalid", ["compare", "m.py", *base], {"m.py": "def build_model(:\n"})
    cli("indentation error in the model file", "invalid", ["compare", "m.py", *base], {"m.py": "if True:\nx = 1\n"})
    cli("model file raises at import", "invalid", ["compare", "m.py", *base], {"m.py": "raise RuntimeError('boom')\n"})
    cli(
        "model file imports a missing module",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": "import no_such_module_xyz\n"},
    )
    cli("model file defines no model", "invalid", ["compare", "m.py", *base], {"m.py": "x = 1\n"})
    cli(
        "build_model returns 42", "invalid", ["compare", "m.py", *base], {"m.py": "def build_model():\n    return 42\n"}
    )
    cli(
        "build_model raises ValueError",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": "def build_model():\n    raise ValueError('no')\n"},
    )
    cli(
        "build_model with a bad expression",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": CLI_MODEL.format(name="bad", ode="-k*x + ")},
    )
    cli(
        "model file with a hostile expression",
        "hostile",
        ["compare", "m.py", *base],
        {"m.py": CLI_MODEL.format(name="evil", ode=HOSTILE_PAYLOADS[2][0])},
    )
    cli(
        "model file whose model name injects code",
        "either",
        ["compare", "m.py", *base],
        {"m.py": CLI_MODEL.format(name='a"""\n    open("@CANARY@", "w")\n    """', ode="-k*x + w")},
        "out",
    )
    for t_span in ('"01"', "(1.0, 0.0)", "(0.0, 1.0, 2.0)", "None", "(0.0, float('nan'))"):
        cli(
            f"T_SPAN = {t_span}",
            "invalid",
            ["compare", "m.py", *base],
            {"m.py": good.replace("T_SPAN = (0.0, 1.0)", f"T_SPAN = {t_span}")},
        )
    cli(
        "exact(t) names no variable",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": good + "\n\ndef exact(t):\n    return {'nope': t}\n"},
    )
    cli(
        "exact(t) raises",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": good + "\n\ndef exact(t):\n    return 1 / 0\n"},
    )
    cli(
        "exact(t) returns the wrong shape",
        "invalid",
        ["compare", "m.py", *base],
        {"m.py": good + "\n\ndef exact(t):\n    return {'x': [1.0, 2.0]}\n"},
    )
    cli("unknown problem name", "invalid", ["compare", "bogus", *base])
    cli("a directory named m.py", "invalid", ["compare", "m.py", *base], dirs=("m.py",))
    cli("a model file with a NUL byte", "invalid", ["compare", "m.py", *base], {"m.py": "x = 1\x00\n"})
    cli("a model file that is not UTF-8", "invalid", ["compare", "m.py", *base], {"m.py": b"\xff\xfe\x00x = 1\n"})
    for extra, desc in (
        (["--points", "0"], "--points 0"),
        (["--points", "-3"], "--points -3"),
        (["--t-end", "nan"], "--t-end nan"),
        (["--t-end", "-1"], "--t-end -1"),
        (["--t-end", "0"], "--t-end 0"),
        (["--t-end", "inf"], "--t-end inf"),
        (["--methods", "bogus"], "--methods bogus"),
        (["--methods", ",,,"], "--methods ,,,"),
        (["--points", "x"], "--points x"),
        (["--bogus"], "--bogus"),
    ):
        cli(desc, "invalid", ["compare", "hessenberg", "--no-progress", "--out", "out", "--methods", "radau", *extra])
    cli("--threads 0", "either", ["compare", "hessenberg", *base, "--threads", "0"])
    cli("--out under a regular file", "invalid", ["compare", "hessenberg", *base[:-1], "/dev/null/out"])
    cli("no arguments", "invalid", [])
    cli("compare without targets", "invalid", ["compare"])
    cli("unknown command", "invalid", ["solve", "hessenberg"])
    cli("--help", "either", ["--help"])
    return out


def fixed_cases() -> list[Case]:
    """Cases that every run includes: the issue's, hostile strings, model, API and CLI edges."""
    return _number(
        [
            *issue_cases(),
            *hostile_cases(),
            *model_edge_cases(),
            *api_edge_cases(),
            *cli_cases(),
            *(_edge_case(*e) for e in EXTREME_NUMBERS),
        ],
        "f",
    )


# Random cases per category (weights), and the generator of each.
RANDOM_MIX = {
    "expr-valid": 0.18,
    "expr-edge": 0.07,
    "expr-hostile": 0.06,
    "options": 0.33,
    "dae-index1": 0.11,
    "dae-index2": 0.11,
    "dae-pendulum": 0.07,
    "known-bad": 0.07,
}


def _random_case(rng: random.Random, category: str) -> Case:
    if category == "expr-valid":
        return gen_expr_valid(rng)
    if category == "expr-edge":
        return gen_expr_edge(rng)
    if category == "expr-hostile":
        return gen_hostile(rng)
    if category == "options":
        return gen_options(rng)
    if category == "known-bad":
        return gen_known_bad(rng)
    return gen_dae(rng, category)


def _random_case_bounded(key: str, category: str, retries: int = 3) -> Case:
    """The case drawn from ``Random(key)``; where its generator finds no tame problem (every attempt
    too costly or unbounded), a redraw from ``Random(key + "-retry<k>")``, and after ``retries`` of
    those a fixed small problem, so that generation always ends."""
    for k in range(retries + 1):
        rng = random.Random(key if k == 0 else f"{key}-retry{k}")
        try:
            with np.errstate(all="ignore"):
                return _random_case(rng, category)
        except NoTameProblem:
            continue
    steps, ref = small_model()
    args = {"t_span": (0.0, 1.0), "method": "radau", "options": {"stages": 3, "h": 0.05}}
    return Case(category, f"small model (no tame random problem for {key})", "valid", steps, "solve", args, ref, 1e-6)


def random_cases(n: int, seed: int = 0, mix: dict | None = None) -> list[Case]:
    """``n`` random cases drawn from ``mix`` (default :data:`RANDOM_MIX`), reproducible from ``seed``.

    Each case has its own generator seeded from ``(seed, i)``, so case i does not depend on how
    many random numbers the cases before it used.
    """
    sys.setrecursionlimit(max(sys.getrecursionlimit(), EXPRESSION_RECURSION_LIMIT))
    mix = RANDOM_MIX if mix is None else mix
    cats, weights = list(mix), list(mix.values())
    picker = random.Random(seed)
    out = []
    for i in range(n):
        category = picker.choices(cats, weights)[0]
        out.append(_random_case_bounded(f"{seed}-{i}-{category}", category))
    return _number(out, f"r{seed}-")


def _number(cases: list[Case], prefix: str) -> list[Case]:
    for i, case in enumerate(cases):
        case.id = f"{prefix}{i:04d}-{case.category}"
    return cases


# Issue cases that hang on the old code: the fast pass leaves them to the slow one.
HANG_PRONE = ("disappearing root", "Robertson", "-sign(x)", "1e300")


def fast_cases() -> list[Case]:
    """A few dozen quick cases for the default test run: the issue's (less the hang-prone),
    a spread of hostile strings, edges and random problems."""
    issue = [c for c in issue_cases() if not any(k in c.description for k in HANG_PRONE)]
    hostile = hostile_cases()
    picked_hostile = [c for c in hostile if "[ode]" in c.description and CANARY in str(c.steps)][:6]
    picked_hostile += [c for c in hostile if "model name injection #0" in c.description][:1]
    picked_hostile += hostile[40:140:20]
    model = model_edge_cases()[::12]
    api = api_edge_cases()[::15]
    cli = [c for c in cli_cases() if "syntax error" in c.description or "hostile" in c.description]
    mix = {k: v for k, v in RANDOM_MIX.items() if k != "known-bad"}
    rand = random_cases(12, seed=20240, mix=mix)
    return _number([*issue, *picked_hostile, *model, *api, *cli, *rand], "fast-")
