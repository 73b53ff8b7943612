"""``Model``: the declarations and ``compile``: validate -> eliminate aliases -> derivative chains -> prune -> match
-> initialise -> numeric rank check -> :class:`CompiledDAE`."""

from __future__ import annotations

import dataclasses

import numpy as np
import sympy as sp

from daemodel.compiling.compiled import CompiledDAE
from daemodel.compiling.init import NumericSystem, initialise
from daemodel.compiling.prune import eliminate_aliases, needed
from daemodel.compiling.structure import Differentiator, derivative_chain, match
from daemodel.declaring.arrays import compact_listing, element_name, split_element
from daemodel.declaring.events import Event
from daemodel.declaring.functions import check_supported
from daemodel.declaring.model import Declaration
from daemodel.declaring.stencils import paused_collection
from daemodel.errors import (
    InvalidValueError,
    MissingInitialValueError,
    MissingODEError,
    MissingParameterValueError,
    ModelError,
    UnbalancedSystemError,
    UnknownOutputError,
)

# Outputs an unknown-output error names (a list of 10^5 wrong names is not repeated whole), and the characters
# of each it shows (a name of a million characters neither).
OUTPUTS_NAMED = 10
NAME_SHOWN = 80


def short_repr(value) -> str:
    """``repr(value)``, cut to :data:`NAME_SHOWN` characters with the length said."""
    text = repr(value)
    return text if len(text) <= NAME_SHOWN else f"{text[:NAME_SHOWN]}... ({len(text):,} characters)"


def output_name(output, known: set, arrays: dict):
    """The name ``compile(outputs=...)`` reads ``output`` as: a symbol's name, an element's name as
    ``sol[...]`` reads it (``u[ 3 ]``, ``u[03]``: ``u[3]``; an index out of range is an
    :class:`UnknownOutputError` naming the array's shape), else ``output`` itself (checked after)."""
    if isinstance(output, sp.Symbol):
        return output.name
    if isinstance(output, str) and output not in known and "[" in output:
        parts = split_element(output)
        if parts is not None and parts[0] in arrays:
            return element_name(*parts, arrays[parts[0]][1], "compile(outputs=...)", UnknownOutputError)
    return output


def with_events(model, compiled):
    """``compiled`` with the events of ``model`` (a Declaration, or what it declared: a
    :class:`~daemodel.declaring.model.Declared`) on its symbols (aliases substituted)."""
    declared = model.declared() if isinstance(model, Declaration) else model
    if not declared.events:
        return compiled
    symbols = declared.symbols()
    aliases = {symbols[name]: expr for name, expr, _ in compiled.aliases if name in symbols}
    known = {compiled.t, *compiled.states, *compiled.algebraics, *compiled.parameters}
    index = {name: i for i, name in enumerate(compiled.state_names)}
    events = []
    for name, when, direction, resets, terminal in declared.events:
        exprs = [when.xreplace(aliases)] + [value.xreplace(aliases) for _, value in resets]
        missing = sorted({s.name for e in exprs for s in e.free_symbols if s not in known})
        targets = [target for target, _ in resets if target not in index]
        if missing or targets:
            raise UnknownOutputError(
                f"event '{name}' needs {', '.join(repr(m) for m in (*missing, *targets))}, which the requested "
                "outputs pruned away; add them to outputs"
            )
        reset = tuple((index[target], expr) for (target, _), expr in zip(resets, exprs[1:], strict=True))
        events.append(Event(name, exprs[0], direction, reset, terminal))
    return dataclasses.replace(compiled, events=tuple(events))


def _names(symbols) -> str:
    return ", ".join(f"'{s.name}'" for s in symbols)


def _validate(model) -> None:
    """Refuse a declaration that is no complete semi-explicit DAE (``model``: a Declared)."""
    if not model.states:
        raise MissingODEError(
            f"model '{model.name}' declares no differential variable; a DAE needs at least one state "
            "with an ODE (declare it with m.states(...) and m.ode(...))"
        )
    missing = [s for name, s in model.states.items() if name not in model.odes]
    if missing:
        raise MissingODEError(
            f"differential variable(s) {_names(missing)} of model '{model.name}' have no ODE; "
            "declare one with m.ode(<state>, <rhs>) or declare the variable as algebraic"
        )
    n_z, n_g = len(model.algebraics), len(model.constraints)
    if n_z != n_g:
        raise UnbalancedSystemError(
            f"model '{model.name}' has {n_z} algebraic variable(s) ({_names(model.algebraics.values()) or 'none'}) "
            f"but {n_g} constraint(s) ({', '.join(repr(c.name) for c in model.constraints) or 'none'}); "
            "a semi-explicit DAE needs exactly one constraint per algebraic variable"
        )
    no_value = [name for name, v in model.parameter_values.items() if v is None]
    if no_value:
        raise MissingParameterValueError(
            f"parameter(s) {', '.join(repr(n) for n in no_value)} of model '{model.name}' have no "
            "value; give one with m.parameter(name, value) or m.set_parameters(name=value)"
        )
    for eq in [*model.odes.values(), *model.constraints]:
        check_supported(eq.expr, f"model '{model.name}', {eq.label}")


