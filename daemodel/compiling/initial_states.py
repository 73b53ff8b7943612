"""A batch of consistent initial states for a solve.

``solve(..., y0=..., z0=..., parameters=...)`` may give one initial state or many: by name
(``{"y1": array, "y2": array}``; states not named keep the model's values) or as an array
``(n,)`` / ``(B, n)`` in ``state_names`` order.  Every sample must satisfy the z-free
constraint levels (the same test as at compile time); its algebraic values then come from
a batched Newton solve of the determining equations, started from ``z0`` when given and from
the compiled ``z0`` otherwise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from daemodel.compiling.determinants import determinant_signs
from daemodel.compiling.init import (
    ALGEBRAIC_TOL,
    NumericSystem,
    hidden_constraints,
    is_root,
    project,
    solve_algebraic,
    violations,
)
from daemodel.declaring.arrays import compact_listing, element_names
from daemodel.errors import (
    BranchError,
    FixedStateError,
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    InvalidValueError,
    ShapeError,
    UnknownSymbolError,
)
from daemodel.messages import quoted
from daemodel.reals import is_real, real

# Samples listed by index in an error message, at most.
LISTED_SAMPLES = 5
# A BranchError shows z on either side, at most this many of them: those that move most between the two outputs
# (at 10^5 unknowns all of them made a message of ~1 MB).
LISTED_BRANCH_VALUES = 8
# check_branch evaluates H_z's nonzeros at this many bytes at a time: a large batch of outputs of a
# model with many algebraic variables would otherwise hold all of them at once.
BRANCH_CHECK_BYTES = 64 * 2**20


@dataclass(frozen=True)
class InitialStates:
    """Consistent initial values of every sample.

    Attributes
    ----------
    y0 : ndarray, shape (B, n)
    z0 : ndarray, shape (B, m)
    p : ndarray, shape (B, k)
    batched : bool
        Whether the caller asked for a batch (a Solution then keeps the batch axis).
    """

    y0: np.ndarray
    z0: np.ndarray
    p: np.ndarray
    batched: bool

    @property
    def size(self) -> int:
        return len(self.y0)


def columns(compiled, value, names, defaults, what: str):
    """One argument's values as columns: ``(B or None, ndarray (B or 1, len(names)))``.

    Parameters
    ----------
    compiled : CompiledDAE
    value : dict, array or None
        By name (numbers or 1-d arrays of samples; a name left out takes its default), an array
        of shape ``(len(names),)`` or ``(B, len(names))``, or None (every default).
    names, defaults : sequences of the same length
        The columns' names, in order, and their values where ``value`` gives none.
    what : str
        The argument's name in messages (``"y0"``, ``"z0"``, ``"parameters"``).

    Returns
    -------
    size : int or None
        The batch size that ``value`` gives; None for a single sample.
    array : ndarray, shape (B or 1, len(names))

    Raises
    ------
    UnknownSymbolError
        A name that is not among ``names`` (nor a parameter that compiling pruned).
    ShapeError
        Arrays of different lengths, of no samples, or of the wrong shape.
    """
    if value is None:
        return None, np.asarray(defaults, dtype=float)[None, :]
    if isinstance(value, dict) and any(isinstance(k, str) and k in compiled.arrays for k in value):
        value = _spread(compiled.arrays, value, what)
    if isinstance(value, dict):
        # a parameter the model declares but no kept equation uses was pruned: its values change
        # nothing, but they are checked and still make a batch
        pruned = set(compiled.dropped.get("parameters", ())) if what == "parameters" else set()
        unknown = sorted(set(value) - set(names) - pruned)
        if unknown:
            raise UnknownSymbolError(
                f"{what} names {', '.join(repr(u) for u in unknown)}, which "
                f"{'is' if len(unknown) == 1 else 'are'} not among {_listed(names)} "
                f"of model '{compiled.name}'"
            )
        arrays = {k: _numbers(v, f"{what}['{k}']") for k, v in value.items()}
        for k, a in arrays.items():
            if a.ndim > 1:
                raise ShapeError(f"{what}['{k}'] must be a number or a 1-d array of samples; got shape {a.shape}")
        sizes = {a.shape[0] for a in arrays.values() if a.ndim == 1}
        if len(sizes) > 1:
            raise ShapeError(
                f"{what}: the arrays have different lengths "
                + ", ".join(f"{k}: {a.shape[0]}" for k, a in arrays.items() if a.ndim == 1)
            )
        size = sizes.pop() if sizes else None
        if size == 0:
            raise ShapeError(f"{what}: the arrays hold no samples; give at least one")
        out = np.repeat(np.asarray(defaults, dtype=float)[None, :], size or 1, axis=0)
        for i, name in enumerate(names):
            if name in arrays:
                out[:, i] = arrays[name]
        return size, out
    array = _numbers(value, what)
    if array.ndim == 2 and array.shape[0] == 0:
        raise ShapeError(f"{what} has shape {array.shape}: a batch of no samples; give at least one")
    if array.ndim not in (1, 2) or array.shape[-1] != len(names):
        raise ShapeError(
            f"{what} must have shape ({len(names)},) or (batch, {len(names)}) with columns {_listed(names)}; "
            f"got shape {array.shape}"
        )
    return (array.shape[0] if array.ndim == 2 else None), np.atleast_2d(array)


def _listed(names) -> str:
    """``names`` for a message, as a list, each array's elements as one entry."""
    return f"[{compact_listing(names)}]" if len(names) else "[]"


