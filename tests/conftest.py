"""Shared fixtures: repository paths and formation files."""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))  # process_hygiene, for every test directory
REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "config"
PAPER = CONFIG / "paper_5agents.yaml"


@pytest.fixture
def paper_path() -> Path:
    return PAPER


@pytest.fixture
def paper_doc() -> dict[str, Any]:
    """The paper preset as a mutable YAML document (fresh copy per test)."""
    return copy.deepcopy(yaml.safe_load(PAPER.read_text()))


# --- ROS 2 isolation ------------------------------------------------------------------------
# Every test run that starts ROS processes takes a ROS_DOMAIN_ID no other live run holds: the
# allocator formation-launch uses (formation_sim.launch.dds_env: free port block and an exclusive flock,
# held until the pytest process exits).


def allocate_ros_domain_id() -> int:
    """A ROS_DOMAIN_ID reserved for this process (the same one on every call)."""
    from formation_sim.launch.dds_env import reserve_domain_id

    return reserve_domain_id()


@pytest.fixture(scope="session")
def ros_domain_id() -> int:
    """This test run's ROS_DOMAIN_ID (exclusive among concurrent runs on this machine)."""
    return allocate_ros_domain_id()


# --- no process and no Fast DDS file left behind -----------------------------------------------
# pytest becomes a child subreaper: a process a test started (or a grandchild of it) that outlives
# its parent is re-parented here, so every descendant is found. Fast DDS shared-memory files are
# attributed to this session by watching which /dev/shm files our descendants map while they run
# (other engineers' runs create such files concurrently: only ours count).
_PR_SET_CHILD_SUBREAPER = 36


def _set_subreaper() -> None:
    import ctypes

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_CHILD_SUBREAPER, 1)
    except OSError:
        pass


_set_subreaper()


def _shm_mapped(pids: list[int]) -> set[str]:
    from process_hygiene import shm_segments

    return {str(seg) for pid in pids for seg in shm_segments(pid)}


#: processes the test interpreter keeps for its own lifetime (not started by a test's code)
_HELPERS = ("multiprocessing.resource_tracker", "multiprocessing.forkserver")


def _helper(cmdline: str) -> bool:
    return any(h in cmdline for h in _HELPERS)


@pytest.fixture(autouse=True)
def no_leftovers() -> Any:
    """Fail a test that leaves a process it started, or a Fast DDS file in /dev/shm, behind."""
    import os
    import threading
    import time

    from process_hygiene import live_descendants

    root = os.getpid()
    before = set(live_descendants(root))
    seen: set[str] = set()
    stop = threading.Event()

    def watch() -> None:
        while not stop.wait(0.25):
            seen.update(_shm_mapped([p for p in live_descendants(root) if p not in before]))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    yield
    stop.set()
    watcher.join()
    deadline = time.monotonic() + 5.0

    def new() -> dict[int, str]:
        # the interpreter's own helpers live as long as pytest (started on first use by a test)
        return {p: c for p, c in live_descendants(root).items() if p not in before and not _helper(c)}

    while (left := new()) and time.monotonic() < deadline:
        time.sleep(0.1)
    for pid in left:
        try:
            os.kill(pid, 9)  # by PID: only what this test left
        except ProcessLookupError:
            pass
    live_maps = _shm_mapped([int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit()])
    shm_left = sorted(p for p in seen if Path(p).exists() and p not in live_maps)
    assert not left, f"processes left behind: {left}"
    assert not shm_left, f"Fast DDS files left in /dev/shm: {shm_left}"