def as_compiled(model, caller: str = "solve()") -> CompiledDAE:
    """A Model compiled with all outputs, or a CompiledDAE as it is; a :class:`ModelError` naming
    ``caller`` for anything else."""
    if isinstance(model, Model):
        model = model.compile()
    if not isinstance(model, CompiledDAE):
        raise ModelError(f"{caller} needs a Model or a CompiledDAE; got {type(model).__name__}")
    return model


def compile_model(model, outputs=None, repair: bool = False) -> CompiledDAE:
    """Compile a :class:`~daemodel.compiling.compiler.Model`; see ``Model.compile`` for the parameters.

    Python's garbage collector is paused meanwhile (as while declaring by stencils): its full
    collections walk every expression alive, ~1 of 7.5 s of CPU at 10^5 unknowns."""
    with paused_collection():
        return _compile(model, outputs, repair)


def _compile(model, outputs, repair: bool) -> CompiledDAE:
    if not isinstance(repair, bool):
        raise InvalidValueError(f"compile(repair=...) must be True or False; got {repair!r}")
    model = model.declared()
    _validate(model)
    states = list(model.states.values())
    parameters = list(model.parameters.values())
    rhs = {s: model.odes[s.name].expr for s in states}
    symbols = {*states, *model.algebraics.values(), *parameters, model.t}
    # derivatives and free symbols shared by every step below, from those the declaration found
    calculus = Differentiator(model.free_symbols)
    equations, algebraics, aliases = eliminate_aliases(
        rhs, model.constraints, list(model.algebraics.values()), symbols, calculus
    )
    algebraic_set = frozenset(algebraics)  # (made once: each chain asks which of them occur)
    constraints = [derivative_chain(e.name, e.number, e.expr, model.t, rhs, algebraic_set, calculus) for e in equations]
    alias_exprs = {name: expr for name, expr, _ in aliases}

    known = [*(s.name for s in states), *model.algebraics]
    # the parameters the events read are used (their variables are the outputs' choice: Model.event names
    # those the requested outputs prune away)
    event_exprs = [e for _, when, _, resets, _ in model.events for e in (when, *(value for _, value in resets))]
    arrays = {name: entry for name, entry in model.arrays.items() if entry[0] != "parameters"}

    def elements(name: str) -> list[str]:
        return [s.name for s in arrays[name][2].flat]

    if outputs is None:
        keep = set(known)
    else:
        try:
            if isinstance(outputs, np.ndarray):  # (an array of names or of the symbols m.states returned)
                outputs = list(outputs.flat)
            outputs = [outputs] if isinstance(outputs, str | sp.Symbol) else list(outputs)
        except TypeError:
            raise UnknownOutputError(
                f"compile(outputs=...) must be a variable name or a list of them; got {type(outputs).__name__}"
            ) from None
        if not outputs:
            raise UnknownOutputError(
                f"compile(outputs=[]) asks for nothing; name the variables you want (of {compact_listing(known)}) "
                "or leave outputs=None for all"
            )
        known_set = set(known)
        # (a symbol stands for its name, an element's name is read as sol[...] reads it: u[ 3 ] and u[03] are
        # u[3], u[5] of 5 elements is out of range, saying so; an array's name stands for its elements)
        outputs = [output_name(o, known_set, arrays) for o in outputs]
        outputs = [e for o in outputs for e in (elements(o) if isinstance(o, str) and o in arrays else (o,))]
        unknown = [o for o in outputs if not isinstance(o, str) or o not in known_set]
        if unknown:
            listed = ", ".join(short_repr(u) for u in unknown[:OUTPUTS_NAMED])
            more = f" and {len(unknown) - OUTPUTS_NAMED:,} more" if len(unknown) > OUTPUTS_NAMED else ""
            raise UnknownOutputError(
                f"compile(outputs=...): {listed}{more} not a variable of model '{model.name}'; variables: "
                f"{compact_listing(known)}"
            )
        keep = needed(outputs, rhs, constraints, algebraics, alias_exprs, calculus)
    algebraic_names = {z.name for z in algebraics}
    kept_constraints = [
        c
        for c in constraints
        if any(s.name in keep for s in calculus.free_symbols(c.determining) if s.name in algebraic_names)
    ]
    kept_states = [s for s in states if s.name in keep]
    kept_algebraics = [z for z in algebraics if z.name in keep]
    kept_aliases = [a for a in aliases if a[0] in keep]
    used = set().union(
        *(calculus.free_symbols(rhs[s]) for s in kept_states),
        *(calculus.free_symbols(e) for c in kept_constraints for e in c.chain),
        *(calculus.free_symbols(e) for _, e, _ in kept_aliases),
        *(e.free_symbols for e in event_exprs),
    )
    kept_parameters = [p for p in parameters if p in used]
    # names, not symbols: a membership test on a list of symbols compares them one by one
    kept = {s.name for s in [*kept_states, *kept_algebraics, *kept_parameters]}
    kept_constraint_names = {c.name for c in kept_constraints}
    kept_alias_names = {a[0] for a in kept_aliases}
    dropped = {
        "differential variables": tuple(s.name for s in states if s.name not in kept),
        "algebraic variables": tuple(z.name for z in algebraics if z.name not in kept),
        "constraints": tuple(c.name for c in constraints if c.name not in kept_constraint_names),
        "aliases": tuple(a[0] for a in aliases if a[0] not in kept_alias_names),
        "parameters": tuple(p.name for p in parameters if p.name not in kept),
    }

    missing = [s for s in kept_states if s.name not in model.initial]
    if missing:
        raise MissingInitialValueError(
            f"differential variable(s) {_names(missing)} of model '{model.name}' have no initial "
            "value; give them with m.initial(name=value)"
        )
    owner = match(kept_constraints, kept_algebraics, calculus)
    numeric = NumericSystem(
        model.t, tuple(kept_states), tuple(kept_algebraics), tuple(kept_parameters), calculus=calculus
    )
    p = np.array([model.parameter_values[q.name] for q in kept_parameters], dtype=float)
    values = initialise(
        numeric,
        kept_constraints,
        [(n, e) for n, e, _ in kept_aliases],
        model.t0,
        model.initial,
        p,
        repair,
        guesses=model.guess,
    )

    invariants = tuple((c.level_name(k), c.chain[k]) for c in kept_constraints for k in range(max(1, c.index - 1)))
    compiled = CompiledDAE(
        name=model.name,
        t=model.t,
        t0=model.t0,
        states=tuple(kept_states),
        algebraics=tuple(kept_algebraics),
        parameters=tuple(kept_parameters),
        parameter_values=p,
        rhs=tuple(rhs[s] for s in kept_states),
        ode_numbers=tuple(model.odes[s.name].number for s in kept_states),
        constraints=tuple(kept_constraints),
        determined_by=tuple(owner),
        aliases=tuple((n, e, q.label) for n, e, q in kept_aliases),
        invariants=invariants,
        y0=values.y0,
        z0=values.z0,
        notes=values.notes,
        dropped=dropped,
        arrays={name: shape for name, (_, shape, _) in arrays.items()},
    )
    compiled._cache["numeric"] = numeric  # (the functions the initialisation made, and its derivatives, serve on)
    return with_events(model, compiled)


