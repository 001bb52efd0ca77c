"""Start, watch and stop the processes of one run (no ROS import).

Each child runs in its own session and process group, writes to its own log file (never a pipe:
a child must be able to finish when its supervisor is gone), and gets SIGTERM if the supervisor
dies (PR_SET_PDEATHSIG), so that a SIGKILLed launcher still leaves its children stopped and the
simulator's summary written. Stopping sends SIGINT to every child at once and SIGKILL only after
a grace period. No SIGTERM in between: a node process treats both alike (rclpy's handlers shut its
context down, formation_ros.shutdown), so SIGTERM after SIGINT changes nothing.

The children may run under Linux's ``SCHED_BATCH`` policy (``Supervisor.batch``, formation-launch
``--scheduling batch``): a process woken by a message then waits for a free core or the next
scheduler tick instead of preempting the one running. A run's processes hand each other ~20
messages a step, and with the default policy every hand-off may preempt the sender (~36
preemptions of the simulator per lockstep step of the paper formation). Batch pays on an idle
machine and halves a run's speed beside other busy processes: docs/ros2.md, BENCHMARKS.md.
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import subprocess
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """A child started with this as ``preexec_fn`` gets SIGTERM when its parent dies (Linux)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def batch_child() -> None:
    """:func:`die_with_parent`, and the child (every thread it will start) under ``SCHED_BATCH``.

    Any user may choose this policy; where it does not exist (not Linux) the child keeps its own.
    """
    die_with_parent()
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):
        pass


_POLICY_NAMES = {
    getattr(os, n): n for n in ("SCHED_OTHER", "SCHED_BATCH", "SCHED_IDLE", "SCHED_FIFO", "SCHED_RR") if hasattr(os, n)
}


def policy_name(pid: int) -> str | None:
    """The scheduling policy of process ``pid`` by name (Popen returns after the exec, so after
    :func:`batch_child`); None where the kernel does not say."""
    try:
        policy = os.sched_getscheduler(pid)
    except (AttributeError, OSError):
        return None
    return _POLICY_NAMES.get(policy, str(policy))


def _argv0(args: Any) -> Any:
    """The program of a Popen's ``args``: its first item, or the whole command when it is one string or path."""
    return args[0] if isinstance(args, (list, tuple)) else args


@dataclass
class Child:
    """One started process: its name, role, log file and (once reaped) its accounting."""

    name: str
    role: str
    proc: subprocess.Popen
    log: Path
    returncode: int | None = None
    rusage: dict[str, float] = field(default_factory=dict)
    reported: bool = False
    #: its scheduling policy once started (``SCHED_BATCH``, ``SCHED_OTHER``, …), as the kernel reports it
    policy: str | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status, ru = os.wait4(self.proc.pid, os.WNOHANG)
            except ChildProcessError:
                self.returncode = self.proc.returncode if self.proc.returncode is not None else -1
                return self.returncode
            if pid == 0:
                return None
            self.returncode = os.waitstatus_to_exitcode(status)
            self.proc.returncode = self.returncode
            self.rusage = {"cpu_user_s": ru.ru_utime, "cpu_system_s": ru.ru_stime, "max_rss_mb": ru.ru_maxrss / 1024}
        return self.returncode

    def signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)  # its own process group (start_new_session)
            except ProcessLookupError:
                pass

    def describe_exit(self) -> str:
        rc = self.returncode
        if rc is not None and rc < 0:
            return f"{self.name} was killed by {signal.Signals(-rc).name}"
        return f"{self.name} exited with status {rc}"