def _spread(shapes: dict, value: dict, what: str) -> dict:
    """``value`` with each array of variables by its name (``{"T": array}``, of the array's shape for one
    sample or ``(B, *shape)`` for a batch) spread over its elements' names."""
    out = {}
    for key, v in value.items():
        if not (isinstance(key, str) and key in shapes):
            out[key] = v
            continue
        shape, array = shapes[key], _numbers(v, f"{what}['{key}']")
        if array.shape != shape and array.shape[1:] != shape:
            raise ShapeError(
                f"{what}['{key}'] must have the array's shape {shape}, or (batch, *{shape}) for a batch; "
                f"got shape {array.shape}"
            )
        one = array.shape == shape  # (else a batch: the samples first)
        for name, index in zip(element_names(key, shape), np.ndindex(*shape), strict=True):
            out[name] = array[index] if one else array[(slice(None), *index)]
    return out


def _numbers(value, what) -> np.ndarray:
    """``value`` as a float array, refusing strings, booleans and objects (numpy would read "1.5" or True)."""
    if isinstance(value, str | bytes):
        raise InvalidValueError(f"{what} must be numbers; got the string {value!r}")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as error:
        raise InvalidValueError(f"{what} must be numbers; got {type(value).__name__} ({error})") from None
    if raw.dtype.kind == "O" and raw.size and all(is_real(v) for v in raw.flat):
        # sympy numbers (sp.pi, sp.Rational(1, 3)) make an object array: each converted, a symbol refused
        return np.array([real(v, what) for v in raw.flat], dtype=float).reshape(raw.shape)
    if raw.dtype.kind not in "iuf":
        kind = {"b": "booleans", "U": "strings", "S": "bytes", "O": "objects", "c": "complex numbers"}
        raise InvalidValueError(
            f"{what} must be real numbers; got {kind.get(raw.dtype.kind, raw.dtype.name)} ({quoted(value, 60)})"
        )
    return raw.astype(float)


def _finite(array, names, what):
    bad = ~np.isfinite(array)
    if bad.any():
        sample, column = np.argwhere(bad)[0]
        raise InvalidValueError(f"{what}: {names[column]} of sample {sample} is {array[sample, column]}, not finite")


def _samples(indices) -> str:
    listed = ", ".join(str(i) for i in indices[:LISTED_SAMPLES])
    return listed + (f" and {len(indices) - LISTED_SAMPLES} more" if len(indices) > LISTED_SAMPLES else "")


@dataclass(frozen=True)
class _Checks:
    """The batched numpy functions of the initial-state checks of one compiled model.

    Attributes
    ----------
    numeric : NumericSystem
    hidden : list of (level name, label, expr)
        Every z-free constraint level.
    residual : callable (t, Y, Z, P) -> (B, len(hidden))
    H : callable (t, Y, Z, P) -> (B, m)
        The determining equations.
    Hz : callable (t, Y, Z, P) -> ndarray (B, m, m) or SparseStack
        Their Jacobian in z (:meth:`~daemodel.compiling.init.NumericSystem.newton_jacobian`: sparse
        for large m).
    """

    numeric: NumericSystem
    hidden: list
    residual: Callable
    H: Callable
    Hz: Callable


