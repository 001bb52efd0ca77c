"""A Fast DDS discovery server for one run: started from the project's environment, stopped by PID.

``formation-launch --discovery server`` starts it as one of the run's processes. Across hosts the
simulator's host starts it (``ros2_ws/sim.sh FILE --discovery server:HOST:PORT``), through this
module's command line (no ROS import)::

    python -m formation_sim.launch.discovery_server serve SPEC -- CMD …   # server, CMD as its client
    python -m formation_sim.launch.discovery_server env SPEC [--super-client]  # export lines for sh

``serve`` starts the server on SPEC's HOST:PORT, runs CMD in the environment of a client, passes
SIGINT, SIGTERM and SIGHUP on to CMD, stops the server by its PID once CMD exits, and exits with
CMD's status. SPEC is ``server[:HOST:PORT]`` (default 127.0.0.1:11811).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
import time
from collections.abc import Sequence
from pathlib import Path

from formation_core.options import DEFAULT_DISCOVERY_PORT, Discovery, discovery
from formation_sim.launch.dds_env import discovery_client_environment, shell_lines

#: the server executable of the ros_fastrtps wheel (in the environment's bin/)
SERVER = "fast-discovery-server"
#: wall seconds a started server may take to bind its port (busy machine: a few hundred ms typical)
START_TIMEOUT = 20.0


class DiscoveryServerError(RuntimeError):
    """The discovery server could not be started (the message says why)."""


def server_executable() -> Path:
    """``fast-discovery-server`` of this interpreter's environment, else the one on PATH."""
    here = Path(sys.executable).parent / SERVER
    if here.is_file():
        return here
    found = shutil.which(SERVER)
    if found is None:
        raise DiscoveryServerError(f"{SERVER} not found beside {sys.executable} or on PATH (package ros-fastrtps)")
    return Path(found)


def free_udp_port(host: str) -> int:
    """A UDP port free on ``host`` now (the kernel's pick: an ephemeral port, which no ROS_DOMAIN_ID of
    :data:`formation_sim.launch.dds_env.DOMAIN_IDS` uses)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def with_port(spec: Discovery, default: int | None = None) -> Discovery:
    """``spec`` with its port: its own, else ``default``, else a free one on its host."""
    if spec.port is not None:
        return spec
    return Discovery("server", spec.host, default or free_udp_port(spec.host))


def server_environment(base: dict[str, str]) -> dict[str, str]:
    """``base`` with the wheel's shared libraries on LD_LIBRARY_PATH (the executable's own RPATH does
    not reach them; Python processes of the environment set the same path when they start)."""
    site = Path(sysconfig.get_paths()["purelib"])
    dirs = [str(p) for p in sorted(site.glob("ros_*.libs"))] + [str(Path(sys.prefix) / "lib")]
    old = [d for d in base.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d and d not in dirs]
    # UDP only, as its clients (dds_env.transport_environment): no shared-memory port files
    return {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", **base, "LD_LIBRARY_PATH": os.pathsep.join(dirs + old)}


def server_command(spec: Discovery) -> list[str]:
    """The server with id 0 (the first of ROS_DISCOVERY_SERVER), listening on UDP HOST:PORT only."""
    assert spec.port is not None, "with_port() first"
    return [str(server_executable()), "-i", "0", "-l", spec.host, "-p", str(spec.port)]


def udp_port_bound(port: int, pid: int | None = None) -> bool:
    """True if a local UDP socket (of process ``pid``, if given) is bound to ``port`` (/proc/net/udp{,6})."""
    inodes: set[str] | None = None
    if pid is not None:
        inodes = set()
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                target = os.readlink(fd)
                if target.startswith("socket:["):
                    inodes.add(target[8:-1])
        except OSError:
            return False  # gone
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if int(fields[1].rsplit(":", 1)[1], 16) == port and (inodes is None or fields[9] in inodes):
                return True
    return False


def wait_listening(proc: subprocess.Popen, spec: Discovery, log: Path | None, timeout: float = START_TIMEOUT) -> None:
    """Return once the server listens on its port; DiscoveryServerError if it exits or times out first."""
    assert spec.port is not None
    deadline = time.monotonic() + timeout
    while not udp_port_bound(spec.port, proc.pid):
        if proc.poll() is not None:
            tail = log.read_text(errors="replace").strip().splitlines()[-3:] if log and log.exists() else []
            raise DiscoveryServerError(
                f"{SERVER} on {spec.address()} exited with status {proc.returncode}"
                + (f": {' / '.join(tail)}" if tail else "")
            )
        if time.monotonic() > deadline:
            raise DiscoveryServerError(f"{SERVER} did not listen on {spec.address()} within {timeout:g} s")
        time.sleep(0.05)


def stop(proc: subprocess.Popen, grace: float = 3.0) -> None:
    """SIGINT to the server's own process group, SIGKILL after ``grace`` s."""
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGKILL, 2.0)):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            continue


def serve(spec: Discovery, cmd: Sequence[str]) -> int:
    """Start the server on ``spec`` (with its port), run ``cmd`` as its client, stop the server; ``cmd``'s
    exit status (128 + N if a signal N ended it)."""
    from formation_sim.launch.supervisor import die_with_parent

    server = subprocess.Popen(
        server_command(spec),
        env=server_environment(dict(os.environ)),
        stdin=subprocess.DEVNULL,
        stdout=sys.stderr,  # its banner, or why it could not start
        start_new_session=True,
        preexec_fn=die_with_parent,
    )
    try:
        wait_listening(server, spec, None)
        print(f"discovery: server {SERVER} (pid {server.pid}) on {spec.address()}", file=sys.stderr, flush=True)
        child = subprocess.Popen(
            list(cmd), env=discovery_client_environment(dict(os.environ), spec), start_new_session=True
        )
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, lambda signum, _frame: child.send_signal(signum))
        code = child.wait()
    finally:
        stop(server)
    return 128 - code if code < 0 else code


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cmd: list[str] = []
    if "--" in argv:
        cmd = argv[argv.index("--") + 1 :]
        argv = argv[: argv.index("--")]
    p = argparse.ArgumentParser(prog="python -m formation_sim.launch.discovery_server", description=__doc__)
    p.add_argument("action", choices=("serve", "env"))
    p.add_argument("spec", type=discovery, help="server or server:HOST:PORT")
    p.add_argument("--super-client", action="store_true", help="env: the client learns the whole graph")
    args = p.parse_args(argv)
    if not args.spec.server:
        p.error("SPEC must be server or server:HOST:PORT")
    spec = with_port(args.spec, DEFAULT_DISCOVERY_PORT)
    if args.action == "env":
        client = discovery_client_environment(dict(os.environ), spec, super_client=args.super_client)
        print(shell_lines(os.environ, client))
        return 0
    if not cmd:
        p.error("serve needs the command after --")
    try:
        return serve(spec, cmd)
    except DiscoveryServerError as exc:
        print(f"discovery: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
