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
    for a, r in reruns.items():
        # every recorded wrench is reproduced (an agent matched by the recorder after its first
        # steps leaves those out of the bag; the analysis then takes the re-run's wrench)
        assert r.compared == len(recorded.wrench[a]) >= 90 and r.max_abs_diff <= 1e-12
        assert r.compared + summary["bag"]["wrenches_from_rerun"].get(a, 0) == 101
    report = check_bag(bag)
    assert report.ok, report.problems
    assert_markers_decode(bag, expected=4)  # 0.1 s at the default 30 Hz display rate: t = 0, 1/30, 2/30, 3/30


def assert_markers_decode(bag: Path, expected: int) -> None:
    """/formation/markers read and decoded by the independent mcap / mcap_ros2 readers: the scene of each instant."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    arrays = []
    for segment in sorted(bag.glob("*.mcap")):
        with segment.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            arrays += [m for _, _, _, m in reader.iter_decoded_messages(topics=["/formation/markers"])]
    assert len(arrays) == expected
    for msg in arrays:
        by_ns: dict[str, int] = {}
        for marker in msg.markers:
            assert marker.header.frame_id == "world"
            by_ns[marker.ns] = by_ns.get(marker.ns, 0) + 1
        # paper: 5 agents (body, frame, label, force, torque) and 4 edges (line, desired-distance ghost)
        assert by_ns == {"bodies": 5, "frames": 5, "labels": 5, "forces": 5, "torques": 5, "edges": 4, "desired": 4}


def test_recorded_realtime_run_gives_the_same_margins(ros_procs, tmp_path: Path) -> None:
    """A realtime run's bag: the analysis finds the simulator's funnel margins (they need no timing)."""
    out = tmp_path / "run"
    run = ros_procs.start(
        [
            *script("formation-launch"),
            str(PAPER),
            "--mode",
            "realtime",
            "--duration",
            "0.3",
            "--control-rate",
            "1000",
            "--physics-rate",
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
    assert run.returncode in (0, 1), stdout + stderr  # 1: a stale wrench on a loaded machine is a fault
    recorded = load_run(out / "bag", formation=PAPER)
    _, summary, _ = analyze_run(recorded)
    theirs = json.loads((out / "summary.json").read_text())
    counts = summary["bag"]["recorder_counts"]
    assert summary["samples"] == counts["published_total"]["/formation/ground_truth"] > 0
    # a lagging realtime simulator may check ticks it did not publish: the bag then holds a subset
    # of its samples, and each minimum over the subset is at least the simulator's minimum
    exact = summary["samples"] == theirs["samples"]

    def check(ours: float | None, sim: float | None, what: object) -> None:
        if exact:
            assert ours == pytest.approx(sim, abs=1e-9), what
        elif ours is not None and sim is not None:
            assert ours >= sim - 1e-9, what

    for name, edge in theirs["edges"].items():
        for key in ("min_margin_e", "min_margin_psi"):
            check(summary["edges"][name][key], edge[key], (name, key))
    for aid, agent in theirs["agents"].items():
        check(summary["agents"][aid]["min_margin_v"], agent["min_margin_v"], aid)
