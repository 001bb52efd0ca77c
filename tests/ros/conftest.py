"""Fixtures of the multi-process ROS 2 tests: an isolated environment (own ROS_DOMAIN_ID, LOCALHOST
discovery, logs under tmp_path) and a process group that always stops exactly the processes it
started (by PID, SIGINT then SIGTERM then SIGKILL), also when a test fails; two busy loops for the
tests under CPU starvation."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ros_helpers import Procs

from formation_sim.launch.dds_env import transport_environment


@pytest.fixture
def ros_env(ros_domain_id: int, tmp_path: Path) -> dict[str, str]:
    """Environment for every started process: own domain, this host only, logs under tmp_path."""
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(ros_domain_id),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(tmp_path / "roslog"),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_STATIC_PEERS", None)
    return env


@pytest.fixture
def procs(ros_env: dict[str, str], tmp_path: Path) -> Iterator[Procs]:
    logdir = tmp_path / "proclogs"
    logdir.mkdir()
    # the processes get what sim.sh/agent.sh give them: UDP only (the whole environment, profile included)
    group = Procs(transport_environment(ros_env), logdir)
    try:
        yield group
    finally:
        group.stop_all()


@pytest.fixture(scope="module")
def busy_loops() -> Iterator[list[int]]:
    """Two busy-loop processes beside the runs (CPU starvation), stopped by their PIDs afterwards."""
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(2)]
    try:
        yield [p.pid for p in loops]
    finally:
        for p in loops:
            p.kill()
            p.wait(timeout=10)
