"""The DDS environment of a run: a ROS_DOMAIN_ID nobody else uses, discovery kept on this host,
and (for runs above Fast DDS's per-host participant limit) a private network namespace, or the
environment of a client of a Fast DDS discovery server (:func:`discovery_client_environment`).

Shared by ``formation-launch`` and the tests' allocator (tests/conftest.py): a domain is taken
only if no local socket uses its port block *and* an exclusive ``flock`` on
``/tmp/formation-ros-domain-<id>.lock`` succeeds; the lock is held by the process until it exits,
so concurrent runs and test sessions on one machine never share a domain.
"""

from __future__ import annotations

import fcntl
import os
import shlex
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import IO

from formation_core.options import Discovery
from formation_msgs_py import topics

#: the Fast DDS profile of a non-secure process whose discovery range is not LOCALHOST (the file
#: says what it sets and why); the profiles ship with the messages package
FASTDDS_PROFILE = Path(topics.__file__).with_name("fastdds_profile.xml")
#: the profile of a non-secure process kept on this host: UDP on 127.0.0.1 only, no shared memory
FASTDDS_LOOPBACK_PROFILE = Path(topics.__file__).with_name("fastdds_loopback.xml")
_OUR_PROFILES = {str(FASTDDS_PROFILE), str(FASTDDS_LOOPBACK_PROFILE)}

#: Ids Fast DDS accepts whose port blocks stay clear of Linux's ephemeral ports (102..214 may collide).
DOMAIN_IDS = (*range(1, 102), *range(215, 233))
#: Above this many DDS participants, run in a private network namespace (Fast DDS LOCALHOST limit).
NETNS_THRESHOLD = 30
IN_NETNS = "FORMATION_IN_NETNS"
_held: tuple[int, IO[str]] | None = None


class DomainError(RuntimeError):
    """No free ROS_DOMAIN_ID on this host."""