def constraint_checks(compiled) -> _Checks:
    """The constraint checks of ``compiled`` (:class:`_Checks`: its hidden constraint levels with
    their residual, and the determining equations with their z Jacobian), generated once and kept
    with it (every solve that passes initial values would otherwise generate them again)."""

    def build() -> _Checks:
        numeric = compiled.numeric
        hidden = hidden_constraints(compiled.constraints)
        determining = [c.determining for c in compiled.constraints]
        return _Checks(
            numeric=numeric,
            hidden=hidden,
            residual=numeric.batch_function([e for _, _, e in hidden]),
            H=numeric.batch_function(determining),
            Hz=numeric.newton_jacobian(determining, compiled.algebraics),
        )

    return compiled.cached("initial_states", build)


def _batch(compiled, arguments) -> tuple[dict, list]:
    """``(sizes of the batched arguments, one array (B, k) per argument)`` from
    ``(argument, value, names, defaults)`` rows: checked, finite, broadcast to one batch size."""
    sizes, blocks = {}, []
    for arg, value, names, defaults in arguments:
        size, block = columns(compiled, value, names, defaults, arg)
        _finite(block, names, arg)
        blocks.append(block)
        if size is not None:
            sizes[arg] = size
    if len(set(sizes.values())) > 1:
        raise ShapeError("the batch sizes differ: " + ", ".join(f"{k} has {v} samples" for k, v in sizes.items()))
    batch = next(iter(sizes.values()), 1)
    return sizes, [np.ascontiguousarray(np.broadcast_to(b, (batch, b.shape[1]))) for b in blocks]


def initial_states(compiled, y0=None, z0=None, parameters=None) -> InitialStates:
    """Resolve, check and complete the initial values of a solve.

    Parameters
    ----------
    compiled : CompiledDAE
    y0 : dict name -> float or array (B,), or array (n,) or (B, n), optional
    z0 : same for the algebraic variables, optional; starting values (and a claim) for Newton
    parameters : dict name -> float or array (B,), or array (k,) or (B, k), optional

    Raises
    ------
    ShapeError, UnknownSymbolError, InvalidValueError
        For malformed input, naming the argument and the expected shape or names.
    InconsistentInitialStateError
        When samples violate a constraint or hidden constraint (the samples are listed).
    InitialisationError, InconsistentAlgebraicValueError
        When Newton fails for the algebraic values, or they disagree with a given ``z0``.
    """
    algebraics = compiled.algebraic_names
    sizes, (Y, Z, P) = _batch(
        compiled,
        (
            ("y0", y0, compiled.state_names, compiled.y0),
            ("z0", z0, algebraics, compiled.z0),
            ("parameters", parameters, compiled.parameter_names, compiled.parameter_values),
        ),
    )
    if y0 is None and z0 is None and parameters is None and _own_values_consistent(compiled, Y, Z, P):
        return InitialStates(y0=Y, z0=Z, p=P, batched=False)

    checks = constraint_checks(compiled)
    t0, hidden = compiled.t0, checks.hidden
    residual, tol, bad = state_violations(compiled, Y, P)
    if bad.any():
        sample, level = np.argwhere(bad)[0]
        name, label, _ = hidden[level]
        raise InconsistentInitialStateError(
            f"initial states of samples {_samples(np.flatnonzero(bad.any(axis=1)))} violate the constraints; "
            f"sample {sample}: {label}: {name} = {residual[sample, level]:.6g} (tolerance {tol[sample]:.1e}). "
            "Give states that satisfy them, or project yours onto them with compiled.consistent(y0=...) (the "
            "nearest such states)"
        )

    if z0 is None:
        return InitialStates(y0=Y, z0=algebraic_values(compiled, t0, Y, P, Z), p=P, batched=bool(sizes))
    # a given z0 that is a root is the user's choice of branch (each sample its own: z**2 = 4 with
    # z0 = [-2, 2] follows both roots); where it is none, the root the model's guess selects (its
    # compiled z0) is the consistent value it disagrees with
    Zc = algebraic_values(compiled, t0, Y, P, np.broadcast_to(compiled.z0, Z.shape), fallback=Z)
    off = (np.abs(Zc - Z) > ALGEBRAIC_TOL * (1 + np.abs(Zc))).any(axis=1)
    if off.any():
        Yo, Zo, Po = Y[off], Z[off], P[off]
        roots = is_root(checks.H(t0, Yo, Zo, Po), checks.Hz(t0, Yo, Zo, Po), Zo)
        if not roots.all():
            sample = int(np.flatnonzero(off)[np.flatnonzero(~roots)[0]])
            j = int(np.argmax(np.abs(Zc[sample] - Z[sample]) > ALGEBRAIC_TOL * (1 + np.abs(Zc[sample]))))
            raise InconsistentAlgebraicValueError(
                f"z0: {algebraics[j]} = {Z[sample, j]:.10g} of sample {sample} disagrees with the consistent "
                f"value {float(Zc[sample, j])!r} (and is no root of the constraints); drop z0 or pass consistent values"
            )
        Zc[off] = algebraic_values(compiled, t0, Yo, Po, Zo)  # (Newton from the given roots: to full precision)
    return InitialStates(y0=Y, z0=Zc, p=P, batched=bool(sizes))


