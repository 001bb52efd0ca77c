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
