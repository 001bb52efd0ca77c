"""Discovery-server mode: every process a client of one Fast DDS discovery server (unicast only).
A lockstep run equals the headless one, past 32 processes on one host without a network namespace,
through formation-launch and through sim.sh/agent.sh; the server is stopped with the run."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
from ros_helpers import (
    PAPER,
    REPO,
    assert_equals_headless,
    executable,
    forty_agents_through_a_discovery_server,
    processes_mentioning,
    read_log,
)

from formation_core.spec import load_formation
from formation_sim.launch.dds_env import netns_available
from formation_sim.launch.discovery_server import free_udp_port, udp_port_bound


def _launch(
    env: dict[str, str], formation: Path, out: Path, *extra: str, timeout: float = 300
) -> subprocess.CompletedProcess:
    cmd = [executable("formation-launch"), str(formation), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--discovery", "server", *extra]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, start_new_session=True)


def _server_row(out: Path) -> dict:
    rows = json.loads((out / "logs" / "processes.json").read_text())
    return next(r for r in rows if r["name"] == "discovery_server")


def test_paper_lockstep_through_a_discovery_server_equals_headless(ros_env: dict[str, str], tmp_path: Path) -> None:
    """formation-launch --discovery server: the paper preset in lockstep equals headless (≤ 1e-9); the
    server was the run's process, every other one its client, and it stopped with the run (status 0)."""
    out = tmp_path / "out"
    r = _launch(ros_env, PAPER, out, "--duration", "0.08", "--record-rate", "10000")
    assert r.returncode == 0, r.stdout + r.stderr
    assert_equals_headless(out / "trajectory.npz", 0.08)
    launch = json.loads((out / "summary.json").read_text())["launch"]
    assert launch["discovery"].startswith("server:127.0.0.1:")
    assert launch["discovery_range"] == "SYSTEM_DEFAULT"  # rmw adds no LOCALHOST peers of its own
    assert launch["network_namespace"] is False
    server = _server_row(out)
    assert server["returncode"] == 0
    assert not udp_port_bound(int(launch["discovery"].rsplit(":", 1)[1]))


@pytest.mark.slow
def test_forty_agents_in_lockstep_on_one_host_without_a_namespace(ros_env: dict[str, str], tmp_path: Path) -> None:
    """41 processes (beyond the ~32 that LOCALHOST simple discovery matches) in discovery-server mode,
    no network namespace: the random 40-agent formation at 1 kHz equals its headless run (≤ 1e-9), and
    every process ended by itself (no SIGKILL)."""
    run = forty_agents_through_a_discovery_server(ros_env, tmp_path)
    assert load_formation(run.formation).simulation.control_rate == 1000.0
    assert not run.failures(), (run.failures(), run.text[-3000:])
    # 50 steps recorded at each: enough to compare every control step; the start of 41 processes dominates
    assert_equals_headless(run.out / "trajectory.npz", 0.05, formation=run.formation, record_rate=1000.0)
    summary = json.loads((run.out / "summary.json").read_text())
    assert summary["launch"]["processes"] == 42  # the server, the simulator, 40 agents
    assert summary["launch"]["network_namespace"] is False
    assert _server_row(run.out)["returncode"] == 0


def test_secure_with_a_discovery_server_is_refused_before_anything_starts(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """--secure with --discovery server exits 2 naming the reason (TLS over TCP only vs a UDP server)."""
    out = tmp_path / "out"
    r = _launch(ros_env, PAPER, out, "--secure", "--duration", "0.01", timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "--discovery server with --secure" in r.stderr and "docs/security.md" in r.stderr
    assert not (out / "logs" / "processes.json").exists()


def test_sim_sh_starts_the_server_and_agent_sh_joins_it(procs, tmp_path: Path) -> None:
    """sim.sh --discovery server:127.0.0.1:PORT starts the server and runs the simulator as its client,
    agent.sh --discovery the same joins it: the lockstep run equals headless, and the server is gone
    once sim.sh has exited."""
    port = free_udp_port("127.0.0.1")
    spec = f"server:127.0.0.1:{port}"
    for a in load_formation(PAPER).agents:
        agent = [str(REPO / "ros2_ws" / "agent.sh"), str(PAPER), a.id, "--discovery", spec]
        procs.start(f"agent_{a.id}", agent, {"NUMBA_DISABLE_JIT": "0"})  # compiled, as the headless run core
    out = tmp_path / "out"
    sim_cmd = [str(REPO / "ros2_ws" / "sim.sh"), str(PAPER), "--discovery", spec, "--out", str(out), "--no-plots"]
    sim = procs.start("sim", [*sim_cmd, "--duration", "0.02", "--record-rate", "10000"])
    assert sim.wait(timeout=300) == 0, read_log(sim)
    assert f"on 127.0.0.1:{port}" in read_log(sim)
    assert_equals_headless(out / "trajectory.npz", 0.02)
    assert not processes_mentioning(f"-p {port}")
    assert not udp_port_bound(port)  # only the server binds it: the agents are clients


def test_agent_sh_refuses_discovery_server_with_secure(tmp_path: Path) -> None:
    """agent.sh --discovery server --secure KEYS exits 2 with the reason, before any process starts."""
    r = subprocess.run(
        [str(REPO / "ros2_ws" / "agent.sh"), str(PAPER), "1", "--discovery", "server", "--secure", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2, r.stderr
    assert "--discovery server cannot be combined with --secure" in r.stderr


def _launch_without_multicast(env: dict[str, str], out: Path, discovery: str) -> subprocess.CompletedProcess:
    """formation-launch in a private network namespace where every multicast packet is dropped
    (iptables; Fast DDS sends its announcements through the loopback whatever its flags and routes):
    the launcher's namespace settings (SUBNET discovery, UDP only) are taken as they are."""
    drop = "iptables -A OUTPUT -d 224.0.0.0/4 -j DROP && iptables -A INPUT -d 224.0.0.0/4 -j DROP"
    script = f'ip link set lo up && {drop} && exec "$@"'
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--duration", "0.02", "--record-rate", "10000", "--discovery", discovery, "--discovery-timeout", "10"]
    env = {**env, "FORMATION_IN_NETNS": "1"}
    return subprocess.run(
        ["unshare", "-n", "sh", "-c", script, "sh", *cmd],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        start_new_session=True,
    )


@pytest.mark.skipif(
    netns_available() is not None or shutil.which("iptables") is None,
    reason=f"needs network namespaces ({netns_available() or 'available'}) and iptables",
)
def test_without_multicast_a_server_works_and_simple_discovery_matches_nothing(
    ros_env: dict[str, str], tmp_path: Path
) -> None:
    """On a loopback that carries no multicast, simple discovery ends with exit 3 naming the unmatched
    agents, while the same run through a discovery server (unicast) equals headless (≤ 1e-9)."""
    simple = _launch_without_multicast(ros_env, tmp_path / "simple", "simple")
    assert simple.returncode == 3, simple.stdout + simple.stderr
    assert "not matched within 10 s" in simple.stdout + simple.stderr
    server = _launch_without_multicast(ros_env, tmp_path / "server", "server")
    assert server.returncode == 0, server.stdout + server.stderr
    assert_equals_headless(tmp_path / "server" / "trajectory.npz", 0.02)
