"""Multi-host deployment: every process on its own "host" (a network namespace) of a private
network, ROS 2 discovery across hosts by multicast or by ROS_STATIC_PEERS, and the paper
scenario, shortened, giving the same result as on one host."""

from __future__ import annotations

import ipaddress
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
from bin_helpers import executable

if TYPE_CHECKING:
    from collections.abc import Callable

    from conftest import PrivateNetwork, Processes

REPO = Path(__file__).resolve().parents[2]

PINGPONG = Path(__file__).with_name("pingpong.py")
PYTHON = REPO / ".venv" / "bin" / "python"
PAPER = REPO / "config" / "paper_5agents.yaml"
#: Simulated time of the shortened paper scenario (500 lockstep steps at 10 kHz).
SHORT_DURATION = 0.05


def discovery_env(ros_env: Callable[..., dict[str, str]], mode: str, net: PrivateNetwork) -> dict[str, str]:
    """ROS environment for a discovery mode; UDP only, so that every message crosses eth0."""
    env = ros_env(FASTDDS_BUILTIN_TRANSPORTS="UDPv4")
    if mode == "multicast":
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    else:  # LOCALHOST: multicast only on this host's loopback; the other hosts by unicast
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        env["ROS_STATIC_PEERS"] = ";".join(h.address for h in net.hosts)
    return env


def test_private_network_has_no_route_off_the_machine(private_network: type[PrivateNetwork]) -> None:
    """The hosts have their subnet and multicast routes only: no default route, nothing in the root namespace."""
    net = private_network.create(["a", "b"])
    subnet = ipaddress.ip_network(net.subnet)
    for host in net.hosts:
        routes = net.routes(host)
        assert "default" not in routes, routes
        assert ipaddress.ip_address(host.address) in subnet
    root = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True, check=True).stdout
    assert all(h.address + "/" not in root for h in net.hosts)


@pytest.mark.parametrize("mode", ["multicast", "static_peers"])
def test_discovery_across_hosts(
    private_network: type[PrivateNetwork], processes: Processes, ros_env: Callable[..., dict[str, str]], mode: str
) -> None:
    """A publisher on one host reaches subscribers on two others (UDP over the private network)."""
    net = private_network.create(["talker", "listener1", "listener2"], multicast=mode == "multicast")
    env = discovery_env(ros_env, mode, net)
    listeners = [
        processes.start(h.name, [str(PYTHON), str(PINGPONG), "listen", "--timeout", "40"], env=env, netns=h.netns)
        for h in net.hosts[1:]
    ]
    talker = processes.start(
        "talker",
        [str(PYTHON), str(PINGPONG), "talk", "--listeners", "2", "--timeout", "40"],
        env=env,
        netns=net.host("talker").netns,
    )
    for proc in [*listeners, talker]:
        status = processes.wait(proc, timeout=60)
        assert status == 0, f"{proc.name} exited {status}\n{processes.logs()}"


