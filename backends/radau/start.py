"""The first step of adaptive steps in one casadi call, on the casadi engine: :func:`.formulas.initial_step`
on casadi symbols, with f at the start and at the probe, built once per model and stages (setup).

On numpy's arrays the same formula took two calls of f and a dozen small array operations, ~35 us of a
pendulum solve's ~330 (:meth:`.control.Radau5Controller.initial_step`).
"""

from __future__ import annotations

from daemodel.backends.radau import formulas
from daemodel.backends.radau.compiled import INLINED_RESIDUAL_MAX_SIZE, lend
from daemodel.backends.radau.formulas import CASADI


def start_function(f, n: int, m: int, P: int, stages: int):
    """casadi function of ``[t0, t1, atol, rtol, y (n), z (m), p (P)]`` to ``[h, f0 (n)]``: the first step
    and f at the start (``f``: the engine's, of ``[t, y, z, p]``)."""
    import casadi

    x = casadi.MX.sym("x", 4 + n + m + P)
    t0, t1, atol, rtol = x[0], x[1], x[2], x[3]
    y, z, p = x[4 : 4 + n], x[4 + n : 4 + n + m], x[4 + n + m :]
    f0 = f(casadi.vertcat(t0, y, z, p))

    def probe(h0):
        return f(casadi.vertcat(t0 + h0, y + h0 * f0, z, p))

    h = formulas.initial_step(CASADI, CASADI.rms, y, f0, probe, atol, rtol, stages, t0, t1)
    return casadi.Function("radau_start", [x], [casadi.vertcat(h, f0)])


class Start:
    """:func:`start_function` of a casadi engine on buffers of its own: ``(t0, t1, y (1, n), z (1, m), atol,
    rtol) -> (h, f0 (1, n))``."""

    @classmethod
    def of(cls, engine) -> Start | None:
        """One for ``engine``, or None above :data:`.compiled.INLINED_RESIDUAL_MAX_SIZE` unknowns, where the
        controller's formula on numpy (two calls of f) costs the same and holds no buffers for the solve's life
        (the casadi function's work and input were 6.8 MB at 10^5 unknowns of reaction-diffusion)."""
        return cls(engine) if engine.D <= INLINED_RESIDUAL_MAX_SIZE else None

    def __init__(self, engine):
        build = lambda: start_function(engine._functions[0], engine.n, engine.m, engine.p.size, engine.s)  # noqa: E731
        self.buffered = lend(engine, engine.compiled.cached(("casadi-radau-start", engine.s), build))
        self.p = engine.p

    def __call__(self, t0, t1, y, z, atol, rtol):
        out = self.buffered.packed((t0, t1, atol, rtol), y[0], z[0], self.p)
        return float(out[0]), out[1:][None]