class LogFollower:
    """Reads the lines a child appends to its log file (the simulator's progress and messages)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._pos = 0
        self._partial = b""

    def new_lines(self) -> list[str]:
        try:
            with self.path.open("rb") as fh:
                fh.seek(self._pos)
                data = fh.read()
        except OSError:
            return []
        self._pos += len(data)
        data = self._partial + data
        *lines, self._partial = data.split(b"\n")
        return [line.decode("utf-8", "replace") for line in lines]


#: Fast DDS's TLS errors, as a process writes them to its console (its log here), coloured or not:
#: ``[RTCP_TLS Error] Handshake failed: certificate verify failed -> Function operator()``. A
#: connecting process logs the handshakes it could not complete; the accepting side logs nothing.
#: A handshake cut by the network (a peer still starting or stopping: "Connection reset by peer")
#: happens in sound runs too and is not counted: only what TLS itself refused (an OpenSSL reason:
#: "certificate verify failed", "tlsv1 alert unknown ca", "EVP lib (asn1 …)", …).
_CONNECTION_ERRORS = (
    "connection reset",
    "connection refused",
    "connection aborted",
    "end of file",
    "stream truncated",
    "broken pipe",
    "operation canceled",
    "timed out",
)
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_TLS_ERROR = re.compile(r"\[RTCP_TLS Error\]\s*(?P<text>.*?)(?:\s*->\s*Function\b.*)?$")


@dataclass(frozen=True)
class TlsFailures:
    """The TLS errors in one process's log: how many, and the last one's text."""

    count: int
    last: str


def tls_failures(log: Path) -> TlsFailures | None:
    """The handshakes TLS refused in ``log`` (Fast DDS's TLS errors but those of a connection cut by
    the network), or None when it has none."""
    count, last = 0, ""
    try:
        with log.open("rb") as fh:
            for raw in fh:
                if b"RTCP_TLS" not in raw:
                    continue
                found = _TLS_ERROR.search(_ANSI.sub("", raw.decode("utf-8", "replace")).rstrip())
                if found and not any(e in found["text"].lower() for e in _CONNECTION_ERRORS):
                    count, last = count + 1, found["text"][:200]
    except OSError:
        return None
    return TlsFailures(count, last) if count else None


@dataclass
class Supervisor:
    """The children of one run and how they are stopped."""

    env: dict[str, str]
    logs: Path
    #: child name -> name of its own environment in ``process_env``, where they differ
    key_names: dict[str, str] = field(default_factory=dict)
    #: per-process environments (secure mode: each its own certificate and port), by key name
    process_env: dict[str, dict[str, str]] = field(default_factory=dict)
    children: list[Child] = field(default_factory=list)
    #: children under SCHED_BATCH (:func:`batch_child`)
    batch: bool = False

    def start(self, name: str, role: str, cmd: list[str]) -> Child:
        log = self.logs / f"{name}.log"
        with open(log, "wb") as fh:
            proc = subprocess.Popen(
                cmd,
                stdin=subprocess.DEVNULL,
                stdout=fh,
                stderr=subprocess.STDOUT,
                env=self.process_env.get(self.key_names.get(name, name), self.env),
                start_new_session=True,
                preexec_fn=batch_child if self.batch else die_with_parent,
            )
        child = Child(name, role, proc, log, policy=policy_name(proc.pid))
        self.children.append(child)
        return child

    def alive(self, children: Iterable[Child] | None = None) -> list[Child]:
        return [c for c in (self.children if children is None else children) if c.poll() is None]

    def newly_dead(self) -> list[Child]:
        """Children that exited since the last call (each reported once)."""
        dead = [c for c in self.children if not c.reported and c.poll() is not None]
        for c in dead:
            c.reported = True
        return dead

    def wait(self, children: list[Child], timeout: float, tick: Callable[[], None] | None = None) -> bool:
        """True once every child in ``children`` has exited; False after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while self.alive(children):
            if time.monotonic() >= deadline:
                return False
            if tick is not None:
                tick()
            time.sleep(0.02)
        return True

    def stop(
        self, children: list[Child], grace: float, note: Callable[[str], None], interrupted: Iterable[str] = ()
    ) -> None:
        """SIGINT to every child at once (but those named in ``interrupted``: they had theirs); SIGKILL
        to those still running ``grace`` s later."""
        for c in self.alive(children):
            if c.name not in interrupted:
                c.signal(signal.SIGINT)
        if self.wait(children, grace):
            return
        left = self.alive(children)
        note(f"{', '.join(c.name for c in left)} still running after {grace:g} s: SIGKILL")
        for c in left:
            c.signal(signal.SIGKILL)
        self.wait(left, 1.0)

    def process_table(self, root: Path) -> list[dict[str, object]]:
        return [
            {
                "name": c.name,
                "pid": c.proc.pid,
                "role": c.role,
                "executable": str(_argv0(c.proc.args)),
                "returncode": c.returncode,
                "log": str(c.log.relative_to(root)),
                "policy": c.policy,
                **c.rusage,
            }
            for c in self.children
        ]