@pytest.mark.parametrize(
    ("network", "delivered"),
    [("bridge", True), ("host", False)],
    ids=["bridge-network", "host-network-without-ipc-host"],
)
def test_containers_need_shared_ipc_on_the_host_network(
    private_network: type[PrivateNetwork],
    processes: Processes,
    ros_env: Callable[..., dict[str, str]],
    network: str,
    delivered: bool,
) -> None:
    """Two "containers" (each with its own /dev/shm, default Fast DDS transports): on a bridge network
    (own addresses) messages arrive; on one host network they match but nothing arrives, because
    Fast DDS then uses shared memory: why formation-compose --host-network adds ``ipc: host``."""
    net = private_network.create(["a", "b"])
    env = ros_env(ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
    listener_ns = net.hosts[1].netns if network == "bridge" else net.hosts[0].netns
    listener = processes.start(
        "listener",
        [str(PYTHON), str(PINGPONG), "listen", "--timeout", "12"],
        env=env,
        netns=listener_ns,
        private_shm=True,
    )
    talker = processes.start(
        "talker",
        [str(PYTHON), str(PINGPONG), "talk", "--timeout", "12"],
        env=env,
        netns=net.hosts[0].netns,
        private_shm=True,
    )
    assert processes.wait(talker, timeout=40) == 0, processes.logs()  # discovery works in both cases
    assert (processes.wait(listener, timeout=40) == 0) == delivered, processes.logs()


# --- the formation scenario ---------------------------------------------------------------------

SIM_SH = REPO / "ros2_ws" / "sim.sh"
AGENT_SH = REPO / "ros2_ws" / "agent.sh"
needs_deployment = pytest.mark.skipif(
    not (SIM_SH.exists() and AGENT_SH.exists()), reason="ros2_ws/sim.sh and agent.sh are not there yet"
)


#: Options of formation-headless and sim.sh for the shortened scenario.
SHORT = ("--duration", str(SHORT_DURATION), "--no-plots", "--quiet")


def run_headless(out: Path) -> None:
    subprocess.run(
        [executable("formation-headless"), str(PAPER), *SHORT, "--out", str(out)],
        check=True,
        timeout=300,
        capture_output=True,
    )


def run_deployment(
    processes: Processes,
    out: Path,
    env: dict[str, str],
    netns: dict[str, str | None],
    timeout: float = 240,
    extra: tuple[str, ...] = (),
) -> None:
    """The simulator and one agent process each (``netns[name]``, None: this host); wait for the simulator.

    ``extra``: options of both sim.sh and agent.sh (e.g. ``--secure KEYS --hosts FILE``). The agents run
    compiled (an agent started alone runs interpreted), as the headless run does: the runs are then
    equal bit for bit."""
    env = {**env, "NUMBA_DISABLE_JIT": "0"}
    agents = [
        processes.start(
            f"agent_{i}",
            [str(AGENT_SH), str(PAPER), str(i), *extra],
            env=env,
            netns=netns[f"agent_{i}"],
        )
        for i in range(1, 6)
    ]
    sim = processes.start(
        "sim",
        [str(SIM_SH), str(PAPER), *SHORT, "--out", str(out), *extra],
        env=env,
        netns=netns["sim"],
    )
    t0 = time.monotonic()
    status = processes.wait(sim, timeout=timeout)
    assert status == 0, f"sim exited {status} after {time.monotonic() - t0:.1f} s\n{processes.logs()}"
    processes.stop_all()  # the agents (SIGINT: they shut down cleanly)
    assert all(a.popen.returncode is not None for a in agents)


def assert_same_run(a: Path, b: Path) -> None:
    """Same trajectory and summary of the edges and agents, bit for bit, and the same funnel verdict."""
    ta, tb = np.load(a / "trajectory.npz"), np.load(b / "trajectory.npz")
    for key in ("t", "p", "R", "v", "u", "e", "psi"):
        assert ta[key].shape == tb[key].shape, key
        np.testing.assert_array_equal(ta[key], tb[key], err_msg=key)
    sa, sb = json.loads((a / "summary.json").read_text()), json.loads((b / "summary.json").read_text())
    assert sa["funnels_held"] == sb["funnels_held"]
    assert sa["first_violation"] == sb["first_violation"]
    for key in ("edges", "agents"):
        assert sa[key] == sb[key], key


NAMES = ["sim"] + [f"agent_{i}" for i in range(1, 6)]


@pytest.fixture(scope="module")
def one_host_runs(
    module_processes: Processes, ros_env: Callable[..., dict[str, str]], tmp_path_factory: pytest.TempPathFactory
) -> dict[str, Path]:
    """The shortened paper scenario on this host: ROS processes (LOCALHOST discovery) and headless."""
    base = tmp_path_factory.mktemp("one_host")
    runs = {"ros": base / "ros", "headless": base / "headless"}
    run_deployment(
        module_processes, runs["ros"], ros_env(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"), dict.fromkeys(NAMES)
    )
    run_headless(runs["headless"])
    return runs


@needs_deployment
@pytest.mark.parametrize("mode", ["multicast", "static_peers"])
def test_paper_scenario_across_hosts_equals_one_host(
    private_network: type[PrivateNetwork],
    processes: Processes,
    ros_env: Callable[..., dict[str, str]],
    one_host_runs: dict[str, Path],
    tmp_path: Path,
    mode: str,
) -> None:
    """Lockstep paper scenario (shortened): six hosts give exactly the run of one host, and of the headless
    runner."""
    net = private_network.create(NAMES, multicast=mode == "multicast")
    multi = tmp_path / "multihost"
    run_deployment(processes, multi, discovery_env(ros_env, mode, net), {h.name: h.netns for h in net.hosts})
    assert_same_run(multi, one_host_runs["ros"])
    assert_same_run(multi, one_host_runs["headless"])


@needs_deployment
def test_discovery_server_scenario_across_hosts_equals_one_host(
    private_network: type[PrivateNetwork],
    processes: Processes,
    ros_env: Callable[..., dict[str, str]],
    one_host_runs: dict[str, Path],
    tmp_path: Path,
) -> None:
    """sim.sh --discovery server:ADDR:PORT starts the server on the simulator's host, agent.sh joins it
    from five others, on a network without multicast: exactly the run of one host."""
    net = private_network.create(NAMES, multicast=False)
    server = f"server:{net.host('sim').address}:11811"
    multi = tmp_path / "server"
    env = ros_env(FASTDDS_BUILTIN_TRANSPORTS="UDPv4")  # every message crosses eth0
    run_deployment(processes, multi, env, {h.name: h.netns for h in net.hosts}, extra=("--discovery", server))
    assert_same_run(multi, one_host_runs["ros"])


@needs_deployment
def test_secure_scenario_across_hosts_equals_one_host(
    private_network: type[PrivateNetwork],
    processes: Processes,
    ros_env: Callable[..., dict[str, str]],
    one_host_runs: dict[str, Path],
    tmp_path: Path,
) -> None:
    """sim.sh / agent.sh --secure KEYS --hosts FILE on six hosts: TLS over TCP between the hosts'
    addresses (no multicast, no UDP), and exactly the run of one host."""
    from formation_deploy.keys import init_keys, process_names

    net = private_network.create(NAMES, multicast=False)
    keys = tmp_path / "keys"
    init_keys(keys, process_names([str(i) for i in range(1, 6)]))
    hosts = tmp_path / "hosts.yaml"
    hosts.write_text("".join(f"{'simulator' if h.name == 'sim' else h.name}: {h.address}\n" for h in net.hosts))
    multi = tmp_path / "secure"
    netns = {h.name: h.netns for h in net.hosts}
    run_deployment(processes, multi, ros_env(), netns, extra=("--secure", str(keys), "--hosts", str(hosts)))
    assert_same_run(multi, one_host_runs["ros"])
    assert json.loads((multi / "summary.json").read_text())["security"]["intruders"] == []


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-v"]))


# --- the documented example ---------------------------------------------------------------------

DOCKER_MD = REPO / "docs" / "docker.md"


def documented_hosts() -> dict[str, list[list[str]]]:
    """docs/docker.md's "Without Docker" example: each machine's command lines (``ROS_DOMAIN_ID=…``
    lines, split as the shell would, without the trailing ``&``), by machine letter."""
    text = DOCKER_MD.read_text()
    start = text.index("Without Docker, the same with the scripts")
    block = text[text.index("```\n", start) + 4 :]
    block = block[: block.index("```")]
    hosts: dict[str, list[list[str]]] = {}
    machine = None
    for line in block.splitlines():
        if line.startswith("# machine "):
            machine = line.split()[2]
            hosts[machine] = []
        elif line.strip():
            assert machine is not None, line
            words = shlex.split(line.removesuffix("&"))
            hosts[machine].append(words)
    return hosts


@needs_deployment
def test_documented_example_without_docker_runs_across_two_hosts(
    private_network: type[PrivateNetwork],
    processes: Processes,
    ros_env: Callable[..., dict[str, str]],
    tmp_path: Path,
) -> None:
    """The lines of docs/docker.md's example run as written on two hosts of a private network, with
    two substitutions only: the test run's own ROS_DOMAIN_ID for 42 (every line must set it), and
    the simulator shortened to 0.05 s, writing into the test's directory. The simulator passes."""
    hosts = documented_hosts()
    assert sorted(hosts) == ["A", "B"]
    lines = [words for commands in hosts.values() for words in commands]
    agents = sorted(w[3] for w in lines if w[1] == "./ros2_ws/agent.sh")
    assert agents == ["1", "2", "3", "4", "5"]
    assert all(w[0] == "ROS_DOMAIN_ID=42" for w in lines), lines
    net = private_network.create(["A", "B"], multicast=True)
    base_env = ros_env()
    sim = None
    for name, commands in sorted(hosts.items(), key=lambda kv: kv[0] != "B"):  # B's agents first
        for words in commands:
            argv = words[1:]
            if argv[0] == "./ros2_ws/sim.sh":
                out = argv.index("--out")
                argv = [*argv[:out], "--out", str(tmp_path / "run"), *argv[out + 2 :], *SHORT]
                sim = processes.start("sim", argv, env=base_env, netns=net.host(name).netns)
            else:
                processes.start(f"agent_{argv[2]}", argv, env=base_env, netns=net.host(name).netns)
    assert sim is not None
    status = processes.wait(sim, timeout=240)
    assert status == 0, f"sim exited {status}\n{processes.logs()}"
    processes.stop_all()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["funnels_held"] is True
