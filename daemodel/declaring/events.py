"""An event as the compiled model holds it: a plain record, declared with ``m.event`` (or made for a
switch on a state by :func:`daemodel.compiling.switches.with_state_events`), located and applied in
:mod:`daemodel.solving.events`."""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp


@dataclass(frozen=True)
class Event:
    """A declared event, compiled: ``when`` and the reset as expressions of the compiled model's
    symbols (aliases substituted); ``reset`` as (state index, expression) pairs."""

    name: str
    when: sp.Expr
    direction: int
    reset: tuple
    terminal: bool
    # a switch's own event (with_state_events): ``when`` is its switching function; after it, the
    # branch is the side the flow goes to (both sides tried: neither is a sliding mode), and going
    # straight back is a crossing too (the branch locked for the piece would be wrong)
    strict: bool = False
    # floor/ceiling: the event is the function reaching the integer below or above its value, and the
    # branch the integer part on the side the flow goes to
    integer: bool = False

    def describe(self, state_names) -> str:
        side = {1: "rising", -1: "falling", 0: "either way"}[self.direction]
        what = f"{self.name}: {self.when} crosses 0 ({side})"
        if self.reset:
            what += "; then " + ", ".join(f"{state_names[i]} = {expr}" for i, expr in self.reset)
        return what + ("; ends the solve" if self.terminal else "")
