"""Lockstep through ROS 2 processes: equal to the headless runner, deterministic, fault-safe."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from process_hygiene import cpu_load, live_descendants
from ros_helpers import (
    PAPER,
    REPO,
    assert_equals_headless,
    children_by_node,
    executable,
    faults_besides_resends,
    kill_hard,
    lockstep_with_a_killed_agent,
    read_log,
    remove_segments,
    run,
    wait_for_line,
)

from formation_core.spec import load_formation

#: 0.08 s of the paper preset at its 10 kHz control rate: 800 lockstep steps, recorded at every step
SHORT = ("--duration", "0.08", "--record-rate", "10000")


def _launch(env: dict[str, str], out: Path, *extra: str) -> subprocess.CompletedProcess:
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += [*SHORT, *extra]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=180, start_new_session=True)


def test_lockstep_equals_headless_and_is_deterministic(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Two ROS lockstep runs equal run_headless sampled at 10 kHz, bit for bit, and so each other."""
    runs = []
    for k in range(2):
        out = tmp_path / f"ros{k}"
        r = _launch(ros_env, out)
        assert r.returncode == 0, r.stdout + r.stderr
        assert_equals_headless(out / "trajectory.npz", 0.08)
        runs.append(np.load(out / "trajectory.npz"))
        assert runs[-1]["t"].shape == (801,)
    for key in runs[0].files:
        np.testing.assert_array_equal(runs[0][key], runs[1][key], err_msg=key)