def used_domain_ids() -> set[int]:
    """Domain ids whose Fast DDS port block (7400 + 250·id …) has a bound UDP socket here."""
    used: set[int] = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            port = int(line.split()[1].rsplit(":", 1)[1], 16)
            if port >= 7400:
                used.add((port - 7400) // 250)
    return used


def reserve_domain_id() -> int:
    """A ROS_DOMAIN_ID reserved for this process until it exits (the same one on every call)."""
    global _held
    if _held is not None:
        return _held[0]
    used = used_domain_ids()
    start = os.getpid() % len(DOMAIN_IDS)
    for k in range(len(DOMAIN_IDS)):
        domain = DOMAIN_IDS[(start + k) % len(DOMAIN_IDS)]
        if domain in used:
            continue
        handle = open(f"/tmp/formation-ros-domain-{domain}.lock", "w")  # held until this process exits
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _held = (domain, handle)
        return domain
    raise DomainError("every ROS_DOMAIN_ID is in use on this host; set ROS_DOMAIN_ID")


def netns_available() -> str | None:
    """None if ``unshare -n`` works here, else the reason."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip (util-linux, iproute2) not found"
    r = subprocess.run(["unshare", "-n", "ip", "link", "set", "lo", "up"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"unshare -n not permitted: {r.stderr.strip() or r.returncode} (needs root or CAP_SYS_ADMIN)"
    return None


def reexec_in_netns(module: str, argv: list[str]) -> None:
    """Replace this process by ``python -m module argv`` inside a new network namespace (loopback only)."""
    env = dict(os.environ, **{IN_NETNS: "1"})
    script = 'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec "$@"'
    cmd = ["unshare", "-n", "sh", "-c", script, "sh", sys.executable, "-m", module, *argv]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execvpe("unshare", cmd, env)


def in_netns() -> bool:
    return os.environ.get(IN_NETNS) == "1"


def transport_environment(base: Mapping[str, str]) -> dict[str, str]:
    """``base`` with Fast DDS's transports of a non-secure process: UDP only, never shared memory.

    Discovery range LOCALHOST (or unset) without ``ROS_STATIC_PEERS`` becomes
    :data:`FASTDDS_LOOPBACK_PROFILE` under ``SYSTEM_DEFAULT``: the rmw's LOCALHOST adds a
    shared-memory transport that no setting removes (the profile says why that matters). Any other
    range, or a client of a discovery server, gets :data:`FASTDDS_PROFILE` and
    ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``. A profile of the environment's own (not one of ours)
    is left alone, with the range it came with. Secure mode replaces all of it per process.
    """
    env = dict(base)
    profile = env.get("FASTRTPS_DEFAULT_PROFILES_FILE")
    if profile and profile not in _OUR_PROFILES:
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        return env
    requested = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST"
    if profile == str(FASTDDS_LOOPBACK_PROFILE) and requested == "SYSTEM_DEFAULT":
        requested = "LOCALHOST"  # this function's own earlier answer
    if env.get("ROS_DISCOVERY_SERVER"):
        requested = "SYSTEM_DEFAULT"  # a client (discovery_client_environment)
    if requested == "LOCALHOST" and not env.get("ROS_STATIC_PEERS"):
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_LOOPBACK_PROFILE)
        env.pop("FASTDDS_BUILTIN_TRANSPORTS", None)  # the profile names its transport itself
    else:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = requested
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
        env.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")
    return env


def transport_name(env: Mapping[str, str]) -> str:
    """What :func:`transport_environment` chose, in words (``summary.json`` ``launch.transport``)."""
    profile = env.get("FASTRTPS_DEFAULT_PROFILES_FILE")
    if profile == str(FASTDDS_LOOPBACK_PROFILE):
        return "UDP on 127.0.0.1 only (fastdds_loopback.xml)"
    if profile == str(FASTDDS_PROFILE):
        return f"Fast DDS builtin transports {env.get('FASTDDS_BUILTIN_TRANSPORTS') or 'default'} (fastdds_profile.xml)"
    return f"the profile {profile}" if profile else "Fast DDS defaults"


def run_environment(base: dict[str, str], *, log_dir: Path) -> dict[str, str]:
    """The environment of every process of a run: a reserved domain unless ROS_DOMAIN_ID is set,
    discovery on this host unless the range is set (in a private namespace: its own loopback), and
    UDP only (:func:`transport_environment`)."""
    env = dict(base)
    env["PYTHONUNBUFFERED"] = "1"
    env["ROS_LOG_DIR"] = str(log_dir)
    if in_netns():
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"  # multicast on the namespace's own loopback only
    env = transport_environment(env)  # secure mode sets its own per process
    if not env.get("ROS_DOMAIN_ID"):
        env["ROS_DOMAIN_ID"] = str(reserve_domain_id())
    return env


def discovery_client_environment(
    base: dict[str, str], discovery: Discovery, *, super_client: bool = False
) -> dict[str, str]:
    """``base`` made the environment of a client of the discovery server ``discovery.address()``.

    Fast DDS (2.14) turns every participant created with ``ROS_DISCOVERY_SERVER`` set into a client
    of that server: it announces itself to the server only (unicast, no multicast) and learns from
    it the participants whose topics match its own. ``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT``
    keeps rmw_fastrtps from adding its own LOCALHOST peers and multicast settings on top.
    ``super_client``: ``ROS_SUPER_CLIENT=TRUE``, the client learns the whole graph (a recorder that
    finds its topics on the graph, ``ros2 topic list``), not only what matches its own topics.
    """
    env = dict(base)
    env["ROS_DISCOVERY_SERVER"] = discovery.address()
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    env.pop("ROS_STATIC_PEERS", None)  # peers of simple discovery: not used by a client
    if super_client:
        env["ROS_SUPER_CLIENT"] = "TRUE"
    else:
        env.pop("ROS_SUPER_CLIENT", None)
    # UDP only, on every interface: the server may be on another host
    return transport_environment(env)


def shell_lines(before: Mapping[str, str], after: Mapping[str, str]) -> str:
    """``export``/``unset`` lines that turn the environment ``before`` into ``after`` (for ``eval``)."""
    lines = [f"export {k}={shlex.quote(v)}" for k, v in after.items() if before.get(k) != v]
    gone = sorted(k for k in before if k not in after)
    return "\n".join(lines + ([f"unset {' '.join(gone)}"] if gone else []))


def main(argv: list[str] | None = None) -> int:
    """``python -m formation_sim.launch.dds_env transports``: the shell lines of
    :func:`transport_environment` for this environment (ros2_ws/lib/network.sh evaluates them)."""
    args = sys.argv[1:] if argv is None else argv
    if args != ["transports"]:
        print("usage: python -m formation_sim.launch.dds_env transports", file=sys.stderr)
        return 2
    print(shell_lines(os.environ, transport_environment(os.environ)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
