"""Fixtures of the deployment tests: a private multi-host network in network namespaces, and
processes started in it that are always stopped.

The network: one namespace holds a bridge; every "host" is a namespace with one veth link
``eth0`` on that bridge and a 10.x address. Nothing is created in the root namespace, no
namespace has a default route, so nothing of it can reach the real network. Names are unique
per test run; the namespaces are deleted whatever happens (also after a failed set-up).
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import signal
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import pytest
from bin_helpers import executable_dir

REPO = Path(__file__).resolve().parents[2]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=30)


def netns_unavailable() -> str | None:
    """Why network namespaces cannot be used here, or None."""
    if os.geteuid() != 0:
        return "needs root (ip netns add)"
    if shutil.which("ip") is None:
        return "needs iproute2 (ip)"
    probe = f"fmprobe{uuid.uuid4().hex[:6]}"
    result = _ip("netns", "add", probe, check=False)
    if result.returncode != 0:
        return f"ip netns add failed: {result.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


_OURS = re.compile(r"^fm(\d+)x[0-9a-f]{4}-\w+$")


def remove_stale_namespaces() -> list[str]:
    """Delete the namespaces of earlier runs of these tests whose pytest process is gone (killed
    before its clean-up ran); the names carry that pid. Returns the names deleted."""
    listed = _ip("netns", "list", check=False).stdout.split("\n")
    stale = []
    for line in listed:
        name = line.split(" ")[0]
        match = _OURS.match(name)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            _ip("netns", "del", name, check=False)
            stale.append(name)
    return stale


@dataclass(frozen=True)
class Host:
    """One simulated machine: a network namespace and its address on the private network."""

    name: str
    netns: str
    address: str


@dataclass
class PrivateNetwork:
    """A bridge namespace and ``hosts`` on it; ``close()`` deletes every namespace it made."""

    run_id: str
    subnet: str
    hosts: list[Host] = field(default_factory=list)
    namespaces: list[str] = field(default_factory=list)

    @classmethod
    def create(cls, host_names: Sequence[str], *, multicast: bool = True) -> PrivateNetwork:
        """Hosts named ``host_names`` on one bridge; ``multicast=False``: no multicast route, so
        that only unicast (static peers) can find the other hosts."""
        remove_stale_namespaces()
        run_id = f"fm{os.getpid()}x{uuid.uuid4().hex[:4]}"
        octet = 100 + os.getpid() % 100
        net = cls(run_id, f"10.{octet}.0.0/24")
        try:
            bridge_ns = net._add_ns("br")
            _ip("-n", bridge_ns, "link", "set", "lo", "up")
            # mcast_snooping 0: flood multicast to every port (no IGMP querier on this network)
            _ip("-n", bridge_ns, "link", "add", "br0", "type", "bridge", "mcast_snooping", "0")
            _ip("-n", bridge_ns, "link", "set", "br0", "up")
            for i, name in enumerate(host_names):
                ns = net._add_ns(f"h{i}")
                address = f"10.{octet}.0.{i + 1}"
                port = f"p{i}"
                _ip("-n", bridge_ns, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", ns)
                _ip("-n", bridge_ns, "link", "set", port, "master", "br0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
                _ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                if multicast:
                    _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", "eth0")  # multicast stays on eth0
                net.hosts.append(Host(name, ns, address))
        except BaseException:
            net.close()
            raise
        return net

    def _add_ns(self, suffix: str) -> str:
        name = f"{self.run_id}-{suffix}"
        _ip("netns", "add", name)
        self.namespaces.append(name)
        return name

    def host(self, name: str) -> Host:
        return next(h for h in self.hosts if h.name == name)

    def routes(self, host: Host) -> str:
        return _ip("-n", host.netns, "route", "show", "table", "all").stdout

    def close(self) -> None:
        for ns in reversed(self.namespaces):
            _ip("netns", "del", ns, check=False)
        self.namespaces.clear()


@dataclass
class Proc:
    name: str
    popen: subprocess.Popen[bytes]
    log: Path
    log_file: IO[bytes]


class Processes:
    """Processes of one test: each in its own session; ``stop_all`` stops exactly those PIDs."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: list[Proc] = []

    def start(
        self,
        name: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str],
        netns: str | None = None,
        private_shm: bool = False,
        cwd: Path = REPO,
    ) -> Proc:
        """Start ``argv`` in network namespace ``netns`` (None: this one); ``private_shm``: with a
        /dev/shm of its own, as a container without ``ipc: host`` has."""
        cmd = list(argv)
        if private_shm:
            mount = 'mount -t tmpfs -o mode=1777 tmpfs /dev/shm && exec "$@"'
            cmd = ["unshare", "--mount", "sh", "-c", mount, "_", *cmd]
        if netns:
            cmd = ["ip", "netns", "exec", netns, *cmd]
        log = self.log_dir / f"{name}.log"
        log_file = log.open("wb")
        popen = subprocess.Popen(
            cmd, env=dict(env), cwd=cwd, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True
        )
        proc = Proc(name, popen, log, log_file)
        self.procs.append(proc)
        return proc

    def wait(self, proc: Proc, timeout: float) -> int:
        """Exit status of ``proc``; fails the test (with its log) if it runs past ``timeout``."""
        try:
            return proc.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{proc.name} still running after {timeout:g} s; log:\n{self.tail(proc)}")

    @staticmethod
    def tail(proc: Proc, lines: int = 40) -> str:
        text = proc.log.read_text(errors="replace").splitlines()
        return "\n".join(text[-lines:])

    def logs(self) -> str:
        return "\n".join(f"--- {p.name} (exit {p.popen.poll()}) ---\n{self.tail(p)}" for p in self.procs)

    def stop_all(self) -> None:
        """SIGINT, then SIGTERM, then SIGKILL (which leaves Fast DDS /dev/shm segments) to each
        process group this object started, and only those."""
        for sig, grace in ((signal.SIGINT, 5.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
            running = [p for p in self.procs if p.popen.poll() is None]
            if not running:
                break
            for p in running:
                try:
                    os.killpg(p.popen.pid, sig)  # the group is the session we created for it
                except ProcessLookupError:
                    pass
            end = time.monotonic() + grace
            while time.monotonic() < end and any(p.popen.poll() is None for p in running):
                time.sleep(0.05)
        for p in self.procs:
            if not p.log_file.closed:
                p.log_file.close()


def make_ros_env(domain_id: int, **extra: str) -> dict[str, str]:
    """The environment of a ROS process of these tests: the directory of the project's scripts
    (tests/bin_helpers.py) first on PATH, the run's own ROS_DOMAIN_ID (tests/conftest.py's
    allocator; needed on this host, harmless in the private namespaces, which no other run can hear)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "FASTDDS_", "FASTRTPS_", "RMW_"))}
    env["PATH"] = f"{executable_dir()}:{env.get('PATH', '/usr/bin:/bin')}"
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


@pytest.fixture(scope="session")
def ros_env(ros_domain_id: int) -> Callable[..., dict[str, str]]:
    """``ros_env(**extra)``: the environment of a ROS process (see :func:`make_ros_env`)."""
    return functools.partial(make_ros_env, ros_domain_id)


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Processes]:
    procs = Processes(tmp_path)
    try:
        yield procs
    finally:
        procs.stop_all()


@pytest.fixture(scope="module")
def module_processes(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Processes]:
    """Like ``processes``, for module-scoped fixtures (stopped at the end of the module)."""
    procs = Processes(tmp_path_factory.mktemp("logs"))
    try:
        yield procs
    finally:
        procs.stop_all()


@pytest.fixture
def private_network() -> Iterator[type[PrivateNetwork]]:
    """A factory ``private_network.create([...host names])``; every network made is deleted."""
    reason = netns_unavailable()
    if reason:
        pytest.skip(reason)
    made: list[PrivateNetwork] = []

    class _Tracked(PrivateNetwork):
        @classmethod
        def create(cls, host_names: Sequence[str], *, multicast: bool = True) -> PrivateNetwork:
            net = PrivateNetwork.create(host_names, multicast=multicast)
            made.append(net)
            return net

    try:
        yield _Tracked
    finally:
        for net in made:
            net.close()
