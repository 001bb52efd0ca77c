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
# Every test run that starts ROS processes takes a ROS_DOMAIN_ID no other live run holds: the
# allocator formation-launch uses (formation_sim.dds_env: free port block and an exclusive flock,
# held until the pytest process exits).


def allocate_ros_domain_id() -> int:
    """A ROS_DOMAIN_ID reserved for this process (the same one on every call)."""
    from formation_sim.dds_env import reserve_domain_id

    return reserve_domain_id()


@pytest.fixture(scope="session")
def ros_domain_id() -> int:
    """This test run's ROS_DOMAIN_ID (exclusive among concurrent runs on this machine)."""
    return allocate_ros_domain_id()
