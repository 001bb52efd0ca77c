"""What a test must not leave behind: processes it started and Fast DDS shared-memory segments.

A process killed with SIGKILL cannot remove its Fast DDS segments from /dev/shm. The processes of a
run that formation-launch or the scripts start use UDP only and have none; a process a test starts
itself with the tests' ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST has them (the rmw adds its
shared-memory transport under LOCALHOST whatever FASTDDS_BUILTIN_TRANSPORTS says). Tests that kill
on purpose note the victim's segments first and remove exactly those afterwards.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def shm_segments(pid: int, *, ports: bool = False) -> set[Path]:
    """The Fast DDS shared-memory segments process ``pid`` maps (``ports``: its port files too)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return {
        Path(line.split(None, 5)[-1].replace(" (deleted)", ""))
        for line in maps.splitlines()
        if "/dev/shm/fastrtps_" in line and (ports or "/dev/shm/fastrtps_port" not in line)
    }


def kill_hard(pid: int) -> set[Path]:
    """SIGKILL ``pid``; returns the shared-memory segments it leaves (Fast DDS cannot remove them)."""
    segments = shm_segments(pid)
    os.kill(pid, signal.SIGKILL)
    return segments


def remove_segments(segments: set[Path], timeout: float = 10.0) -> None:
    """Remove the segments a SIGKILLed process left, once no process maps them any more."""
    deadline = time.monotonic() + timeout
    live = [int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit()]
    while any(seg in shm_segments(p) for p in live for seg in segments) and time.monotonic() < deadline:
        time.sleep(0.2)
    for seg in segments:
        seg.unlink(missing_ok=True)
        Path(f"{seg}_el").unlink(missing_ok=True)


def live_descendants(root: int) -> dict[int, str]:
    """{pid: command line} of the live (non-zombie) descendants of ``root``."""
    parent: dict[int, int] = {}
    cmd: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            state, ppid = stat.rsplit(")", 1)[1].split()[:2]
            if state == "Z":
                continue
            line = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
        except (OSError, ValueError):
            continue  # gone meanwhile: then neither its parent nor its command line is kept
        parent[int(d.name)] = int(ppid)
        cmd[int(d.name)] = line
    out = {}
    for pid in parent:
        p, hops = parent.get(pid), 0
        while p is not None and p > 1 and hops < 64:
            if p == root:
                out[pid] = cmd[pid]
                break
            p, hops = parent.get(p), hops + 1
    return out


@contextmanager
def cpu_load(n: int) -> Iterator[list[subprocess.Popen]]:
    """``n`` busy-loop processes (a loaded machine), stopped by their PIDs on exit."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait()


def stop_group(proc: subprocess.Popen, grace: float = 60.0) -> None:
    """Stop the process group a test started (``start_new_session``) by its PID: SIGINT, then SIGKILL
    after ``grace`` s."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
