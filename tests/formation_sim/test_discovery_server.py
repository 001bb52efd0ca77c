"""The discovery server helper: client environments, the ``env`` lines for sh, and ``serve``, which
runs a command as the server's client and stops the server by PID when the command exits."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from formation_core.options import Discovery
from formation_sim.launch import discovery_server
from formation_sim.launch.dds_env import discovery_client_environment


def test_client_environment_names_the_server_and_drops_simple_discovery_settings() -> None:
    """A client gets ROS_DISCOVERY_SERVER, range SYSTEM_DEFAULT, no static peers; ROS_SUPER_CLIENT only if asked."""
    base = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": "10.0.0.2", "ROS_SUPER_CLIENT": "TRUE"}
    env = discovery_client_environment(base, Discovery("server", "10.0.0.1", 7000))
    assert env["ROS_DISCOVERY_SERVER"] == "10.0.0.1:7000"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert "ROS_STATIC_PEERS" not in env and "ROS_SUPER_CLIENT" not in env
    assert base["ROS_STATIC_PEERS"] == "10.0.0.2"  # the caller's mapping is left alone
    sup = discovery_client_environment({}, Discovery("server", "10.0.0.1", 7000), super_client=True)
    assert sup["ROS_SUPER_CLIENT"] == "TRUE"


def test_env_lines_set_the_client_environment_in_sh() -> None:
    """``env SPEC``, run in the shell's environment (as ros2_ws/lib/network.sh does), prints lines that
    sh evaluates into the client environment (default port 11811, UDP only)."""
    shell_env = {"ROS_STATIC_PEERS": "10.0.0.9", "PATH": "/usr/bin:/bin"}
    lines = subprocess.run(
        [sys.executable, "-m", "formation_sim.launch.discovery_server", "env", "server"],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        env=shell_env,
    ).stdout
    script = lines + '\necho "$ROS_DISCOVERY_SERVER/$ROS_AUTOMATIC_DISCOVERY_RANGE/${ROS_STATIC_PEERS-unset}"'
    script += '\necho "$FASTDDS_BUILTIN_TRANSPORTS"'
    shown = subprocess.run(["sh", "-c", script], capture_output=True, text=True, timeout=30, env=shell_env)
    assert shown.stdout.split() == ["127.0.0.1:11811/SYSTEM_DEFAULT/unset", "UDPv4"]


def test_serve_runs_the_command_as_client_and_stops_the_server(tmp_path: Path) -> None:
    """``serve`` starts the server on a free port (bound while the command runs), passes the command's
    exit status through, and the server is gone afterwards."""
    port = discovery_server.free_udp_port("127.0.0.1")
    probe = tmp_path / "probe.txt"
    command = (
        f'echo "$ROS_DISCOVERY_SERVER" > {probe}; '
        f"grep -qi ':{port:04X} ' /proc/net/udp && echo bound >> {probe}; exit 3"
    )
    serve = [sys.executable, "-m", "formation_sim.launch.discovery_server", "serve", f"server:127.0.0.1:{port}"]
    result = subprocess.run(
        [*serve, "--", "sh", "-c", command],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 3, result.stderr
    assert probe.read_text().split() == [f"127.0.0.1:{port}", "bound"]
    assert not discovery_server.udp_port_bound(port)


def test_a_server_that_cannot_bind_is_a_clear_error(tmp_path: Path) -> None:
    """A port another process holds: the server exits and wait_listening says so (no hang)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
        held.bind(("127.0.0.1", 0))
        spec = Discovery("server", "127.0.0.1", held.getsockname()[1])
        proc = subprocess.Popen(
            discovery_server.server_command(spec),
            env=discovery_server.server_environment({}),
            stdout=(tmp_path / "server.log").open("wb"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            discovery_server.wait_listening(proc, spec, tmp_path / "server.log", timeout=30)
        except discovery_server.DiscoveryServerError as exc:
            message = str(exc)
        else:
            message = ""
        finally:
            discovery_server.stop(proc)
    assert "exited with status" in message, message
