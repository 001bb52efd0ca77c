"""The agent's step synchroniser (no processes): matching by stamp, gaps, repeats, clock jumps."""

from __future__ import annotations

from ros_helpers import PAPER

from formation_agent.agent_node import StepSynchroniser
from formation_agent.controller import ERROR, AgentController
from formation_msgs_py.spec import agent_view, load_formation, simulator_view
from formation_sim.core.simulation import Simulation


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


def test_poses_of_a_later_step_wait_and_those_of_answered_steps_are_forgotten() -> None:
    """Poses that arrive before their velocity wait for it; answering a step forgets its poses and
    any earlier ones; the memory of stamps is bounded when velocities never come."""
    sync, poses, v, sent = _setup()
    for ns in (200_000, 100_000):  # step 200 µs arrives first (the agent lags)
        for j, (p, R) in poses.items():
            sync.on_pose(j, ns, p, R, now=0.0)
    assert sent == [] and sorted(sync.steps) == [100_000, 200_000]
    sync.on_velocity(100_000, v, now=0.0)
    sync.on_velocity(200_000, v, now=0.0)
    assert [ns for ns, _ in sent] == [100_000, 200_000] and sync.steps == {}
    ref = AgentController(sync.controller.view)
    assert sent == [(ns, ref.compute(ns / 1e9, poses, v).wrench) for ns in (100_000, 200_000)]
    j, (p, R) = next(iter(poses.items()))
    for k in range(3, 30):
        sync.on_pose(j, k * 100_000, p, R, now=0.0)
    assert sorted(sync.steps) == [k * 100_000 for k in range(22, 30)]  # the newest 8


def test_resent_step_after_a_missing_pose_is_answered_from_the_resend() -> None:
    """A step answered without a pose (later than pose_wait) and then re-sent is answered again from
    the resend's poses: the wrench the controller gives with every pose (the simulator's witness)."""
    sync, poses, v, sent = _setup()
    (j, (p, R)), *late = poses.items()
    sync.on_pose(j, 0, p, R, now=0.0)
    sync.on_velocity(0, v, now=0.0)
    sync.try_compute(sync.deadline(), final=True)  # the other pose came too late: zero and ERROR
    assert sent == [(0, (0.0,) * 6)]
    for k, (p, R) in poses.items():  # the resend: every pose, then the velocity
        sync.on_pose(k, 0, p, R, now=1.0)
    sync.on_velocity(0, v, now=1.0)
    ref = AgentController(sync.controller.view).compute(0.0, poses, v)
    assert late and sent[-1] == (0, ref.wrench) and any(ref.wrench)
    sync.on_velocity(0, v, now=2.0)  # answered with every pose: a further resend repeats it
    assert sent[-1] == sent[-2] and len(sent) == 3