def _own_values_consistent(compiled, Y: np.ndarray, Z: np.ndarray, P: np.ndarray) -> bool:
    """Whether the model's own ``y0`` satisfy its constraints and its ``z0`` is their root at them (kept with
    those values).  A ``dataclasses.replace`` copy at other ``y0`` or parameter values keeps the ``z0`` made
    for the first ones: taken as it was, radau printed z(t0) = 2 beside x(t0) = 0.4 for z = 2 x, and the
    reference locked Min(1, z) to the branch of z = 2 (u = 2.0 for 0.393, "success"); such values go
    the way of values given to :func:`initial_states` (checked, z solved again)."""

    def build() -> bool:
        if not Y.shape[1] and not Z.shape[1]:
            return True
        if state_violations(compiled, Y, P)[2].any():
            return False
        if not Z.shape[1]:
            return True
        checks = constraint_checks(compiled)
        return bool(is_root(checks.H(compiled.t0, Y, Z, P), checks.Hz(compiled.t0, Y, Z, P), Z).all())

    on = (compiled.y0, compiled.z0, compiled.parameter_values, compiled.t0)
    return compiled.cached(("own-values-consistent",), build, on=on)


def algebraic_values(
    compiled, t: float, Y: np.ndarray, P: np.ndarray, Z: np.ndarray, fallback: np.ndarray | None = None
) -> np.ndarray:
    """The algebraic values (B, m) that the states ``Y`` (B, n) determine at time ``t``: one
    batched Newton solve of the determining equations started from ``Z`` (B, m), as at t0, and
    for the samples where that fails, from ``fallback`` (B, m) when given.

    Raises
    ------
    InitialisationError
        Naming the samples where Newton fails.
    """
    checks = constraint_checks(compiled)
    H, Hz = checks.H, checks.Hz
    result = solve_algebraic(lambda Zc: H(t, Y, Zc, P), lambda Zc: Hz(t, Y, Zc, P), Z)
    failed = ~result.converged
    if fallback is not None and failed.any():
        Yf, Pf = Y[failed], P[failed]
        retry = solve_algebraic(lambda Zc: H(t, Yf, Zc, Pf), lambda Zc: Hz(t, Yf, Zc, Pf), fallback[failed])
        x, residual = result.x.copy(), result.residual.copy()
        x[failed], residual[failed] = retry.x, retry.residual
        still = failed.copy()
        still[failed] = ~retry.converged
        result = dataclasses.replace(result, x=x, residual=residual, converged=~still)
        failed = still
    if failed.any():
        sample = int(np.flatnonzero(failed)[0])
        raise InitialisationError(
            f"Newton for the algebraic values at t = {t:.6g} failed for samples {_samples(np.flatnonzero(failed))}; "
            f"sample {sample} keeps residuals {result.residual[sample]} of {[c.label for c in compiled.constraints]} "
            f"after {result.iterations} steps; pass starting values with z0=... (or m.guess), or check that the "
            "constraints have a real root at these states"
        )
    return result.x