class Model(Declaration):
    """A semi-explicit DAE declared by name.

    Parameters
    ----------
    name : str
        Shown in reports and used in result file names: letters, digits, ``_``, ``-`` and ``.``,
        starting with a letter, at most 64 characters.

    Attributes
    ----------
    t : sympy.Symbol
        Time, for equations that depend on it: ``m.ode(x, -x + sp.sin(m.t))``, or ``"t"`` in a
        string (``m.ode(x, "-x + sin(t)")``).  It cannot be declared as a variable.

    Examples
    --------
    >>> import daemodel as dm
    >>> m = dm.Model("decay")
    >>> (x,) = m.states("x")
    >>> (w,) = m.algebraics("w")
    >>> m.ode(x, -w)
    >>> m.constraint(w - 2 * x, name="rate")
    >>> m.initial(x=1.0)
    >>> m.compile().z0
    array([2.])
    """

    def compile(self, outputs=None, repair: bool = False):
        """Check the structure, initialise consistently, prune and return a ``CompiledDAE``.

        Parameters
        ----------
        outputs : list of str, optional
            Variable names the user wants (an array's name stands for all its elements, ``"u[3]"``
            for one, read as ``sol["u[3]"]`` reads it), or the symbols ``m.states`` returned (an
            array of them too); only what they depend on through the coupled system is kept.
            ``None`` keeps everything.
        repair : bool
            Project an inconsistent initial state onto the constraint manifold (least change)
            and replace disagreeing algebraic values, reporting both, instead of raising.
        """
        # the same declarations and arguments give the same (frozen) CompiledDAE: a Model passed to
        # dm.solve again is not recompiled, and the compiled model keeps its generated code
        if outputs is not None and not (isinstance(outputs, list | tuple) and all(isinstance(o, str) for o in outputs)):
            return compile_model(self, outputs=outputs, repair=repair)  # (it names the mistake)
        key = (None if outputs is None else tuple(outputs), repair, self._fingerprint())
        if self._compiled is None or self._compiled[0] != key:
            self._compiled = (key, compile_model(self, outputs=outputs, repair=repair))
        return self._compiled[1]
