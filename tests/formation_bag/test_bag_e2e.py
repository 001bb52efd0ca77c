"""End to end: a ROS 2 lockstep run recorded by formation-launch --record, analysed from its bag."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from bag_helpers import PAPER, REPO, cpu_load, script

from formation_bag.dataset import load_run
from formation_bag.interop_check import check_bag
from formation_sim.offline.analysis import analyze_run

REALTIME = REPO / "config" / "realtime_5agents_100hz.yaml"
#: what the judge decides: equal between the run and the analysis of its bag
JUDGED = ("verdict", "exit_status", "funnels_held", "first_violation", "worst_margin", "duration", "edges", "agents")


def _compare(ours: Any, theirs: Any, path: str) -> list[str]:
    if isinstance(theirs, dict):
        assert isinstance(ours, dict) and ours.keys() == theirs.keys(), (path, ours, theirs)
        return [d for k in theirs for d in _compare(ours[k], theirs[k], f"{path}.{k}")]
    if isinstance(theirs, float) and isinstance(ours, float):
        # as tests/formation_sim/test_offline.py's assert_same_summary: rotations through quaternions
        # move the margins by some 1e-13; the velocity margins are the re-run's, within the round-off bound
        return [] if abs(ours - theirs) <= 1e-9 else [f"{path}: {ours!r} != {theirs!r}"]
    return [] if ours == theirs else [f"{path}: {ours!r} != {theirs!r}"]


def test_lockstep_bag_is_complete_under_cpu_load(ros_procs, tmp_path: Path) -> None:
    """The default run (10 kHz lockstep, recording) with three busy loops added: the bag holds every
    step of every topic, and its analysis and re-run reproduce the run's verdict and wrenches exactly."""
    out = tmp_path / "run"
    with cpu_load(3):
        run = ros_procs.start(
            [*script("formation-launch"), str(PAPER), "--duration", "0.1", "--no-plots", "--quiet", "--out", str(out)]
        )
        stdout, stderr = ros_procs.finish(run, timeout=400)
    theirs = json.loads((out / "summary.json").read_text())
    assert run.returncode == 0 == theirs["exit_status"], stdout + stderr
    assert theirs["recorder"]["not_recorded"] == 0, theirs["recorder"]
    bag = out / "bag"
    recorded = load_run(bag)
    steps = 1001
    assert len(set(recorded.ground_truth.stamps)) == steps
    for a in recorded.spec.agent_ids:
        assert len(set(recorded.velocity[a].stamps)) == steps and len(set(recorded.wrench[a].stamps)) == steps
    for link, series in recorded.relative_pose.items():
        assert len(set(series.stamps)) == steps, link  # the paper's pairs stay within sensing range
    _, summary, reruns = analyze_run(recorded)
    assert summary["bag"]["missing"] == [] and summary["bag"]["recorder_counts"]["missing"] == {}
    assert _compare({k: summary[k] for k in JUDGED}, {k: theirs[k] for k in JUDGED}, "") == []
    for r in reruns.values():
        # formation-rerun's equality: within each step's round-off tolerance (bit for bit when the
        # agent ran compiled on this host, as the launcher starts it at 10 kHz)
        assert r.compared == steps and r.first_difference(None) is None
    assert summary["bag"]["wrenches_from_rerun"] == {}
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
        assert by_ns == {
            "bodies": 5, "frames": 5, "labels": 5, "forces": 5, "torques": 5, "edges": 4, "desired": 4, "contacts": 5
        }  # fmt: skip


def test_recorded_realtime_run_gives_the_same_margins(ros_procs, tmp_path: Path) -> None:
    """A realtime run's bag: the analysis finds the simulator's funnel margins (they need no timing)."""
    out = tmp_path / "run"
    run = ros_procs.start(
        [
            *script("formation-launch"),
            str(REALTIME),
            "--duration",
            "1",
            # physics at the control rate keeps the simulator on the wall clock on a loaded machine
            "--physics-rate",
            "100",
            "--ground-truth-rate",
            "100",
            "--lag-budget",
            "30",
            "--no-plots",
            "--quiet",
            "--out",
            str(out),
        ]
    )
    stdout, stderr = ros_procs.finish(run, timeout=240)
    # the realtime preset holds its funnels; stale wrenches on a loaded machine are counted faults
    assert run.returncode == 0, stdout + stderr
    recorded = load_run(out / "bag", formation=REALTIME)
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
