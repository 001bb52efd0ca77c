"""Realtime fault handling, the agents' ROS graph contract, and clean shutdown of run.sh."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
from rclpy.node import Node
from ros_helpers import PAPER, REALTIME, RUN_SH, processes_mentioning, read_log, ros_context, wait_for_line

from formation_msgs_py.spec import agent_view, load_formation


def test_realtime_zeroes_a_killed_agent_and_carries_on(procs, tmp_path: Path) -> None:
    """kill -9 of an agent in realtime: the simulator zeroes its wrench, reports it and runs to the end."""
    spec = load_formation(REALTIME)
    agents = {a.id: procs.agent(REALTIME, a.id) for a in spec.agents}
    out = tmp_path / "out"
    # physics at the control rate keeps the simulator on the wall clock on a loaded 2-core machine
    sim = procs.sim(REALTIME, out, "--duration", "3", "--physics-rate", "100", "--progress-period", "0.2")
    assert wait_for_line(sim, "progress t=", 90), read_log(sim)
    time.sleep(0.5)
    os.kill(agents["2"].pid, signal.SIGKILL)
    code = sim.wait(timeout=60)
    log = read_log(sim)
    assert code in (0, 1), log
    assert "agent 2: " in log and "zero wrench" in log, log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["duration"] == 3.0
    assert summary["stale_commands"]["2"] > 50
    u = np.load(out / "trajectory.npz")["u"]
    index = spec.agent_ids.index("2")
    assert np.all(u[-50:, index] == 0.0)
    others = [i for i in range(len(spec.agents)) if i != index]
    assert np.any(u[-50:, others] != 0.0)


def test_agents_subscribe_to_exactly_their_contract(procs, ros_env: dict[str, str]) -> None:
    """Read from the ROS graph: agent i subscribes to its velocity, its neighbours' poses (and /clock)."""
    spec = load_formation(PAPER)
    for a in spec.agents:
        procs.agent(PAPER, a.id)
    with ros_context(ros_env) as context:
        node = Node("graph_query", context=context)
        names = {("formation_agent", f"/agent_{a.id}") for a in spec.agents}
        deadline = time.monotonic() + 60
        while not names <= set(node.get_node_names_and_namespaces()):
            assert time.monotonic() < deadline, node.get_node_names_and_namespaces()
            time.sleep(0.2)
        time.sleep(1.5)  # endpoints are announced after the participant
        for a in spec.agents:
            view = agent_view(spec, a.id)
            expected = {f"/agent_{a.id}/velocity", "/clock"}
            expected |= {f"/agent_{a.id}/relative_pose/agent_{j}" for j in view.neighbours}
            subs = {t for t, _ in node.get_subscriber_names_and_types_by_node("formation_agent", f"/agent_{a.id}")}
            assert subs == expected, (a.id, subs)
            pubs = {t for t, _ in node.get_publisher_names_and_types_by_node("formation_agent", f"/agent_{a.id}")}
            assert pubs == {f"/agent_{a.id}/wrench", "/diagnostics", "/rosout", "/parameter_events"}, pubs
        assert node.get_subscriptions_info_by_topic("/formation/ground_truth") == []
        node.destroy_node()


def test_sigint_to_run_sh_leaves_no_process(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Ctrl-C (SIGINT) to run.sh stops every process it started and writes a partial OUT."""
    formation = tmp_path / "sigint_formation.yaml"  # a path only this run's processes mention
    shutil.copy(PAPER, formation)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [str(RUN_SH), str(formation), "--out", str(out), "--duration", "5", "--no-plots"],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        sim_log = out / "logs" / "sim.log"
        deadline = time.monotonic() + 90
        while not (sim_log.exists() and "progress" in sim_log.read_text()):
            assert time.monotonic() < deadline and proc.poll() is None, proc.poll()
            time.sleep(0.1)
        assert len(processes_mentioning(str(formation))) >= 7  # simulator, 5 agents, recorder
        proc.send_signal(signal.SIGINT)
        stdout, _ = proc.communicate(timeout=90)
        assert proc.returncode == 130, stdout
        assert processes_mentioning(str(formation)) == [], stdout
        table = json.loads((out / "logs" / "processes.json").read_text())
        assert len(table) == 7 and all(row["returncode"] is not None for row in table), (table, stdout)
        assert {row["role"] for row in table} == {"sim", "agent", "recorder"}
        for row in table:
            assert not Path(f"/proc/{row['pid']}").exists() or "Z" in Path(f"/proc/{row['pid']}/stat").read_text()
        assert json.loads((out / "summary.json").read_text())["interrupted"] is True
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
