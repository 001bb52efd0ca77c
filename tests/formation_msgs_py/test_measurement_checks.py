"""Agent input checks (offline): every class of bad message is refused, counted, answered with zero."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from formation_agent.controller import ERROR, AgentController
from formation_agent.synchroniser import StepSynchroniser
from formation_core import rotations
from formation_core.errors import RotationError
from formation_core.formation import agent_view, simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import codec, measurement_checks
from formation_sim.core.simulation import Simulation

NS = 1_000_000_000
GOOD_POSE = (1.0, 2.0, 0.5, 0.0, 0.0, 0.0, 1.0)
MAX_AGE = NS // 10  # the paper preset's measurement_timeout, 0.1 s
PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


def check() -> measurement_checks.InputCheck:
    return measurement_checks.InputCheck(sensing_radius=4.0, max_age_ns=MAX_AGE)


@pytest.mark.parametrize(
    ("values", "kind"),
    [
        ((math.nan, 0, 0, 0, 0, 0, 1), measurement_checks.NON_FINITE),
        ((0, math.inf, 0, 0, 0, 0, 1), measurement_checks.NON_FINITE),
        ((1, 0, 0, 0, 0, 0, math.nan), measurement_checks.NON_FINITE),
        ((1, 0, 0, 0, 0, 0, 0), measurement_checks.BAD_QUATERNION),  # zero quaternion
        ((1, 0, 0, 0, 0, 0, 2), measurement_checks.BAD_QUATERNION),  # (0,0,0,2): once 1e8 N·m
        ((1, 0, 0, 0, 0, 0, 1 + 2e-6), measurement_checks.BAD_QUATERNION),
        ((1e6, 0, 0, 0, 0, 0, 1), measurement_checks.OUT_OF_RANGE),  # once 1.2e8 N
        ((4.5, 0, 0, 0, 0, 0, 1), measurement_checks.OUT_OF_RANGE),  # 1.125 × the 4 m sensing radius
    ],
)
def test_bad_relative_pose_is_refused_and_counted(values, kind) -> None:
    """Non-finite, zero / non-unit quaternion, beyond the sensing radius: refused with its kind."""
    c = check()
    refusal = c.pose("3", 5 * NS, values, clock_ns=5 * NS)
    assert refusal is not None and refusal.kind == kind and "relative pose of 3" in refusal.reason
    assert c.counts == {kind: 1}


def test_plausible_pose_passes_within_the_stated_tolerances() -> None:
    """Unit quaternion to 1e-7 (float32), 4.3 m (within 10 % of 4 m), stamp 0.09 s from /clock: accepted."""
    c = check()
    assert c.pose("3", 5 * NS, GOOD_POSE, clock_ns=5 * NS) is None
    assert c.pose("3", 5 * NS, (4.3, 0, 0, 0, 0, 0, 1 + 1e-7), clock_ns=5 * NS - 90_000_000) is None
    assert c.pose("3", 5 * NS, GOOD_POSE, clock_ns=0) is None  # no /clock yet: stamps not judged
    # measurements may lead the /clock of their step (different topics): 0.5 s is not the future
    assert c.velocity(5 * NS + NS // 2, (0.0,) * 6, clock_ns=5 * NS) is None
    assert not c.counts


@pytest.mark.parametrize(
    ("ns", "clock_ns", "kind"),
    [
        ((2**31 - 1) * NS, 5 * NS, measurement_checks.FUTURE_STAMP),
        (5 * NS + measurement_checks.MAX_LEAD_NS + 1, 5 * NS, measurement_checks.FUTURE_STAMP),
        (5 * NS - MAX_AGE - 1, 5 * NS, measurement_checks.OLD_STAMP),
    ],
)
def test_stamp_from_the_future_or_too_old_is_refused(ns, clock_ns, kind) -> None:
    """A stamp more than 1 s ahead of /clock, or more than measurement_timeout behind it: refused."""
    c = check()
    assert c.pose("3", ns, GOOD_POSE, clock_ns).kind == kind
    assert c.velocity(ns, (0.0,) * 6, clock_ns).kind == kind
    assert c.counts == {kind: 2}


def test_non_finite_velocity_is_refused() -> None:
    c = check()
    assert c.velocity(NS, (0, 0, math.nan, 0, 0, 0), NS).kind == measurement_checks.NON_FINITE
    assert c.velocity(NS, (0, 0, 1e308, 0, 0, 0), NS) is None  # finite: the controller bounds its wrench


def test_zero_quaternion_cannot_crash_the_conversion() -> None:
    """The one conversion of a message quaternion raises RotationError, never ZeroDivisionError."""
    with pytest.raises(RotationError, match="has no rotation"):
        codec.relative_pose_from_values((1, 0, 0, 0, 0, 0, 0))
    with pytest.raises(RotationError):
        rotations.matrix_from_quaternion(math.nan, 0, 0, 1)


def test_refused_measurement_answers_its_step_with_zero_and_error() -> None:
    """The synchroniser answers a step whose pose or velocity was refused: zero wrench, ERROR, the reason."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    sent: list = []
    sync = StepSynchroniser(AgentController(agent_view(spec, "5")), lambda ns, u: sent.append((ns, tuple(u))))
    v = meas.velocities[4].tolist()
    sync.on_velocity(0, v, now=0.0)
    sync.refuse(0, "relative pose of 3: quaternion norm 0 is not 1", now=0.0, neighbour="3")
    assert sent == [(0, (0.0,) * 6)]
    assert sync.last_output.level == ERROR and "quaternion norm 0" in sync.last_output.message
    sync.refuse(1000, "velocity: non-finite value", now=0.0)
    p, R = meas.relative_poses["5"]["3"]
    sync.on_pose("3", 1000, p, R, now=0.0)
    assert sent[-1] == (1000, (0.0,) * 6) and "non-finite" in sync.last_output.message
    # the next good step is computed normally
    sync.on_pose("3", 2000, p, R, now=0.0)
    sync.on_velocity(2000, v, now=0.0)
    assert sent[-1][0] == 2000 and any(x != 0.0 for x in sent[-1][1])


