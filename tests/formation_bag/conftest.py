"""Fixtures of the bag tests: synthetic lockstep bags (no ROS, bag_fixtures) and ROS processes started safely.

ROS processes get the test run's exclusive domain (tests/conftest.py ros_domain_id), discovery
on this host only, a temporary ROS_LOG_DIR and their own session; every process a test starts
is stopped by its PID (SIGINT, then SIGTERM, SIGKILL only as a last resort) even when the test
fails.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from formation_sim.launch.dds_env import transport_environment

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bag_fixtures, bag_helpers and synth, next to this file
from bag_fixtures import short_bags, violating_bag  # noqa: F401 (fixtures of this folder's tests)

# -- ROS processes ----------------------------------------------------------------------------------


@dataclass
class Processes:
    """Starts processes in their own session with the test's ROS environment; stops exactly those.

    A thread per stream collects the output, so a test can wait for a line and still read all of it.
    """

    env: dict[str, str]
    started: list[subprocess.Popen] = field(default_factory=list)
    lines: dict[int, tuple[list[str], list[str]]] = field(default_factory=dict)

    def start(self, args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
        """Start ``args`` with the test's environment (plus ``env``)."""
        proc = subprocess.Popen(
            args,
            env={**self.env, **(env or {})},
            start_new_session=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.started.append(proc)
        out: list[str] = []
        err: list[str] = []
        self.lines[proc.pid] = (out, err)
        for stream, sink in ((proc.stdout, out), (proc.stderr, err)):
            threading.Thread(target=lambda s=stream, k=sink: k.extend(iter(s.readline, "")), daemon=True).start()
        return proc

    def wait_line(self, proc: subprocess.Popen, needle: str, timeout: float) -> str:
        """Wait for a stdout line containing ``needle`` (fails after ``timeout`` s or if the process ends)."""
        deadline = time.monotonic() + timeout
        out, err = self.lines[proc.pid]
        while time.monotonic() < deadline:
            for line in list(out):
                if needle in line:
                    return line
            if proc.poll() is not None:
                time.sleep(0.2)
                if not any(needle in line for line in out):
                    break
            time.sleep(0.05)
        raise AssertionError(f"no line with {needle!r} from {proc.args} in {timeout} s: {''.join(out)}{''.join(err)}")

    def finish(self, proc: subprocess.Popen, timeout: float) -> tuple[str, str]:
        """Wait for the process to exit; (stdout, stderr)."""
        proc.wait(timeout)
        time.sleep(0.1)  # let the reader threads reach EOF
        out, err = self.lines[proc.pid]
        return "".join(out), "".join(err)

    @staticmethod
    def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        """Send ``sig`` to this one process; escalate to SIGTERM, then SIGKILL; returns the exit status."""
        for s, wait in ((sig, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if proc.poll() is not None:
                break
            proc.send_signal(s)
            try:
                proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        return proc.wait()

    def stop_all(self) -> None:
        for proc in reversed(self.started):
            if proc.poll() is None:
                self.stop(proc)


@pytest.fixture
def ros_procs(tmp_path: Path, ros_domain_id: int) -> Iterator[Processes]:
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(ros_domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PYTHONUNBUFFERED="1",
    )
    procs = Processes(transport_environment(env))  # UDP only, as the scripts give it (record.sh, replay.sh)
    try:
        yield procs
    finally:
        procs.stop_all()
