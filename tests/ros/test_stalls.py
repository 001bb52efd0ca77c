"""Lockstep under stalls and forged answers: a run equals the headless one, or it is not PASS and says why.

Every answer is compared with the simulator's witness (its shadow of the agent's controller): a
forged wrench is never applied; after a live gain change the witness follows the agent's new gains. A
simulator or an agent stopped (SIGSTOP) for longer than the step timeout, at a seeded random step,
on a machine made busier by two busy loops, leaves the run equal to the headless one (bit for bit)
and PASS, or ends it not PASS naming the cause.
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import (
    FORGED,
    PAPER,
    assert_equals_headless,
    executable,
    launch_beside_a_forger,
    read_log,
    ros_context,
    run,
    wait_for_line,
)

from formation_core.spec import load_formation
from formation_msgs_py import topics

#: 0.2 s of the paper preset at 10 kHz: 2000 lockstep steps, every one recorded
DURATION = 0.2
RUN = ("--duration", str(DURATION), "--record-rate", "10000", "--step-timeout", "1", "--progress-period", "1e-6")
#: the simulator prints its progress every 64 steps (a tiny progress period)
PROGRESS_EVERY = 64


def test_a_forged_answer_is_never_applied(ros_env: dict[str, str], tmp_path: Path) -> None:
    """An outsider answers each of agent 3's steps with 50 N on /agent_3/wrench as soon as the step is
    published (the pending step's stamp, mostly before agent 3): never in u, counted as answer_mismatch,
    the run equals the headless one, and it ends INCOMPLETE (untrusted input) naming the outsider."""
    out = tmp_path / "out"
    duration = 0.05
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--duration", str(duration), "--record-rate", "10000"]
    code, log, forged = launch_beside_a_forger(cmd, ros_env)
    assert code == 4, log  # the outsider is an intruder: untrusted input, whatever the witness kept out
    assert forged > 0, log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["faults"]["3"]["answer_mismatch"]["count"] >= 1, summary["faults"]
    assert ("/agent_3/wrench", "/outsider") in {(i["topic"], i["node"]) for i in summary["security"]["intruders"]}
    assert summary["incomplete_reason"].startswith("untrusted input: "), summary["incomplete_reason"]
    u = np.load(out / "trajectory.npz")["u"]
    i3 = load_formation(PAPER).agent_ids.index("3")
    assert not np.any(np.all(u[:, i3] == FORGED, axis=-1)), "a forged wrench was applied"
    assert_equals_headless(out / "trajectory.npz", duration)


def _stop_at_random_step(sim: subprocess.Popen, victim: int, pause: float, rng: random.Random) -> int:
    """SIGSTOP ``victim`` for ``pause`` wall s once the simulator passed a step drawn from ``rng`` (and a
    random fraction of a progress interval more); the step passed."""
    step = rng.randrange(0, int(DURATION * 10000) - 4 * PROGRESS_EVERY, PROGRESS_EVERY)
    deadline = time.monotonic() + 120
    pattern = re.compile(r"progress t=([0-9.]+)/")
    while True:
        times = [float(t) for t in pattern.findall(read_log(sim))]
        if times and times[-1] * 10000 >= step - 0.5:
            break
        assert sim.poll() is None and time.monotonic() < deadline, read_log(sim)
        time.sleep(0.005)
    time.sleep(rng.uniform(0.0, 0.05))
    os.kill(victim, signal.SIGSTOP)
    try:
        time.sleep(pause)
    finally:
        os.kill(victim, signal.SIGCONT)
    return step


@pytest.mark.parametrize(("who", "seed"), [("simulator", s) for s in (1, 2, 3)] + [("agent", s) for s in (1, 2, 3)])
def test_a_stall_at_any_step_leaves_the_run_headless_or_not_pass(
    busy_loops: list[int], procs, tmp_path: Path, who: str, seed: int
) -> None:
    """The simulator stopped 2.5 s, or one agent 2 s, at a random step (step timeout 1 s), two busy loops
    beside: PASS and equal to the headless run (bit for bit), or not PASS with the cause named."""
    rng = random.Random(f"{who}-{seed}")
    agents = {a.id: procs.agent(PAPER, a.id) for a in load_formation(PAPER).agents}
    out = tmp_path / "out"
    sim = procs.sim(PAPER, out, *RUN)
    assert wait_for_line(sim, "progress t=", 120), read_log(sim)
    if who == "simulator":
        victim, pause = sim.pid, 2.5
    else:
        victim, pause = agents[rng.choice(sorted(agents))].pid, 2.0
    step = _stop_at_random_step(sim, victim, pause, rng)
    code = sim.wait(timeout=180)
    log = read_log(sim)
    summary = json.loads((out / "summary.json").read_text())
    note = f"{who} stopped after step {step}: exit {code}, {summary['verdict']}, faults {summary['faults']}\n{log}"
    if code == 0:
        assert summary["verdict"] == "PASS", note
        assert_equals_headless(out / "trajectory.npz", DURATION)
    else:
        assert summary["verdict"] != "PASS", note
        assert code == 3 and re.search(r"formation-sim: ERROR: lockstep: no answer .*from agent \w+", log), note


def test_the_witness_follows_an_agent_whose_gain_changed_live(procs, ros_env: dict[str, str], tmp_path: Path) -> None:
    """gamma of agent 3 set mid-run (ros2 param set): the witness follows it, the run goes on to its end
    with no answer refused for long, and summary.json witness says agent 3 used γ = 20 from a sim time
    inside the run (a live change), the others their file's gains throughout."""
    for a in load_formation(PAPER).agents:
        procs.agent(PAPER, a.id)
    with ros_context(ros_env) as context:
        node = Node("parameter_driver", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        client = AsyncParameterClient(node, topics.agent_node("3"))
        assert client.wait_for_services(timeout_sec=60)
        out = tmp_path / "out"
        sim = procs.sim(PAPER, out, *RUN)
        assert wait_for_line(sim, "progress t=", 120), read_log(sim)
        future = client.set_parameters([Parameter("gamma", value=20.0)])
        executor.spin_until_future_complete(future, timeout_sec=30)
        assert future.done() and future.result().results[0].successful, read_log(sim)
        node.destroy_node()
    code = sim.wait(timeout=180)
    log = read_log(sim)
    summary = json.loads((out / "summary.json").read_text())
    assert code in (0, 1) and summary["verdict"] in ("PASS", "FAIL"), log  # the funnels decide: gains changed
    agents = summary["witness"]["agents"]
    first, then = agents["3"]["gains"]
    assert (first["gamma"], first["source"], first["from_t"]) == (15.0, "formation file", 0.0), agents["3"]
    assert then["gamma"] == 20.0 and then["source"] == "live change" and 0.0 < then["from_t"] < DURATION, then
    assert all(len(agents[a]["gains"]) == 1 for a in agents if a != "3"), agents
    assert "agent 3: δ=0.1, γ=20 from t=" in log, log


def test_an_agent_that_answers_wrongly_is_named_with_its_own_exit_status(procs, tmp_path: Path) -> None:
    """Agent 3 reads another copy of the formation file (edge 3-4 wants 2.55 m, not 2.5 m): its first answer
    differs from the witness's, the same answer to the re-sent step names it (exit 5, wrong answer), no
    wrench of it is applied, and formation-analyze of the run's bag says the same reason and status."""
    doc = yaml.safe_load(PAPER.read_text())
    for edge in doc["edges"]:
        if (str(edge["tail"]), str(edge["head"])) == ("3", "4"):
            edge["distance"] = 2.55
    other = tmp_path / "other_copy.yaml"
    other.write_text(yaml.safe_dump(doc))
    for a in load_formation(PAPER).agents:
        procs.agent(other if a.id == "3" else PAPER, a.id)
    out = tmp_path / "out"
    sim = procs.sim(PAPER, out, "--duration", "0.05", "--bag", str(tmp_path / "bag"))
    code = sim.wait(timeout=180)
    log = read_log(sim)
    assert code == 5, log
    summary = json.loads((out / "summary.json").read_text())
    reason = summary["incomplete_reason"]
    assert summary["verdict"] == "INCOMPLETE" and summary["exit_status"] == 5, summary
    assert reason.startswith("lockstep: wrong answer: agent 3 (max |u - witness|"), reason
    assert "allowed bit for bit" in reason and "at t=0.000000 s, re-sent" in reason, reason
    assert summary["faults"]["3"]["answer_mismatch"]["count"] >= 2, summary["faults"]
    u = np.load(out / "trajectory.npz")["u"]
    assert not np.any(u[:, load_formation(PAPER).agent_ids.index("3")]), "a wrench of agent 3 was applied"
    analyzed = tmp_path / "analysis"
    analyze = [executable("formation-analyze"), str(tmp_path / "bag"), "--out", str(analyzed), "--no-plots"]
    code, text = run(analyze, dict(os.environ))
    assert code == 5, text
    again = json.loads((analyzed / "summary.json").read_text())
    assert again["incomplete_reason"].startswith("the run stopped: " + reason), again["incomplete_reason"]