def test_bytes_that_are_no_message_are_refused_and_dropped() -> None:
    c = check()
    refusal = c.malformed("relative pose of 3")
    assert refusal.kind == measurement_checks.MALFORMED and refusal.kind in measurement_checks.DROPPED_KINDS
    assert c.counts == {measurement_checks.MALFORMED: 1}


def test_refused_measurement_of_a_past_step_changes_nothing() -> None:
    """A refused velocity stamped before the last answered step: no answer, no controller reset."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    sent: list = []
    sync = StepSynchroniser(AgentController(agent_view(spec, "5")), lambda ns, u: sent.append((ns, tuple(u))))
    p, R = meas.relative_poses["5"]["3"]
    sync.on_pose("3", 2000, p, R, now=0.0)
    sync.on_velocity(2000, meas.velocities[4].tolist(), now=0.0)
    assert len(sent) == 1
    sync.refuse(1000, "velocity: non-finite value", now=0.0)
    assert len(sent) == 1 and sync.resets == 0 and sync.last_ns == 2000


def test_stamps_are_judged_against_the_agents_confirmed_step_and_clock_only_widens() -> None:
    """The agent's time is its confirmed step: a /clock jumped back 1 s (an outsider's) refuses no
    genuine stamp, a /clock far ahead makes none old; a stamp more than MAX_LEAD ahead of both, or
    more than measurement_timeout behind both, is refused."""
    c = check()
    lead = measurement_checks.MAX_LEAD_NS
    genuine = 5 * NS + 100_000
    assert c.velocity(genuine, (0.0,) * 6, clock_ns=4 * NS, ref_ns=5 * NS) is None  # /clock back 1 s
    assert c.pose("3", genuine, GOOD_POSE, clock_ns=4 * NS, ref_ns=5 * NS) is None
    assert c.velocity(genuine, (0.0,) * 6, clock_ns=60 * NS, ref_ns=5 * NS) is None  # /clock far ahead
    assert c.velocity(genuine, (0.0,) * 6, clock_ns=0, ref_ns=5 * NS) is None  # no /clock: the stream alone
    assert not c.counts
    assert c.velocity(5 * NS + lead + 1, (0.0,) * 6, clock_ns=4 * NS, ref_ns=5 * NS).kind == "future_stamp"
    assert c.velocity(5 * NS + lead + 1, (0.0,) * 6, clock_ns=0, ref_ns=5 * NS).kind == "future_stamp"
    # after a stall the simulator's /clock, ahead of the last confirmed step, lets its stamps in
    assert c.velocity(9 * NS, (0.0,) * 6, clock_ns=9 * NS, ref_ns=5 * NS) is None
    assert c.velocity(4 * NS - MAX_AGE - 1, (0.0,) * 6, clock_ns=4 * NS, ref_ns=5 * NS).kind == "old_stamp"
    # a restart of simulation time (a replay's loop): /clock back to the stamps, which pass
    assert c.velocity(NS // 10, (0.0,) * 6, clock_ns=NS // 10, ref_ns=5 * NS) is None
    assert c.counts == {"future_stamp": 2, "old_stamp": 1}
