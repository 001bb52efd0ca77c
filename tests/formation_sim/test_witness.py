"""The lockstep witness without ROS (formation_sim.node.witness): a whole paper run through the messages'
bytes, every answer judged; bit for bit for agents on this platform, within the round-off bound otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from formation_agent.controller import AgentController
from formation_agent.synchroniser import StepSynchroniser
from formation_core.formation import FormationSpec, agent_view, simulator_view
from formation_core.numba_kernels import FORM_INTERPRETED, numeric_platform
from formation_core.spec import load_formation
from formation_msgs_py import codec
from formation_msgs_py.measurement_checks import InputCheck
from formation_sim.cli.headless import run_headless
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam
from formation_sim.node.step_messages import StepMessages
from formation_sim.node.stepping import APPLY, WrenchBook, admit
from formation_sim.node.witness import AgentReport, Witness

pytestmark = pytest.mark.numeric

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


class AgentProcess:
    """What an agent process does with a step's bytes (formation_agent.agent_node, without ROS): decode,
    check, synchronise, compute; its answers are collected."""

    def __init__(self, spec: FormationSpec, agent_id: str) -> None:
        view = agent_view(spec, agent_id)
        self.answers: list[tuple[int, tuple[float, ...]]] = []
        self.sync = StepSynchroniser(AgentController(view), lambda ns, u: self.answers.append((ns, tuple(u))))
        self.inputs = InputCheck(view.sensing_radius, round(view.controller.measurement_timeout * codec.NS_PER_S))
        self.pose_codec = codec.relative_pose_codec(agent_id)
        self.twist_codec = codec.twist_codec(agent_id)

    def take(self, poses: list[tuple[str, bytes]], velocity: bytes) -> tuple[int, tuple[float, ...]]:
        """The agent's answer to one step: its neighbours' poses, then its velocity (the simulator's order)."""
        for j, data in poses:
            ns, values = self.pose_codec.decode(data)
            assert self.inputs.pose(j, ns, values, 0, self.sync.confirmed_ns) is None
            p, R = codec.relative_pose_from_values(values)
            self.sync.on_pose(j, ns, p, R, 0.0)
        ns, v = self.twist_codec.decode(velocity)
        assert self.inputs.velocity(ns, v, 0, self.sync.confirmed_ns) is None
        self.sync.on_velocity(ns, v, 0.0)
        return self.answers.pop()


def lockstep_without_ros(spec: FormationSpec, answer, witness: Witness) -> tuple[RunRecorder, int]:
    """Step ``spec`` as the lockstep simulator steps it: measure, encode, the witness's expectations on the
    decoded bytes, every agent's answer (``answer(i, k, messages, meas)``) admitted by the witness and
    applied; returns the recorder and how many answers were admitted."""
    sim = Simulation(simulator_view(spec))
    messages = StepMessages(spec)
    s = spec.simulation
    recorder = RunRecorder(spec, record_every=round(s.control_rate / s.record_rate), control_rate=s.control_rate)
    n_steps = round(s.duration * s.control_rate)
    admitted = 0
    for k in range(n_steps + 1):
        meas = sim.sense()
        messages.encode(meas)
        margin_v, _ = witness.step(messages.decoded(meas), recorder)
        book = WrenchBook(len(spec.agents))
        for i in range(len(spec.agents)):
            ns, u = answer(i, k, messages, meas)
            decision = admit(i, ns, u, None, book, witness.answers)
            assert decision.action == APPLY, (k, spec.agent_ids[i], decision)
            book.accept(i, ns, decision.u)
            admitted += 1
        u = np.array(book.value)
        recorder.add(meas.t, sim.state.p, sim.state.R, sim.state.v, u, margin_v)
        if k < n_steps:
            sim.advance(u)
    return recorder, admitted


def test_the_whole_paper_run_through_the_bytes_is_the_headless_run() -> None:
    """The paper's 5 s at 10 kHz: every agent's answer, computed by its own synchroniser and controller from
    the bytes it would receive, equals the witness's (bit for bit, all 250 005 of them) and the run equals
    the headless run core's, bit for bit."""
    spec = load_formation(PAPER)
    agents = [AgentProcess(spec, a) for a in spec.agent_ids]

    def answer(i, k, messages, meas):
        mine = [e for e, observer in enumerate(messages.observer) if observer == spec.agent_ids[i]]
        return agents[i].take([(messages.target[e], messages.poses[e]) for e in mine], messages.velocities[i])

    recorder, admitted = lockstep_without_ros(spec, answer, Witness(spec))
    assert admitted == 5 * 50_001
    ours, headless = recorder.arrays(), run_headless(spec, controller_mode="sampled").recorder.arrays()
    for key in ("t", "p", "R", "v", "u", "e", "psi"):
        np.testing.assert_array_equal(ours[key], headless[key], err_msg=key)


def test_answers_of_another_platform_agree_within_the_round_off_bound() -> None:
    """Agent 3 reports another numeric platform and runs interpreted (numpy's exp and log instead of the
    compiled code's): where its answers differ from the witness's (in the last places, when numpy's SIMD
    paths round otherwise than libm: on AVX-512 machines, not with those paths disabled), every one of them
    over the paper's 5 s lies within the step's round-off bound, and the largest ratio to it is reported."""
    spec = load_formation(PAPER)
    witness = Witness(spec)
    three = spec.agent_ids.index("3")
    witness.agent_reported(three, AgentReport(FORM_INTERPRETED, "another host", None, None))
    remote = AgentTeam(spec)
    assert remote.set_form(three, FORM_INTERPRETED)
    local = AgentTeam(spec)

    differed = []

    def answer(i, k, messages, meas):
        received = messages.decoded(meas)
        team = remote if i == three else local
        if i == 0 or i == three:  # one evaluation of each team per step
            team.evaluate(received, None)
        if i == three:
            differed.append(not np.array_equal(remote.out[i, :6], local.out[i, :6]))
        return received.ns, tuple(team.out[i, :6].tolist())

    lockstep_without_ros(spec, answer, witness)
    report = witness.report()["agents"]
    assert report["3"]["judged"] == "within the round-off bound"
    assert report["3"]["largest_ratio_to_tolerance"] < 1.0, report["3"]
    assert (report["3"]["largest_ratio_to_tolerance"] > 0.0) == any(differed), report["3"]
    assert all(report[a]["judged"] == "bit for bit" for a in spec.agent_ids if a != "3")


@pytest.mark.parametrize(("report", "judged"), [
    (AgentReport("compiled", numeric_platform(), None, None), "bit for bit"),
    (AgentReport("interpreted", numeric_platform(), None, None), "bit for bit"),
    (AgentReport("compiled", "another host", None, None), "within the round-off bound"),
    (AgentReport(None, None, None, None), "within the round-off bound"),
])  # fmt: skip
def test_how_an_agent_is_judged_follows_its_report(report: AgentReport, judged: str) -> None:
    """Same platform and a form this process runs: bit for bit; another platform, or no report: the bound."""
    spec = load_formation(PAPER)
    witness = Witness(spec)
    witness.agent_reported(0, report)
    assert witness.report()["agents"]["1"]["judged"] == judged