def test_every_process_has_a_log_and_outputs(ros_env: dict[str, str], tmp_path: Path) -> None:
    """run.sh writes OUT as docs/outputs.md (a bag by default) with one log per process; exit 0 when funnels hold."""
    out = tmp_path / "out"
    r = subprocess.run(
        [str(REPO / "ros2_ws" / "run.sh"), str(PAPER), "--out", str(out), "--duration", "0.02"],
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=180,
        start_new_session=True,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "PASS: every funnel held" in r.stdout
    for name in ("summary.json", "trajectory.npz", "errors.png", "orientation_errors.png", "inputs.png"):
        assert (out / name).is_file(), name
    logs = {p.name for p in (out / "logs").iterdir()}
    assert {"sim.log", *(f"agent_{i}.log" for i in range(1, 6)), "processes.json"} <= logs
    assert "recorder.log" not in logs  # the simulator writes a lockstep run's bag
    assert (out / "bag" / "metadata.yaml").is_file()

    # --force into the same OUT: the earlier run's outputs go first, so nothing of it (its PASS,
    # its figures, its bag, its agents' fault counts) can be read as the new run's
    (out / "notes.txt").write_text("mine")
    r = _launch(ros_env, out, "--force", "--record", "--duration", "0.01")
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["duration"] == pytest.approx(0.01)  # 100 steps' stamps in integer ns over 1e9: a rounding
    assert not (out / "errors.png").exists() and (out / "notes.txt").read_text() == "mine"
    with (out / "bag" / "metadata.yaml").open() as f:
        info = yaml.safe_load(f)["rosbag2_bagfile_information"]
    gt = next(t for t in info["topics_with_message_count"] if t["topic_metadata"]["name"] == "/formation/ground_truth")
    assert gt["message_count"] == 101  # this run's 0.01 s at 10 kHz, not the first run's 0.02 s


def test_lockstep_names_a_killed_agent(procs, tmp_path: Path) -> None:
    """kill -9 of an agent mid-run: the simulator names it and exits 3 within its step timeout."""
    run = lockstep_with_a_killed_agent(procs, tmp_path / "out")
    assert not run.failures(), (run.failures(), run.log)


def test_lockstep_blames_no_agent_for_a_stopped_simulator(procs, tmp_path: Path) -> None:
    """A simulator stopped for longer than its step timeout (SIGSTOP here; a debugger, a stalled disk)
    names no agent: the answers sent meanwhile count, and the run equals the headless one (bit for bit)."""
    for a in load_formation(PAPER).agents:
        procs.agent(PAPER, a.id)
    out = tmp_path / "out"
    extra = ("--duration", "0.2", "--record-rate", "10000", "--step-timeout", "1")
    sim = procs.sim(PAPER, out, *extra, "--progress-period", "0.2")
    assert wait_for_line(sim, "progress t=", 90), read_log(sim)
    os.kill(sim.pid, signal.SIGSTOP)
    time.sleep(2.5)
    os.kill(sim.pid, signal.SIGCONT)
    assert sim.wait(timeout=120) == 0, read_log(sim)
    assert "no answer" not in read_log(sim)
    assert_equals_headless(out / "trajectory.npz", 0.2)


def test_launcher_stops_everything_when_an_agent_dies(ros_env: dict[str, str], tmp_path: Path) -> None:
    """The launcher notices a dead agent at once, stops the rest and exits 3."""
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [executable("formation-launch"), str(PAPER), "--out", str(out), "--duration", "5", "--no-plots", "--no-record"],
        env=ros_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 90
        while not (out / "logs" / "sim.log").exists() or "progress" not in (out / "logs" / "sim.log").read_text():
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        pids = children_by_node(proc.pid)
        left = kill_hard(pids["agent_2"])
        stdout, _ = proc.communicate(timeout=60)
        remove_segments(left)
        assert proc.returncode == 3, stdout
        assert "agent_2 was killed by SIGKILL" in stdout
        table = json.loads((out / "logs" / "processes.json").read_text())
        assert all(row["returncode"] is not None for row in table)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_a_simulator_that_goes_silent_is_stopped_as_hung(ros_env: dict[str, str], tmp_path: Path) -> None:
    """The simulator frozen (SIGSTOP) while it steps writes nothing more: after --hang-timeout the
    launcher stops every process (SIGKILL reaches a stopped one), exits 3, and its summary says so.
    Without the bound the launcher would wait for it for ever. 30 s: longer than a working simulator
    is silent while it starts on a busy machine (before its first line, between its discovery lines)."""
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--duration", "5", "--no-plots"]
    cmd += ["--no-record", "--hang-timeout", "30"]
    proc = subprocess.Popen(
        cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 90
        while not (out / "logs" / "sim.log").exists() or "progress" not in (out / "logs" / "sim.log").read_text():
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        (sim,) = [p for p, c in live_descendants(proc.pid).items() if "formation_sim.node.sim_node" in c]
        os.kill(sim, signal.SIGSTOP)
        stdout, _ = proc.communicate(timeout=120)
        assert proc.returncode == 3, stdout
        assert "the simulator wrote nothing for 30 s (hung; --hang-timeout)" in stdout
        summary = json.loads((out / "summary.json").read_text())
        assert summary["verdict"] == "INCOMPLETE" and "wrote nothing for 30 s" in summary["incomplete_reason"]
        table = {row["name"]: row["returncode"] for row in json.loads((out / "logs" / "processes.json").read_text())}
        assert table["sim"] == -9 and all(code is not None for code in table.values()), table
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_invalid_file_exits_2_before_starting(ros_env: dict[str, str], tmp_path: Path) -> None:
    """An invalid formation file: exit 2, a message naming the field, no output directory, no process."""
    doc = yaml.safe_load(PAPER.read_text())
    doc["edges"][0]["distance"] = 4.5
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    r = subprocess.run(
        [str(REPO / "ros2_ws" / "run.sh"), str(bad), "--out", str(out)],
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2, r.stdout + r.stderr
    assert "edges[0].distance" in r.stderr
    assert not out.exists()
    assert "simulator" not in r.stdout


def test_help_of_every_script() -> None:
    """Every script answers --help with exit 0."""
    for cmd in (
        [str(REPO / "ros2_ws" / "run.sh"), "--help"],
        [str(REPO / "ros2_ws" / "agent.sh"), "--help"],
        [str(REPO / "ros2_ws" / "sim.sh"), "--help"],
        [executable("formation-agent"), "--help"],
        [executable("formation-sim"), "--help"],
        [executable("formation-launch"), "--help"],
    ):
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, (cmd, r.stderr)
        assert "--" in r.stdout and len(r.stdout) > 200, cmd


@pytest.mark.skipif(shutil.which("unshare") is None, reason="unshare (util-linux) is not installed")
def test_private_network_namespace(ros_env: dict[str, str], tmp_path: Path) -> None:
    """--netns on runs the formation inside its own network namespace (how 50 agents run)."""
    from formation_sim.launch.dds_env import netns_available

    reason = netns_available()
    if reason is not None:
        pytest.skip(reason)
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--duration", "0.01", "--netns", "on"]
    r = subprocess.run(
        [*cmd, "--no-plots", "--quiet"],
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=180,
        start_new_session=True,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "private network namespace" in r.stdout
    assert json.loads((out / "summary.json").read_text())["launch"]["network_namespace"] is True


@pytest.mark.parametrize("rate", [3000.0, 7000.0])
def test_a_rate_whose_period_is_no_whole_number_of_nanoseconds(
    ros_env: dict[str, str], tmp_path: Path, rate: float
) -> None:
    """At 3 kHz and 7 kHz (periods of 333 333.3 and 142 857.1 ns) every agent's time is its stamp's, as the
    witness's and the headless run core's: the lockstep run equals the headless one bit for bit."""
    out = tmp_path / "out"
    duration = 0.1
    code, log = run(
        [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--quiet", "--no-record",
         "--control-rate", repr(rate), "--duration", str(duration), "--record-rate", repr(rate)],
        ros_env,
    )  # fmt: skip
    assert code == 0, log
    summary = json.loads((out / "summary.json").read_text())
    assert faults_besides_resends(summary)[0] == {}, summary["faults"]
    assert_equals_headless(
        out / "trajectory.npz", duration, record_rate=rate, overrides={"control_rate": rate, "physics_rate": rate}
    )


def test_agents_of_other_code_forms_and_platforms_in_one_run(procs, tmp_path: Path) -> None:
    """A compiled simulator with agent 3 interpreted on its platform (judged bit for bit against an
    interpreted witness) and agent 2 interpreted on what stands for another host (numba told of another
    CPU: another platform fingerprint, judged within the round-off bound; numpy's exp and log differ from
    the compiled witness's libm in the last places on CPUs with AVX-512): every answer agrees, the run
    passes with no fault."""
    other_cpu = {"NUMBA_DISABLE_JIT": "1", "NUMBA_CPU_NAME": "generic"}
    for a in load_formation(PAPER).agent_ids:
        env = {"NUMBA_DISABLE_JIT": "1"} if a == "3" else other_cpu if a == "2" else {"NUMBA_DISABLE_JIT": "0"}
        procs.agent(PAPER, a, env=env)
    out = tmp_path / "out"
    sim = procs.sim(PAPER, out, "--duration", "0.2", env={"NUMBA_DISABLE_JIT": "0"})
    assert sim.wait(timeout=300) == 0, read_log(sim)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"] == "PASS" and faults_besides_resends(summary)[0] == {}, summary["faults"]
    agents = summary["witness"]["agents"]
    assert (agents["3"]["judged"], agents["3"]["code_form"]) == ("bit for bit", "interpreted"), agents["3"]
    assert (agents["2"]["judged"], agents["2"]["code_form"]) == ("within the round-off bound", "interpreted")
    assert agents["2"]["largest_ratio_to_tolerance"] < 1.0, agents["2"]
    assert all(agents[a]["judged"] == "bit for bit" for a in ("1", "4", "5")), agents


def test_a_contact_is_reported_in_lockstep_realtime_and_the_analysis(ros_env: dict[str, str], tmp_path: Path) -> None:
    """Two non-neighbours steered into each other (tests/formation_sim/data/crossing_3agents.yaml): the
    lockstep run reports the contact as the headless run does (pair 1-3 from t = 0.2 s), so does
    formation-analyze of its bag, and so does a realtime run (at its own times)."""
    from formation_core.spec import load_formation as load
    from formation_sim.cli.headless import run_headless

    crossing = REPO / "tests" / "formation_sim" / "data" / "crossing_3agents.yaml"
    expected = run_headless(load(crossing), controller_mode="sampled").summary["clearance"]
    assert expected["first_contact"] == {"t": 0.2, "pair": ["1", "3"]}
    out = tmp_path / "lockstep"
    code, log = run(
        [executable("formation-launch"), str(crossing), "--out", str(out), "--no-plots", "--quiet"], ros_env
    )
    assert code == 0, log
    assert json.loads((out / "summary.json").read_text())["clearance"] == expected
    analysis = tmp_path / "analysis"
    code, log = run([executable("formation-analyze"), str(out / "bag"), "--out", str(analysis), "--no-plots"], ros_env)
    assert code == 0, log
    analysed = json.loads((analysis / "summary.json").read_text())["clearance"]
    assert analysed["first_contact"] == expected["first_contact"]
    out = tmp_path / "realtime"
    cmd = [executable("formation-launch"), str(crossing), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    code, log = run([*cmd, "--mode", "realtime", "--control-rate", "250"], ros_env)
    assert code in (0, 1), log  # realtime: the funnels decide, at their own times
    realtime = json.loads((out / "summary.json").read_text())["clearance"]
    assert realtime["first_contact"]["pair"] == ["1", "3"], realtime
    assert "CONTACT: agents 1 and 3 touched" in log


LINKS_PRESET = REPO / "config" / "links_5agents_100hz.yaml"


def test_a_run_with_links_in_lockstep_equals_headless_also_beside_busy_loops(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """The link preset (delays and losses on poses, velocities and wrenches) in lockstep, agents compiled,
    beside two busy loops: the headless run's trajectory, link ages and link statistics, bit for bit; its
    bag's analysis reports the same link statistics."""
    from formation_core.spec import load_formation as load
    from formation_sim.cli.headless import run_headless

    spec = load(LINKS_PRESET).with_simulation(duration=3.0)
    expected = run_headless(spec)
    out = tmp_path / "lockstep"
    env = {**ros_env, "NUMBA_DISABLE_JIT": "0"}  # the headless run's code form: the same bits
    cmd = [executable("formation-launch"), str(LINKS_PRESET), "--mode", "lockstep", "--duration", "3"]
    with cpu_load(2):
        code, log = run([*cmd, "--out", str(out), "--no-plots", "--quiet"], env)
    assert code == 0, log
    ours, theirs = np.load(out / "trajectory.npz"), expected.recorder.arrays()
    for key in ("t", "p", "R", "v", "u", "e", "psi", "link_age"):
        np.testing.assert_array_equal(ours[key], theirs[key], err_msg=key)
    links = json.loads((out / "summary.json").read_text())["links"]
    assert links == json.loads(json.dumps(expected.summary["links"]))
    assert links["poses"]["lost"] > 0 and links["wrench"]["lost"] > 0  # the model was at work
    analysis = tmp_path / "analysis"
    code, log = run([executable("formation-analyze"), str(out / "bag"), "--out", str(analysis), "--no-plots"], env)
    assert code == 0, log
    assert json.loads((analysis / "summary.json").read_text())["links"] == links
    assert "links: worst " in log


def test_a_run_with_links_in_realtime_reports_them_and_the_real_latency(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """The link preset in realtime (3 s): the simulator emulates the links on top of this host's network and
    says both: the links' statistics and the latency it measured."""
    out = tmp_path / "realtime"
    cmd = [executable("formation-launch"), str(LINKS_PRESET), "--duration", "3", "--out", str(out)]
    code, log = run([*cmd, "--no-plots", "--quiet", "--no-record"], ros_env)
    assert code in (0, 1), log  # realtime on a loaded host: the funnels decide
    links = json.loads((out / "summary.json").read_text())["links"]
    assert links["poses"]["sent"] > 0 and links["real_latency_ms"]["samples"] > 0
    assert "the real network under them" in log
