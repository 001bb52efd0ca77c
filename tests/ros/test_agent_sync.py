"""The agent's step synchroniser (no processes): matching by stamp, gaps, repeats, clock jumps."""

from __future__ import annotations

import math

from ros_helpers import PAPER

from formation_agent.agent_node import StepSynchroniser
from formation_agent.controller import ERROR, AgentController
from formation_msgs_py.spec import agent_view, load_formation, simulator_view
from formation_sim.simulation import Simulation


def _setup(agent: str = "1"):
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    sent: list[tuple[int, tuple[float, ...]]] = []
    sync = StepSynchroniser(AgentController(agent_view(spec, agent)), lambda ns, u: sent.append((ns, tuple(u))))
    v = meas.velocities[spec.agent_ids.index(agent)].tolist()
    return sync, meas.relative_poses[agent], v, sent


def test_computes_when_velocity_and_every_pose_share_a_stamp() -> None:
    """Poses first or velocity first: one wrench, stamped with the step, equal to the core's."""
    sync, poses, v, sent = _setup()
    sync.on_velocity(0, v, now=0.0)
    assert sent == []
    for j, (p, R) in poses.items():
        sync.on_pose(j, 0, p, R, now=0.0)
    ref = AgentController(sync.controller.view).compute(0.0, poses, v)
    assert sent == [(0, ref.wrench)]
    assert sync.last_output.level != ERROR


def test_missing_neighbour_answers_zero_after_pose_wait() -> None:
    """A neighbour out of range: no answer before pose_wait, then a zero wrench with ERROR."""
    sync, poses, v, sent = _setup()
    j, (p, R) = next(iter(poses.items()))
    sync.on_pose(j, 0, p, R, now=0.0)
    sync.on_velocity(0, v, now=0.0)
    assert sent == [] and sync.deadline() == sync.pose_wait
    sync.try_compute(sync.deadline(), final=True)
    assert sent == [(0, (0.0,) * 6)]
    assert sync.last_output.level == ERROR and "no relative pose" in sync.last_output.message
    missing = ", ".join(n for n in sync.neighbours if n != j)
    assert sync.faults.as_dict() == {
        "1": {"missing_pose": {"count": 1, "first_t": 0.0, "last_t": 0.0, "first": missing, "last": missing}}
    }


def test_repeated_stamp_gets_the_same_wrench_and_earlier_stamp_resets() -> None:
    """A re-sent step is answered again identically; a stamp going back resets the controller."""
    sync, poses, v, sent = _setup()
    for ns in (0, 100_000):
        for j, (p, R) in poses.items():
            sync.on_pose(j, ns, p, R, now=0.0)
        sync.on_velocity(ns, v, now=0.0)
    sync.on_velocity(100_000, v, now=0.0)
    assert sent[-1] == sent[-2]
    assert sync.controller.rho_v0 is not None and sync.resets == 0
    sync.on_velocity(0, v, now=0.0)
    assert sync.resets == 1
    for j, (p, R) in poses.items():  # answered again, then back once more: every reset is counted
        sync.on_pose(j, 100_000, p, R, now=0.0)
    sync.on_velocity(100_000, v, now=0.0)
    sync.on_velocity(0, v, now=0.0)
    assert sync.resets == 2
    reset = sync.faults.as_dict()["1"]["reset"]
    assert (reset["count"], reset["first_t"], reset["last_t"]) == (2, 0.0, 0.0)
    assert reset["first"] == "measurements stamped 0.000000 s after 0.000100 s"


def test_non_finite_and_too_old_measurements_give_zero_and_error() -> None:
    """NaN in a measurement, or a velocity far behind /clock: zero wrench, ERROR, never NaN out."""
    sync, poses, v, sent = _setup()
    for j, (p, R) in poses.items():
        sync.on_pose(j, 0, p, R, now=0.0)
    sync.on_velocity(0, [math.nan, *v[1:]], now=0.0)
    assert sent[-1] == (0, (0.0,) * 6) and "non-finite" in sync.last_output.message
    ns = 100_000
    for j, (p, R) in poses.items():
        sync.on_pose(j, ns, p, R, now=0.0)
    sync.on_velocity(ns, v, now=0.0, clock_ns=ns + 2 * sync.measurement_timeout_ns)
    assert sent[-1] == (ns, (0.0,) * 6) and "too old" in sync.last_output.message
    faults = sync.faults.as_dict()["1"]
    assert faults["non_finite_measurement"]["count"] == 1 and faults["non_finite_measurement"]["first_t"] == 0.0
    assert faults["stale_measurement"]["count"] == 1 and faults["stale_measurement"]["first_t"] == 1e-4
