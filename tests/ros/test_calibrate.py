"""formation-check --calibrate: the floor's processes count their messages and the costs are stored."""

from __future__ import annotations

import json

import pytest

from formation_sim import capacity
from formation_sim.cli import check
from formation_sim.launch import calibrate


@pytest.fixture
def small_floor(ros_env, tmp_path, monkeypatch) -> None:
    """A chain of 3 at 50 Hz for 40 ticks, in this test's ROS domain, with its own cache directory."""
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOG_DIR"):
        monkeypatch.setenv(key, ros_env[key])
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(calibrate, "AGENTS", 3)
    monkeypatch.setattr(calibrate, "RATE", 50.0)
    monkeypatch.setattr(calibrate, "TICKS", 40)
    monkeypatch.setattr(calibrate, "WARMUP", 10)


def test_floor_counts_each_process_messages(small_floor) -> None:
    """Chain of 3, 40 ticks, /clock every 10: the simulator 7 sent + 3 taken a tick, agents 3 or 4, + 4 clocks."""
    m = calibrate.measure(3, 50.0, 40, 10)
    assert m["sim"]["messages"] == 40 * (7 + 3) + 4
    assert {a: v["messages"] for a, v in m["agents"].items()} == {"c0": 124, "c1": 164, "c2": 124}
    assert m["sim"]["cpu_s"] > 0 and all(v["cpu_s"] > 0 for v in m["agents"].values())
    assert 0.0 <= m["sim"]["on_time_fraction"] <= 1.0


def test_check_calibrate_stores_this_hosts_costs(small_floor, capsys) -> None:
    """formation-check --calibrate exits 0 and writes the costs that --realtime then uses."""
    assert check.main(["--calibrate"]) == 0
    path = capacity.calibration_path()
    doc = json.loads(path.read_text())
    assert doc["sim_message_s"] > 0 and doc["agent_message_s"] > 0
    assert capacity.load_costs().source.startswith("calibrated on ")
    assert f"written to {path}" in capsys.readouterr().out
