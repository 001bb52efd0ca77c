"""Simulator input checks (offline): every class of bad wrench is refused with its kind and a reason
naming the value (the simulator counts refusals as faults: tests/ros/test_bad_messages.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from formation_sim.core import wrench_checks

NS = 1_000_000_000
RATE = 1000.0  # Hz: steps every 1 ms
GOOD = (1.0, 2.0, 3.0, 0.1, 0.2, 0.3)


def check(lockstep: bool = True) -> wrench_checks.WrenchCheck:
    return wrench_checks.WrenchCheck((100.0, 100.0), (50.0, 50.0), RATE, lockstep=lockstep)


@pytest.mark.parametrize(
    ("u", "kind"),
    [
        ((math.nan, 0, 0, 0, 0, 0), wrench_checks.NON_FINITE),
        ((0, 0, 0, 0, math.inf, 0), wrench_checks.NON_FINITE),
        ((1e308, 0, 0, 0, 0, 0), wrench_checks.OVER_LIMIT),
        ((1e8, 0, 0, 0, 0, 0), wrench_checks.OVER_LIMIT),
        ((60.0, 60.0, 60.0, 0, 0, 0), wrench_checks.OVER_LIMIT),  # 104 N > 100 N
        ((0, 0, 0, 0, 0, 50.001), wrench_checks.OVER_LIMIT),
    ],
)
def test_bad_wrench_value_is_refused(u, kind) -> None:
    """Non-finite or beyond the actuator limits: refused with that kind."""
    c = check()
    refusal = c.check(1, 5 * NS // 1000, u, current_ns=5 * NS // 1000)
    assert refusal is not None and refusal.kind == kind


def test_wrench_at_the_limit_is_accepted() -> None:
    """A controller scaling to exactly its limit (rounding 1e-15) passes; so does a plain wrench."""
    c = check()
    at_limit = (100.0 * (1 + 1e-15), 0, 0, 0, 0, 50.0)
    assert c.check(0, 0, at_limit, current_ns=0) is None
    assert c.check(0, 0, GOOD, current_ns=0) is None


@pytest.mark.parametrize(
    ("ns", "current_ns", "lockstep", "kind"),
    [
        ((2**31 - 1) * NS, 5 * NS, False, wrench_checks.FUTURE_STEP),  # once held for the rest of a realtime run
        ((2**31 - 1) * NS, 5 * NS, True, wrench_checks.FUTURE_STEP),  # once stalled a lockstep run
        (5 * NS + 1_000_000, 5 * NS, True, wrench_checks.FUTURE_STEP),
        (5 * NS - 1_000_000, 5 * NS, True, wrench_checks.PAST_STEP),
        (5 * NS + 1, 6 * NS, False, wrench_checks.UNKNOWN_STEP),
    ],
)
def test_wrench_for_a_step_that_does_not_exist_is_refused(ns, current_ns, lockstep, kind) -> None:
    c = check(lockstep)
    refusal = c.check(0, ns, GOOD, current_ns)
    assert refusal is not None and refusal.kind == kind
    assert kind in wrench_checks.DROPPED_KINDS


def test_realtime_accepts_a_late_answer_lockstep_does_not() -> None:
    """Realtime holds the newest wrench, so an answer to an earlier step is valid; lockstep refuses it."""
    assert check(lockstep=False).check(0, 4 * NS, GOOD, current_ns=5 * NS) is None
    assert check(lockstep=True).check(0, 4 * NS, GOOD, current_ns=5 * NS) == wrench_checks.WrenchRefusal(
        wrench_checks.PAST_STEP, "stamp 4 s is before the current step 5 s"
    )


def test_refusal_reasons_name_the_value() -> None:
    """The reason is what the simulator logs and counts (first and last) for the agent."""
    c = check()
    assert c.check(0, 0, (math.nan,) * 6, current_ns=0) == wrench_checks.WrenchRefusal(
        wrench_checks.NON_FINITE, "non-finite value"
    )
    over = c.check(1, 0, (1e9, 0, 0, 0, 0, 0), current_ns=0)
    assert (
        over is not None
        and over.kind == wrench_checks.OVER_LIMIT
        and "1e+09 N" in over.reason
        and "100 N" in over.reason
    )
    unknown = c.check(0, 5 * NS + 1, GOOD, current_ns=6 * NS)
    assert unknown is not None and "no step of the 1000 Hz grid" in unknown.reason


def test_non_finite_state_names_the_agent() -> None:
    p, R, v = np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 6))
    assert wrench_checks.non_finite_agents(("1", "2", "3"), p, R, v) == []
    v[1, 4] = math.nan
    R[2, 0, 0] = math.inf
    assert wrench_checks.non_finite_agents(("1", "2", "3"), p, R, v) == ["2", "3"]


def test_blown_up_plant_ends_the_run_incomplete_naming_the_agent(tmp_path) -> None:
    """An initial spin of 1e200 rad/s overflows the integrator: INCOMPLETE (exit 4), agent named, strict JSON."""
    import yaml

    from formation_core.verdict import ExitCode
    from formation_sim.cli import headless

    agent = {"radius": 0.5, "sensing_radius": 3.0, "dynamics": {"mass": 1.0, "inertia": [0.1, 0.2, 0.3]}}
    doc = {
        "simulation": {"duration": 0.01, "physics_rate": 1000.0, "control_rate": 1000.0, "rate_check": "warn"},
        "agents": [
            {"id": "a", "position": [0, 0, 0], "angular_velocity": [1e200, 1e200, 0], **agent},
            {"id": "b", "position": [2, 0, 0], **agent},
        ],
        "edges": [{"tail": "a", "head": "b", "distance": 1.5}],
    }
    path = tmp_path / "spin.yaml"
    path.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    assert headless.main([str(path), "--out", str(out), "--no-plots", "--quiet"]) == ExitCode.INCOMPLETE
    summary = json.loads((out / "summary.json").read_text())
    # the compiled plant never raises: the overflow shows as a non-finite state of agent a
    assert "non-finite plant state of agent(s) a" in summary["incomplete_reason"]
    json.dumps(summary, allow_nan=False)


def test_bytes_that_are_no_wrench_are_refused() -> None:
    """Raw bytes on a wrench topic that do not decode: counted as malformed for that agent."""
    import struct

    from formation_msgs_py import codec

    c = check()
    with pytest.raises(struct.error):
        codec.wrench_codec("b").decode(b"\x00\x01\x00\x00garbage")
    assert c.malformed().kind == wrench_checks.MALFORMED and wrench_checks.MALFORMED in wrench_checks.DROPPED_KINDS


class _Sim:
    """What advance_checked needs of a Simulation: advance() moves to the given state."""

    agent_ids = ("1", "2", "3")
    t = 0.001

    def __init__(self, p: np.ndarray, R: np.ndarray, v: np.ndarray) -> None:
        self._next = (p, R, v)

    def advance(self, u: np.ndarray) -> None:
        from formation_sim.core.plant import PlantState

        self.state = PlantState(*self._next)


@pytest.mark.parametrize(
    ("agent", "field", "value", "reason"),
    [
        (None, None, None, ""),
        (1, "v", math.nan, "non-finite plant state of agent(s) 2"),
        (2, "R", -math.inf, "non-finite plant state of agent(s) 3"),
        # finite values whose sum overflows: no agent is non-finite, nothing to report
        (0, "p", 1e308, ""),
    ],
)
def test_advance_checked_names_non_finite_agents_only(agent, field, value, reason) -> None:
    state = {"p": np.zeros((3, 3)), "R": np.tile(np.eye(3), (3, 1, 1)), "v": np.zeros((3, 6))}
    if agent is not None:
        state[field][agent].flat[:2] = value  # two entries: 1e308 + 1e308 overflows the sum
    sim = _Sim(state["p"], state["R"], state["v"])
    got = wrench_checks.advance_checked(sim, np.zeros((3, 6)))
    assert got == (f"t=0.001000 s: {reason}" if reason else "")
