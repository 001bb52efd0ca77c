"""Shared fixtures: repository paths and formation files."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

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
# Every test run that starts ROS processes takes a ROS_DOMAIN_ID no other live run holds: an
# exclusive flock on /tmp/formation-ros-domain-<id>.lock, held until the pytest process exits.
# Ids come from 1..101 and 215..232 (Fast DDS refuses ids above 232; 102..214 may collide with
# ephemeral ports on Linux), starting from a pid-derived offset.
_DOMAIN_IDS = [*range(1, 102), *range(215, 233)]
_held_domain: tuple[int, object] | None = None


def allocate_ros_domain_id() -> int:
    """A ROS_DOMAIN_ID reserved for this process (the same one on every call)."""
    global _held_domain
    if _held_domain is not None:
        return _held_domain[0]
    import fcntl
    import os

    start = os.getpid() % len(_DOMAIN_IDS)
    for k in range(len(_DOMAIN_IDS)):
        domain = _DOMAIN_IDS[(start + k) % len(_DOMAIN_IDS)]
        handle = open(f"/tmp/formation-ros-domain-{domain}.lock", "w")  # held for the session
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _held_domain = (domain, handle)
        return domain
    raise RuntimeError("every ROS_DOMAIN_ID is held by another test run")


@pytest.fixture(scope="session")
def ros_domain_id() -> int:
    """This test run's ROS_DOMAIN_ID (exclusive among concurrent runs on this machine)."""
    return allocate_ros_domain_id()
