"""Fail closed in secure mode: a process whose secure transport profile did not apply must not run.

Fast DDS ignores a profile file it cannot parse (an error on stderr) and falls back to its builtin
UDP and shared-memory transports. A secure-mode process (``FORMATION_SECURE=1``, set with the
profile by formation_deploy.secure_transport) therefore checks, once its node exists, that it has
no UDP socket: the TLS-over-TCP profile opens none, the builtin transports always do. Linux only
(/proc); no ROS import.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

SECURE_FLAG = "FORMATION_SECURE"


class InsecureTransportError(RuntimeError):
    """Secure mode was asked for, but this process talks over an unauthenticated transport."""


def udp_sockets(pid: int | str = "self") -> list[str]:
    """Local addresses (hex ``ip:port`` as in /proc/net/udp*) of the UDP sockets ``pid`` holds."""
    inodes = set()
    fd_dir = Path(f"/proc/{pid}/fd")
    for fd in fd_dir.iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:[") : -1])
    found = []
    for table in ("udp", "udp6"):
        try:
            rows = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        found += [cols[1] for cols in (row.split() for row in rows) if cols[9] in inodes]
    return found


def check_secure_transport(environ: Mapping[str, str] = os.environ) -> None:
    """Raise InsecureTransportError if secure mode is on and this process has a UDP socket."""
    if environ.get(SECURE_FLAG) != "1":
        return
    sockets = udp_sockets()
    if sockets:
        profile = environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", "(unset)")
        raise InsecureTransportError(
            f"secure mode, but this process has {len(sockets)} UDP socket(s): the profile {profile} did not "
            "apply (Fast DDS fell back to its builtin UDP/shared-memory transports; see its XMLPARSER error)"
        )
