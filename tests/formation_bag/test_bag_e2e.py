"""End to end: a ROS 2 lockstep run recorded by formation-launch --record, analysed from its bag."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from bag_helpers import PAPER, script

from formation_bag.analysis import analyze_run
from formation_bag.dataset import load_run
from formation_bag.interop import check_bag

pytest.importorskip("rclpy")
pytest.importorskip("formation_sim.launch")

#: summary keys that describe the process, not the funnels
RUN_ONLY = {"wall_time", "real_time_factor", "bag", "source", "mode", "samples"}


def _compare(ours: dict, theirs: dict, path: str = "") -> list[str]:
    diffs = []
    for key, value in theirs.items():
        if key in RUN_ONLY or (path == "" and key not in ours):
            continue  # the launcher's extras (timing, discovery, …)
        where = f"{path}.{key}"
        if isinstance(value, dict):
            diffs += _compare(ours.get(key, {}), value, where)
        elif isinstance(value, float) and isinstance(ours.get(key), float):
            if abs(ours[key] - value) > 1e-9:
                diffs.append(f"{where}: {ours[key]!r} != {value!r}")
        elif ours.get(key) != value:
            diffs.append(f"{where}: {ours.get(key)!r} != {value!r}")
    return diffs


def test_recorded_run_reproduces_its_summary(ros_procs, tmp_path: Path) -> None:
    """formation-launch --record leaves OUT/bag; its analysis gives the run's summary (1e-9) and wrenches."""
    out = tmp_path / "run"
    run = ros_procs.start(
        [
            *script("formation-launch"),
            str(PAPER),
            "--duration",
            "0.1",
            "--control-rate",
            "1000",
            "--ground-truth-rate",
            "1000",
            "--allow-low-rate",
            "--record",
            "--no-plots",
            "--quiet",
            "--out",
            str(out),
        ]
    )
    stdout, stderr = ros_procs.finish(run, timeout=240)
    assert run.returncode == 0, stdout + stderr
    bag = out / "bag"
    assert (bag / "metadata.yaml").exists()
    recorded = load_run(bag, formation=PAPER)
    _, summary, reruns = analyze_run(recorded)
    theirs = json.loads((out / "summary.json").read_text())
    assert _compare(summary, theirs) == []
    assert summary["bag"]["ground_truth_samples"] == 101 and summary["bag"]["ground_truth_gaps"] == 0
    for r in reruns.values():
        assert r.compared == 101 and r.max_abs_diff <= 1e-12
    report = check_bag(bag)
    assert report.ok, report.problems