def consistent_states(compiled, y0=None, parameters=None, fix=()) -> dict:
    """:meth:`CompiledDAE.consistent`: ``y0`` (as ``solve`` takes it) projected onto every z-free
    constraint level, by name, one float per state or an array (B,) for a batch; the states named
    in ``fix`` keep their values and the others change the least."""
    names = compiled.state_names
    if isinstance(fix, str):
        fix = (fix,)
    fix = tuple(fix)
    unknown = [f for f in fix if f not in names]
    if unknown:
        listed = ", ".join(repr(u) for u in unknown)
        raise UnknownSymbolError(
            f"consistent(fix=...): {listed} {'is' if len(unknown) == 1 else 'are'} not a state of model "
            f"'{compiled.name}'; the states are {list(names)}"
        )
    sizes, (Y, P) = _batch(
        compiled,
        (
            ("y0", y0, names, compiled.y0),
            ("parameters", parameters, compiled.parameter_names, compiled.parameter_values),
        ),
    )
    free = np.array([name not in fix for name in names])
    checks = constraint_checks(compiled)
    if fix and not free.any():
        residual, tol, bad = state_violations(compiled, Y, P)
        if bad.any():
            sample, level = np.argwhere(bad)[0]
            name, label, _ = checks.hidden[level]
            raise FixedStateError(
                f"consistent(fix=...) holds every state ({', '.join(names)}), so nothing can move, but sample "
                f"{sample} violates {label}: {name} = {residual[sample, level]:.6g} (tolerance {tol[sample]:.1e}); "
                "leave at least one state out of fix"
            )
    projected = project_states(compiled, Y, P, free=free)
    residual, tol, bad = state_violations(compiled, projected, P)
    if bad.any():
        sample, level = np.argwhere(bad)[0]
        name, label, _ = checks.hidden[level]
        if fix:
            raise FixedStateError(
                f"consistent(fix=...): with {', '.join(fix)} held at sample {sample}'s values, no values of the other "
                f"states ({', '.join(n for n, f in zip(names, free, strict=True) if f)}) satisfy {label}: {name} = "
                f"{residual[sample, level]:.6g} after the projection (tolerance {tol[sample]:.1e}); fix fewer "
                "states, or values that the constraints allow"
            )
        raise InconsistentInitialStateError(
            f"consistent(): no state near sample {sample}'s satisfies {label}: {name} = "
            f"{residual[sample, level]:.6g} after the projection (tolerance {tol[sample]:.1e}); the constraints "
            "may have no real solution near these states"
        )
    if not sizes:
        return {name: float(projected[0, i]) for i, name in enumerate(names)}
    return {name: projected[:, i].copy() for i, name in enumerate(names)}


def state_violations(compiled, Y: np.ndarray, P: np.ndarray):
    """``(residual (B, L), tolerance (B,), violated (B, L))`` of the states ``Y`` (B, n) on every
    z-free constraint level of ``compiled`` at its t0 (:func:`daemodel.compiling.init.violations`)."""
    Z = np.zeros((len(Y), len(compiled.algebraics)))  # (the z-free levels do not read it)
    residual = constraint_checks(compiled).residual(compiled.t0, Y, Z, P)
    return (residual, *violations(residual, Y))


