"""The plant state a simulator can go on with (no ROS).

A plant state that is no longer finite (:func:`advance_checked`) ends the run as INCOMPLETE with
the agents named; it is never recorded, so no NaN reaches summary.json. What the simulator accepts
from the agents before it integrates anything is the wrench message's check
(:mod:`formation_msgs_py.wrench_checks`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from formation_sim.core.simulation import Simulation


def advance_checked(sim: Simulation, u: np.ndarray) -> str:
    """``sim.advance(u)`` (``u``: the agents' body wrenches (N,6) [N, N·m]); "" when the new plant
    state is finite, else why the run cannot go on, naming the agents (never raises on overflow)."""
    ids = sim.agent_ids
    try:
        sim.advance(u)
    except (ValueError, OverflowError, FloatingPointError, ZeroDivisionError) as exc:
        speed = np.abs(sim.state.v).max(axis=1)
        worst = ids[int(np.argmax(speed))]
        return f"t={sim.t:.6f} s: integration failed ({exc}); fastest agent {worst} (|v| up to {speed.max():.3g})"
    s = sim.state
    with np.errstate(over="ignore", invalid="ignore"):  # a huge finite state may overflow a sum: looked at below
        total = s.p.sum() + s.R.sum() + s.v.sum()
    if math.isfinite(total):  # finite sums have finite terms: the usual case, ~5 µs
        return ""
    bad = non_finite_agents(ids, s.p, s.R, s.v)
    return f"t={sim.t:.6f} s: non-finite plant state of agent(s) {', '.join(bad)}" if bad else ""


def non_finite_agents(agent_ids: Sequence[str], p: np.ndarray, R: np.ndarray, v: np.ndarray) -> list[str]:
    """The agents whose position (N,3), attitude (N,3,3) or twist (N,6) is not finite."""
    ok = np.isfinite(p).all(axis=1) & np.isfinite(R).all(axis=(1, 2)) & np.isfinite(v).all(axis=1)
    return [a for a, good in zip(agent_ids, ok.tolist()) if not good]
