"""Textbook problems: Robertson's stiff chemical kinetics as an index-1 DAE, and a bouncing ball
whose impacts are events with a reset (a closed form by parabolas between them)."""

from __future__ import annotations

import numpy as np

from daemodel.problems.problem import Problem

ROBERTSON = Problem(
    name="robertson",
    odes={"y1": "-0.04*y1 + 1e4*y2*y3", "y2": "0.04*y1 - 1e4*y2*y3 - 3e7*y2**2"},
    algebraics=("y3",),
    constraints={"mass": "y1 + y2 + y3 - 1"},
    initial={"y1": 1.0, "y2": 0.0},
    t_span=(0.0, 40.0),
    index=1,
    source="Robertson's chemical kinetics as an index-1 DAE, stiff after t ~ 0.01 (Hairer & Wanner, "
    "Solving ODEs II, VI.1)",
)


# ---- a bouncing ball: events ---------------------------------------------------------------------
#
# Dropped from h = 1 at rest, g = 9.81, restitution e = 0.8: the k-th impact is at
# t_k = sqrt(2/g) (1 + 2 (e + ... + e^(k-1))), the speed after it u_k = e^k sqrt(2 g), and on the flight
# after it h = u_k s - g s^2 / 2, v = u_k - g s with s = t - t_k.  The impacts accumulate at
# sqrt(2/g) (1 + 2 e / (1 - e)) = 4.0637 (Zeno): the span ends before it, after 6 impacts.
# (e is a number in the reset, not a parameter: compile() refuses a parameter used only in an event, issue 40
# item 10)
BALL_G, BALL_E, BALL_IMPACTS = 9.81, 0.8, 12  # (12 impacts: the closed form holds up to t = 3.9)


def _ball_exact() -> tuple[dict, tuple]:
    """The bouncing ball's closed form: Piecewise h and v, each piece ``t < t_k`` (the values at an
    impact are those after it), and the impact times."""
    g, e = BALL_G, BALL_E
    times = [float(np.sqrt(2 / g) * (1 + 2 * sum(e**j for j in range(1, k)))) for k in range(1, BALL_IMPACTS + 1)]
    speeds = [float(e**k * np.sqrt(2 * g)) for k in range(1, BALL_IMPACTS + 1)]
    h = [f"(1 - {g / 2!r}*t**2, t < {times[0]!r})"]
    v = [f"(-{g!r}*t, t < {times[0]!r})"]
    for k, (t_k, u_k) in enumerate(zip(times, speeds, strict=True)):
        until = f"t < {times[k + 1]!r}" if k + 1 < len(times) else "True"
        h.append(f"({u_k!r}*(t - {t_k!r}) - {g / 2!r}*(t - {t_k!r})**2, {until})")
        v.append(f"({u_k!r} - {g!r}*(t - {t_k!r}), {until})")
    exact = {"h": f"Piecewise({', '.join(h)})", "v": f"Piecewise({', '.join(v)})"}
    return exact, tuple(repr(t_k) for t_k in times)


_BALL_EXACT, _BALL_IMPACT_TIMES = _ball_exact()

BOUNCING_BALL = Problem(
    name="bouncing-ball",
    odes={"h": "v", "v": "-g"},
    algebraics=(),
    constraints={},
    parameters={"g": BALL_G},
    initial={"h": 1.0, "v": 0.0},
    t_span=(0.0, 3.0),
    index=0,
    # h = 0.075 first: at h = 0.3 a flight of 0.30 lies inside two outputs and its impacts go unseen (issue 40)
    compare_steps=40,
    exact=_BALL_EXACT,
    exact_events={"floor": _BALL_IMPACT_TIMES},
    events=({"name": "floor", "when": "h", "direction": -1, "reset": {"v": f"-{BALL_E!r}*v"}},),
    source="a ball dropped from h = 1 that bounces with restitution 0.8 (an event with a reset; closed form "
    "by parabolas between the impacts)",
)
