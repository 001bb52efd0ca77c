"""The agent's step synchroniser (no processes): matching by stamp, gaps, repeats, time from the measurements."""

from __future__ import annotations

from pathlib import Path

from formation_agent.controller import ERROR, AgentController
from formation_agent.synchroniser import StepSynchroniser
from formation_core.formation import agent_view, simulator_view
from formation_core.spec import load_formation
from formation_sim.core.simulation import Simulation

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


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


def _step(sync, poses, v, ns: int, now: float = 0.0) -> None:
    """One genuine step: every neighbour's pose, then the velocity."""
    for j, (p, R) in poses.items():
        sync.on_pose(j, ns, p, R, now=now)
    sync.on_velocity(ns, v, now=now)


def test_repeated_stamp_gets_the_same_wrench_and_an_earlier_one_is_refused_without_reset() -> None:
    """A re-sent step is answered again identically; a velocity stamped before the agent's time
    (no resend) is refused and counted as past_stamp: no answer, no reset, the time unchanged."""
    sync, poses, v, sent = _setup()
    for ns in (0, 100_000, 200_000):
        _step(sync, poses, v, ns)
    sync.on_velocity(100_000, v, now=0.0)  # a resend of a remembered step, not the newest
    assert sent[-1] == sent[1] and len(sent) == 4
    sync.on_velocity(200_000, v, now=0.0)
    assert sent[-1] == sent[2] and len(sent) == 5
    rho_v0 = sync.controller.rho_v0
    assert rho_v0 is not None
    sync.answers.clear()  # a step long forgotten (beyond the memory of answers)
    sync.on_velocity(100_000, v, now=0.0)
    assert len(sent) == 5 and sync.pending is None
    assert sync.resets == 0 and sync.controller.rho_v0 == rho_v0 and sync.confirmed_ns == 200_000
    past = sync.faults.as_dict()["1"]["refused_past_stamp"]
    assert past["count"] == 1 and past["first"] == "velocity stamped 0.0001 s, before the agent's time 0.0002 s"
    _step(sync, poses, v, 300_000)  # the next step is answered as usual
    assert sent[-1][0] == 300_000 and any(sent[-1][1]) and sync.confirmed_ns == 300_000


def test_forged_velocity_ahead_of_the_genuine_steps_resets_nothing() -> None:
    """A velocity stamped 5 ms ahead (an outsider's, no pose of that stamp ever comes) is answered
    alone with zero after pose_wait and confirms nothing: the genuine steps before its stamp are
    answered as if it had not come, with the controller's wrenches, and nothing is reset."""
    sync, poses, v, sent = _setup()
    _step(sync, poses, v, 0)
    forged = 5_000_000
    sync.on_velocity(forged, v, now=1.0)
    sync.try_compute(sync.deadline(), final=True)
    assert sent[-1] == (forged, (0.0,) * 6) and sync.last_ns == forged and sync.confirmed_ns == 0
    # the genuine steps of the next 5 ms, poses first or velocity first, each a full answer
    ref = AgentController(sync.controller.view)
    ref.compute(0.0, poses, v)
    for k in range(1, 6):
        ns = k * 1_000_000
        if k % 2:
            _step(sync, poses, v, ns, now=2.0)
        else:
            sync.on_velocity(ns, v, now=2.0)
            for j, (p, R) in poses.items():
                sync.on_pose(j, ns, p, R, now=2.0)
        assert sent[-1] == (ns, ref.compute(ns / 1e9, poses, v).wrench), k
    assert sync.resets == 0 and sync.confirmed_ns == 5_000_000 and sync.last_ns == forged
    assert "refused_past_stamp" not in sync.faults.as_dict().get("1", {})


def test_clock_jumping_back_alone_is_counted_and_resets_nothing() -> None:
    """/clock back by 1 s (an outsider's): a clock_jump fault; the genuine steps after it are
    answered normally, and a later velocity of an earlier stamp is still refused (the jump was
    forgotten at the first confirmed step after it)."""
    sync, poses, v, sent = _setup()
    for ns in (2_000_000_000, 2_000_100_000):
        _step(sync, poses, v, ns)
    sync.clock_jumped_back(1_000_100_000, -1_000_000_000)
    _step(sync, poses, v, 2_000_200_000)
    ref = AgentController(sync.controller.view)
    ref.compute(2.0, poses, v)
    assert sent[-1] == (2_000_200_000, ref.compute(2.0002, poses, v).wrench)
    assert sync.rewind_ns is None and sync.resets == 0
    sync.answers.clear()
    _step(sync, poses, v, 1_000_200_000)
    assert sent[-1][0] == 2_000_200_000 and sync.resets == 0
    faults = sync.faults.as_dict()["1"]
    assert faults["clock_jump"]["count"] == 1 and faults["clock_jump"]["first"] == "/clock jumped by -1.000000 s"
    assert faults["refused_past_stamp"]["count"] == 1


def test_time_restarts_when_clock_and_measurements_go_back_together() -> None:
    """A bag replayed in a loop: /clock back to the start, then a step of that time with its poses:
    one reset, and the step is answered as the first one of a fresh controller. A velocity of an
    earlier stamp without any pose after such a jump restarts nothing (refused as past_stamp)."""
    sync, poses, v, sent = _setup()
    for ns in (0, 100_000, 200_000):
        _step(sync, poses, v, ns)
    sync.clock_jumped_back(0, -200_000)
    sync.answers.clear()  # the loop's first step is no longer remembered (a long bag)
    sync.on_velocity(100_000, v, now=1.0)
    sync.try_compute(sync.deadline(), final=True)  # no pose of that stamp: no restart
    assert sync.resets == 0 and len(sent) == 3 and sync.confirmed_ns == 200_000
    _step(sync, poses, v, 0, now=2.0)
    assert sync.resets == 1 and sync.confirmed_ns == 0 and sync.rewind_ns is None
    assert sent[-1] == (0, AgentController(sync.controller.view).compute(0.0, poses, v).wrench)
    reset = sync.faults.as_dict()["1"]["reset"]
    assert reset["first"] == "/clock back to 0.000000 s, measurements at 0.000000 s after 0.000200 s"
    assert sync.faults.as_dict()["1"]["refused_past_stamp"]["count"] == 1


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
