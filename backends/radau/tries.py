"""An attempt's tries, written once over a namespace (:mod:`.formulas`): where the first try fails,
again with a fresh Jacobian where the kept one may be stale, then from the start value, and where all
fail, the check that z stays determined over the step.

Three callers make them, each with its side (:class:`AbstractTriesSide`: what a try, a refresh, a
check is there): :meth:`.step.Stepper.attempt` on the general path (each try
:meth:`.newton.Newton.simplified`), :meth:`.step.Stepper.compiled_attempt` (each try one compiled
call), both on Python values (:data:`.formulas.SCALAR`: each condition a Python branch), and
:func:`.loop.run_function`, which builds them into its casadi graph (:data:`.formulas.CASADI`: each
conditional try a casadi switch that runs only the branch taken).  The order and the conditions are
here.
"""

from __future__ import annotations

import abc
from typing import NamedTuple


class AbstractTriesSide(abc.ABC):
    """What one side (Python values, or casadi symbols) makes of the tries' pieces.

    ``matrices``: what a try runs on (the Jacobian's factored systems, and whatever the side needs
    with them); ``guess``: a start guess; ``result``: a try's outcome.  On casadi symbols each is an
    expression or a tuple of them, passed into the switches whole (:meth:`.formulas.CasadiOps.branch`:
    a branch reads nothing else).
    """

    @abc.abstractmethod
    def attempt(self, matrices, guess):
        """One try from ``guess`` on ``matrices``: its result."""

    @abc.abstractmethod
    def failed(self, result):
        """Whether the try failed (any outcome but convergence)."""

    @abc.abstractmethod
    def evaluations(self, result):
        """The residual evaluations the try made."""

    @abc.abstractmethod
    def kept(self):
        """Whether the Jacobian, after the first try, was kept from an earlier step (it may be stale)."""

    @abc.abstractmethod
    def refresh(self, matrices):
        """The matrices of a fresh Jacobian at the step's start."""

    @abc.abstractmethod
    def usable(self, matrices):
        """Whether the factored systems can serve (else the attempt goes to the general path)."""

    @abc.abstractmethod
    def check_stages(self, matrices):
        """Whether the algebraic variables' iteration matrix changes sign over the step's stages, from
        the last fresh Jacobian's (z stops being determined; the Python side raises there)."""


class Tries(NamedTuple):
    """What :func:`attempt_tries` found."""

    result: object  # the last try's
    matrices: object  # those it ran on (refreshed where the Jacobian was stale)
    stale: object  # the first try failed on a kept Jacobian: it was refreshed
    usable: object  # the refreshed matrices can serve (without a refresh: True)
    retries: object  # the tries that failed
    evaluations: object  # the residual evaluations of all tries
    newton_failed: object  # every try failed with finite values (the controller halves h)
    stage_flip: object  # the stages' check (check_stages; only where Newton failed)


def attempt_tries(xp, side: AbstractTriesSide, matrices, guess, start, extrapolated) -> Tries:
    """An attempt's tries, in their order:

    1. from ``guess`` (the last step's polynomial, or a given guess: ``extrapolated``; else the
       start value) on ``matrices``;
    2. where it failed on a Jacobian kept from an earlier step (:meth:`~AbstractTriesSide.kept`),
       which may be stale (Newton contracts more slowly with it): again with a fresh one, where its
       systems can serve;
    3. where that failed too (or was not tried) and the guess was ``extrapolated``: from the start
       value ``start`` (the extrapolation can be far off: a fast transient, a degree-2s-1
       polynomial taken past its step);
    4. where every try failed (the controller then shrinks h), the last on finite values or not: the
       check that z stays determined over the step, which the error estimate alone would step over.
       Values that turned non-finite fail the attempt as a diverging Newton does: the general path
       (:class:`.step.GeneralTries`) fails them so, and shrinks h, and the compiled sides now do the
       same in place of handing the attempt to it (Akzo Nobel at rtol 1e-4: one extrapolated guess
       under a sqrt cost 0.65 ms of its 1.5 ms on the general path); the general path names them
       where h underflows (:meth:`.control.Radau5Controller.run`).

    Matrices that cannot serve (``usable`` False) end the tries: the attempt goes to the general path.
    """
    first = side.attempt(matrices, guess)
    stale = xp.and_(side.failed(first), side.kept())

    def attempt(m, g, r):
        return side.attempt(m, g)

    def kept_result(m, g, r):
        return r

    def fresh(m, g, r):
        m = side.refresh(m)
        return m, xp.branch("usable", side.usable(m), attempt, kept_result, m, g, r)

    matrices, result = xp.branch("stale", stale, fresh, lambda m, g, r: (m, r), matrices, guess, first)
    usable = xp.cond(stale, lambda: side.usable(matrices), lambda: True)
    second = xp.and_(stale, usable)
    again = xp.and_(xp.and_(side.failed(result), extrapolated), usable)
    retried = xp.branch("from_start", again, attempt, kept_result, matrices, start, result)
    newton_failed = xp.and_(side.failed(retried), usable)
    stage_flip = xp.branch("determined", newton_failed, side.check_stages, lambda m: False, matrices)
    retries = side.failed(first) + xp.and_(second, side.failed(result)) + xp.and_(again, side.failed(retried))
    evaluations = side.evaluations(first)
    evaluations = evaluations + xp.where(second, side.evaluations(result), 0)
    evaluations = evaluations + xp.where(again, side.evaluations(retried), 0)
    return Tries(retried, matrices, stale, usable, retries, evaluations, newton_failed, stage_flip)