def project_states(compiled, Y: np.ndarray, P: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """The nearest states to the rows of ``Y`` (B, n) that satisfy every z-free constraint level
    (:func:`daemodel.compiling.init.project`; ``free`` (n,) the states allowed to move, default all)."""
    checks = constraint_checks(compiled)
    exprs = [e for _, _, e in checks.hidden]
    if not exprs:
        return np.array(Y, dtype=float)
    jacobian = compiled.cached(
        "initial_states.projection", lambda: checks.numeric.batch_jacobian(exprs, compiled.states)
    )
    Z = np.zeros((len(Y), len(compiled.algebraics)))
    t0 = compiled.t0
    return project(Y, lambda y: checks.residual(t0, y, Z, P), lambda y: jacobian(t0, y, Z, P), free)


def branch_check_functions(compiled):
    """The nonzeros of ``H_z`` that :func:`check_branch` reads, ``(rows, cols, values(t, Y, Z, P))``,
    generated once per model (a solve makes them in its setup: generated at the check, after the
    integration, they were 50-170 ms of the first solve's clock), and kept with the model (the numeric
    system's own cache hashes every expression per look-up: 80 ms a time at 10^5 unknowns)."""

    def build():
        determining = [c.determining for c in compiled.constraints]
        return compiled.numeric.batch_jacobian_entries(determining, compiled.algebraics)

    return compiled.cached("branch-check-functions", build, on=(compiled.constraints, compiled.algebraics))


def check_branch(method: str, compiled, times, values: np.ndarray, P: np.ndarray, signs=None) -> None:
    """Refuse a solution whose algebraic variables leave the branch of roots they start on.

    Between two output times of one sample, ``det H_z`` (the determining equations' Jacobian in z)
    keeps its sign along a branch of roots; a change means a singular ``H_z`` in between, where the
    branch folds or meets another and the constraints no longer determine z: the values after it
    belong to no continuation of the initial root.  The check every method's solution passes
    (:func:`daemodel.backends.base.make_solution`); a jump between two roots with the same sign of
    ``det H_z`` is caught only where the method checks its own Newton (the reference does).

    Parameters
    ----------
    method : str
    compiled : CompiledDAE
    times : ndarray, shape (T,)
    values : ndarray, shape (B, T, n + m)
    P : ndarray, shape (B, k)
    signs : ndarray, shape (B, T), optional
        ``sign(det H_z)`` at ``values`` where the method knows it (radau's solve at the outputs reads it off
        its QR of ``H_z``: :class:`~daemodel.compiling.algebraic.Resolved`), NaN where not: only those are
        evaluated here.

    Raises
    ------
    BranchError
        Naming the method, the sample, the two output times and z on either side.
    """
    m, n = len(compiled.algebraics), len(compiled.states)
    B, T = values.shape[:2]
    if m == 0 or T < 2:
        return
    sign = np.empty(B * T) if signs is None else np.array(signs, dtype=float).reshape(B * T)
    unknown = None if signs is None else np.flatnonzero(np.isnan(sign))  # (None: every one)
    if unknown is None or unknown.size:
        rows = np.asarray(values, dtype=float).reshape(B * T, n + m)
        T_all = np.asarray(times, dtype=float)
        T_all, P_all = (T_all if B == 1 else np.tile(T_all, B)), np.repeat(P, T, axis=0)
        if unknown is not None:
            rows, T_all, P_all = rows[unknown], T_all[unknown], P_all[unknown]
        read = sign if unknown is None else np.empty(len(unknown))
        at, to, entries = branch_check_functions(compiled)
        chunk = max(1, BRANCH_CHECK_BYTES // (8 * max(len(at), 1)))  # (rows per evaluation of H_z's nonzeros)
        with np.errstate(all="ignore"):
            for a in range(0, len(read), chunk):
                b = slice(a, a + chunk)
                # (a transposed view of the values, not its C-ordered copy: 4.4 MB at 10^5 unknowns of reaction-
                # diffusion, a cold solve's peak with the factors it holds then, 2.25 -> 2.13 times their bytes)
                nonzeros = entries(T_all[b], rows[b, :n], rows[b, n:], P_all[b], contiguous=False)
                read[b] = determinant_signs(at, to, nonzeros, m)
        if unknown is not None:
            sign[unknown] = read
    sign = sign.reshape(B, T)
    changed = sign[:, 1:] * sign[:, :1] < 0  # (signs -1, 0, +1: opposite and both nonzero, in two operations)
    if not changed.any():
        return
    sample, k = np.argwhere(changed)[0]
    names = compiled.algebraic_names
    z0, z1 = values[sample, k, n:], values[sample, k + 1, n:]
    shown = np.arange(m)  # (beyond LISTED_BRANCH_VALUES: those that move most, the fold's, in their order)
    if m > LISTED_BRANCH_VALUES:
        shown = np.sort(np.argsort(-np.nan_to_num(np.abs(z1 - z0), nan=np.inf), kind="stable")[:LISTED_BRANCH_VALUES])
    more = f", and {m - len(shown):,} more" if m > len(shown) else ""
    before = ", ".join(f"{names[i]} = {z0[i]:.6g}" for i in shown) + more
    after = ", ".join(f"{names[i]} = {z1[i]:.6g}" for i in shown) + more
    raise BranchError(
        f"{method}: the algebraic variables leave the branch of roots chosen at t0 between t = {times[k]:.8g} "
        f"({before}) and t = {times[k + 1]:.8g} ({after}) (sample {sample} of '{compiled.name}'): det(dH/dz) "
        "changes sign there, so dH/dz is singular in between: the branch turns back (a fold) or meets another "
        "one, and the constraints do not determine z past it. End t_span before this time, or change the "
        "constraints so that their root stays isolated"
    )
