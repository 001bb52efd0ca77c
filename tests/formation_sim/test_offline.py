"""Offline analysis and controller re-run of recorded runs (no ROS), on the bag tests' synthetic bags."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "formation_bag"))  # bag_fixtures, bag_helpers, synth
import bag_fixtures
from bag_helpers import PAPER, VIOLATING, paper_spec

from formation_bag.contract import KEY_FORMATION_YAML
from formation_bag.dataset import RUN_SETTING_KEYS, apply_overrides, load_run
from formation_bag.reader import Bag
from formation_bag.writer import SegmentedBagWriter
from formation_core.errors import BagFormatError, OverrideError
from formation_sim.cli.headless import run_headless
from formation_sim.offline import analysis, rerun
from formation_sim.offline.analysis import analyze_run, message_ages
from formation_sim.offline.rerun import rerun_all

pytestmark = pytest.mark.numeric

# the bag tests' session fixtures, offered to this module's tests
short_bags = bag_fixtures.short_bags
violating_bag = bag_fixtures.violating_bag

IGNORED = {"wall_time", "real_time_factor", "bag", "source", "controller", "physics_rate", "mode", "samples"}


def assert_same_summary(ours: dict, theirs: dict, tol: float = 1e-9, path: str = "") -> None:
    """Same verdicts, violation and margins (to ``tol``); run-specific fields ignored.

    The analysis judges the ground-truth messages, whose rotations travel as quaternions (some ulps
    off the simulator's R): e and ψ move by some 1e-15, their margins by that over ρ (≥ 0.01): 1e-13.
    The velocity margins come from the re-run, bit for bit here. 1e-9 is far from any of it and from
    any change of a verdict."""
    for key, value in theirs.items():
        if key in IGNORED:
            continue
        where = f"{path}.{key}"
        assert key in ours, f"{where} missing"
        if isinstance(value, dict):
            assert_same_summary(ours[key], value, tol, where)
        elif isinstance(value, float) and isinstance(ours[key], float):
            assert abs(ours[key] - value) <= tol, f"{where}: {ours[key]} != {value}"
        else:
            assert ours[key] == value, f"{where}: {ours[key]!r} != {value!r}"


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_analysis_reproduces_the_runs_summary(short_bags, storage: str) -> None:
    """formation-analyze of a lockstep bag gives the run's own summary: verdicts and margins to 1e-9."""
    bag, result = short_bags[storage]
    run = load_run(bag)
    _, summary, reruns = analyze_run(run)
    assert_same_summary(summary, result.summary)
    assert summary["bag"]["ground_truth_samples"] == result.steps
    assert not summary["bag"]["truncated"]
    # the bag's wrenches were computed by this process's compiled controller on the same bytes
    assert all(r.max_abs_diff == 0.0 and r.compared == result.steps for r in reruns.values())


def test_analysis_of_a_violating_run(violating_bag, tmp_path: Path) -> None:
    """A run at a too-low control rate: the analysis names the agent, channel and time of the violation."""
    bag, result = violating_bag
    headless = run_headless(paper_spec(**VIOLATING), stop_on_violation=True).summary
    out = tmp_path / "out"
    code = analysis.main([str(bag), "--out", str(out)])
    assert code == 1
    summary = json.loads((out / "summary.json").read_text())
    fv = summary["first_violation"]
    assert fv == result.summary["first_violation"]  # exactly what the run itself recorded
    assert fv["kind"] == headless["first_violation"]["kind"] == "velocity"
    assert fv["agent"] == headless["first_violation"]["agent"] == "1"
    assert fv["channel"] == headless["first_violation"]["channel"] == "wz"
    # the agents computed from quaternion-coded poses: the unstable sampled loop amplifies the 1e-16
    # differences to the headless run (matrices), so the time agrees to some 20 steps only
    assert fv["t"] == pytest.approx(headless["first_violation"]["t"], abs=0.05)
    assert 1.0 < fv["t"] < 1.2
    assert summary["funnels_held"] is False
    for name in (
        "trajectory.npz",
        "errors.png",
        "orientation_errors.png",
        "inputs.png",
        "errors.csv",
        "inputs.csv",
        "positions.csv",
        "ages.json",
        "ages.csv",
    ):
        assert (out / name).exists(), name
    traj = np.load(out / "trajectory.npz")
    assert traj["p"].shape[1:] == (5, 3) and traj["e"].shape[1] == 4 and traj["u"].shape[2] == 6
    ages = json.loads((out / "ages.json").read_text())
    assert ages["log_time"] == "sim" and "relative_pose" not in ages  # lockstep log times: no ages to measure
    assert (out / "ages.csv").read_text().count("\n") == 1  # the header only
    # the distance/orientation funnels alone held until then; the bag stops there: INCOMPLETE, not PASS
    assert analysis.main([str(bag), "--out", str(tmp_path / "o2"), "--velocity-margins", "none", "--no-plots"]) == 4
    partial = json.loads((tmp_path / "o2" / "summary.json").read_text())
    assert partial["verdict"] == "INCOMPLETE" and partial["first_violation"] is None
    assert partial["incomplete_reason"].startswith("data missing: ground truth: ")
    # refuses to overwrite; --force replaces the earlier analysis, figures included
    assert analysis.main([str(bag), "--out", str(out)]) == 2
    assert analysis.main([str(bag), "--out", str(out), "--force", "--no-plots", "--velocity-margins", "none"]) == 4
    assert not (out / "errors.png").exists() and (out / "ages.csv").exists()
    assert json.loads((out / "summary.json").read_text())["verdict"] == "INCOMPLETE"


def test_analysis_of_a_truncated_bag(violating_bag, tmp_path: Path) -> None:
    """A bag that lost its last segment and its metadata.yaml is analysed as far as it goes."""
    src, result = violating_bag
    bag = tmp_path / "bag"
    shutil.copytree(src, bag)
    segs = sorted(bag.glob("bag_*.mcap"), key=lambda p: int(p.stem.split("_")[1]))
    (bag / "metadata.yaml").unlink()
    last = segs[-1]
    partial = bag / f".{last.stem}"
    partial.mkdir()
    data = last.read_bytes()
    (partial / f".{last.stem}.mcap").write_bytes(data[: len(data) // 2])  # as a killed recorder leaves it
    last.unlink()
    run = load_run(bag)
    assert run.recovered and len(run.lost) == 1
    _, summary, _ = analyze_run(run)
    assert summary["bag"]["truncated"]
    assert 0 < summary["bag"]["ground_truth_samples"] < result.steps
    assert summary["duration"] < result.summary["duration"]
    # what is left agrees with the full run up to there, and says what it lacks
    assert summary["verdict"] == "INCOMPLETE" and summary["first_violation"] is None
    assert summary["funnels_held"] is None
    assert any(item.startswith("lost ") for item in summary["bag"]["missing"])


def test_rerun_reproduces_and_reports_overrides(violating_bag, tmp_path: Path, capsys) -> None:
    """Re-running the recorded measurements reproduces every wrench; an override's changes are reported."""
    bag, result = violating_bag
    assert rerun.main([str(bag), "--out", str(tmp_path / "same")]) == 0
    report = json.loads((tmp_path / "same" / "rerun.json").read_text())
    assert report["equal"] and report["tolerance"] == "round-off bound"
    for a in report["agents"].values():  # computed by this process's compiled controller on the same bytes
        assert a["max_abs_diff"] == 0.0 and a["bit_for_bit"] == a["compared"] == result.steps
        assert a["largest_ratio_to_round_off"] == 0.0
    override = tmp_path / "gains.yaml"
    override.write_text(yaml.safe_dump({"agents": {"3": {"controller": {"gamma": 10.0}}}}))
    assert (
        rerun.main(
            [str(bag), "--agent", "3", "--agent", "1", "--override", str(override), "--out", str(tmp_path / "diff")]
        )
        == 1
    )
    report = json.loads((tmp_path / "diff" / "rerun.json").read_text())
    assert report["agents"]["1"]["equal"]  # agent 1's gains did not change
    a3 = report["agents"]["3"]
    assert not a3["equal"] and a3["first_difference"]["t"] == 0.0 and a3["max_abs_diff"] > 1e-3
    # γ scales the wrench: 10/15 of the recorded one at the first step
    rec = np.array(a3["first_difference"]["recorded"])
    # at the first step, below the actuator limits, u is linear in γ: 10/15 of it to a few roundings
    np.testing.assert_allclose(np.array(a3["first_difference"]["rerun"]), rec * 10.0 / 15.0, rtol=1e-9)
    out = capsys.readouterr().out
    assert "agent 3" in out and "DIFFERENT" in out


def test_rerun_out_refuses_a_used_directory_unless_forced(short_bags, tmp_path: Path, capsys) -> None:
    """--out into a non-empty directory exits 2 naming --force; with --force an earlier re-run's
    outputs (rerun.json, every rerun_<agent>.npz) are replaced and nothing else is touched."""
    bag, _ = short_bags["mcap"]
    out = tmp_path / "out"
    assert rerun.main([str(bag), "--agent", "1", "--out", str(out)]) == 0
    (out / "notes.txt").write_text("mine\n")
    assert rerun.main([str(bag), "--agent", "2", "--out", str(out)]) == 2
    assert "exists and is not empty (use --force to overwrite)" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "rerun.json", "rerun_1.npz"]
    assert rerun.main([str(bag), "--agent", "2", "--out", str(out), "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "rerun.json", "rerun_2.npz"]
    assert list(json.loads((out / "rerun.json").read_text())["agents"]) == ["2"]
    file_out = tmp_path / "a_file"
    file_out.write_text("")
    assert rerun.main([str(bag), "--out", str(file_out), "--force"]) == 2
    assert f"output directory {file_out} is a file, not a directory" in capsys.readouterr().err


def test_override_errors_name_the_field(violating_bag) -> None:
    """Bad override files are refused with the offending path."""
    run = load_run(violating_bag[0], need_ground_truth=False)
    with pytest.raises(OverrideError, match=re.escape("override.agents.9")):
        apply_overrides(run.document, {"agents": {"9": {"controller": {"gamma": 1.0}}}})
    with pytest.raises(OverrideError, match=re.escape("override.edges.2-4")):
        apply_overrides(run.document, {"edges": {"2-4": {}}})
    with pytest.raises(OverrideError, match=re.escape("override.gains")):
        apply_overrides(run.document, {"gains": {}})


def test_rerun_judges_a_recorded_wrench_by_its_steps_round_off_tolerance(short_bags) -> None:
    """A recorded wrench computed elsewhere (another host, libm or code form) may differ in the last places:
    within the step's round-off tolerance it is equal, beyond it (or beyond an explicit --tolerance) not."""
    run = load_run(short_bags["mcap"][0], need_ground_truth=False)
    r = rerun_all(run, ["2"])["2"]
    k = r.compared // 2
    assert np.all(r.tolerance[k] > 0)
    exact = r.recorded.copy()
    r.recorded[k] = exact[k] + 0.5 * r.tolerance[k]
    assert r.first_difference(None) is None
    report = r.report(None)
    assert report["bit_for_bit"] == r.compared - 1
    # the sum rounds to the wrench's last place, half an ulp at most; the tolerance is at least 4 ulp
    assert abs(report["largest_ratio_to_round_off"] - 0.5) <= 0.125
    assert r.first_difference(0.0) == k  # an explicit tolerance replaces the bound
    r.recorded[k, 4] = exact[k, 4] + 2.0 * r.tolerance[k, 4]
    assert r.first_difference(None) == k
    assert r.report(None)["first_difference"]["round_off_tolerance"] == r.tolerance[k].tolist()


def test_rerun_of_one_agent_only(short_bags) -> None:
    """One agent can be re-run alone; the others are not touched."""
    run = load_run(short_bags["mcap"][0], need_ground_truth=False)
    only = rerun_all(run, ["4"])
    assert list(only) == ["4"] and only["4"].max_abs_diff == 0.0


@pytest.mark.parametrize("command", ["analyze", "rerun"])
def test_a_closed_pipe_keeps_the_verdict_and_prints_no_traceback(violating_bag, tmp_path: Path, command: str) -> None:
    """`formation-analyze BAG | head -1` (and -rerun): the reader closes the pipe first; the command
    still ends with its own exit status (1: the run violates a funnel, a wrench differs under the
    override below) and its outputs, and nothing but progress reaches stderr."""
    bag, _ = violating_bag
    out = tmp_path / "out"
    if command == "analyze":
        args = ["-m", "formation_sim.offline.analysis", str(bag), "--no-plots", "--out", str(out)]
        expected = 1
    else:
        override = tmp_path / "override.yaml"
        override.write_text("agents: {'1': {controller: {gamma: 7.0}}}\n")
        args = [
            "-m",
            "formation_sim.offline.rerun",
            str(bag),
            "--agent",
            "1",
            "--override",
            str(override),
            "--out",
            str(out),
        ]
        expected = 1
    proc = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # closed before the first line: every write meets a closed pipe
    err = proc.stderr.read()
    assert proc.wait(timeout=300) == expected, err
    assert "Traceback" not in err and "Error" not in err, err
    assert (out / ("summary.json" if command == "analyze" else "rerun.json")).is_file()


def test_bag_without_formation_needs_one(tmp_path: Path, short_bags) -> None:
    """A bag without the formation file asks for --formation; with it, the analysis runs."""
    from synth import write_run_bag

    bag = tmp_path / "bag"
    write_run_bag(paper_spec(duration=0.01, control_rate=1000.0, physics_rate=1000.0), bag)
    with pytest.raises(BagFormatError, match="--formation"):
        load_run(bag)
    run = load_run(bag, formation=PAPER)
    assert len(run.ground_truth) == 11
    assert message_ages(run)["log_time"] == "sim"  # a lockstep bag: log times are no receive times
    # as if recorded with receive times (the synthesiser's log times advance 1 ms per step, 1 µs per message)
    run.custom_data["recorder_counts"] = json.dumps({"log_time": "receive"})
    ages = message_ages(run)
    assert ages["velocity"]["2"]["sim_age"]["count"] == 11
    assert ages["wrench"]["1"]["response_wall"]["median"] > 0


def _copy_without(
    src: Path, dst: Path, drop: Callable[[str, int], bool], custom_data: dict[str, str] | None = None
) -> None:
    """A copy of bag ``src`` without the messages ``drop(topic, stamp_ns)`` selects (with ``custom_data``
    instead of its own if given)."""
    from formation_msgs_py.codec import stamp_of

    custom = custom_data
    with (
        Bag(src) as bag,
        SegmentedBagWriter(dst, custom_data=dict(bag.custom_data) if custom is None else custom) as out,
    ):
        for t in bag.topics.values():
            out.add_topic(t.name, t.msgtype)
        for msg in bag.messages():
            if not drop(msg.topic, stamp_of(bytes(msg.data))):
                out.write(msg.topic, msg.log_time, msg.data)


def test_bag_with_messages_removed_is_incomplete_not_fail(short_bags, tmp_path: Path) -> None:
    """Ground truth and agent 2's velocity removed at 0.05-0.059 s, one wrench at 0.1 s: INCOMPLETE
    (exit 4) with the gaps listed, no violation; the re-run says where it could not compare."""
    src, result = short_bags["mcap"]
    assert result.summary["verdict"] == "PASS"
    bag = tmp_path / "holes"
    gap = range(50_000_000, 60_000_000)

    def drop(topic: str, stamp: int) -> bool:
        if topic in ("/formation/ground_truth", "/agent_2/velocity", "/agent_1/relative_pose/agent_2"):
            return stamp in gap
        return topic == "/agent_4/wrench" and stamp == 100_000_000

    _copy_without(src, bag, drop)
    out = tmp_path / "out"
    assert analysis.main([str(bag), "--out", str(out), "--no-plots"]) == 4
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"] == "INCOMPLETE" and summary["first_violation"] is None
    assert summary["bag"]["missing"] == [
        "ground truth: 10 steps missing (0.0500-0.0590 s)",
        "agent 2 velocity: 10 steps missing (0.0500-0.0590 s)",
        "agent 4 wrench: 1 steps missing (0.1000-0.1000 s)",
    ]
    assert summary["bag"]["ground_truth_missing"] == [[0.05, 0.059]]
    assert summary["incomplete_reason"].startswith("data missing: ground truth: 10 steps missing")
    # the margins of what is there are the run's own (a subset of its samples: at least as large)
    for name, edge in summary["edges"].items():
        assert edge["min_margin_e"] >= result.summary["edges"][name]["min_margin_e"] - 1e-12
    runs = rerun.rerun_all(load_run(bag))
    assert runs["1"].measurements_missing == 10 and runs["1"].first_difference(1e-12) is None
    assert runs["4"].compared == len(runs["4"].stamps) - 1
    assert rerun.main([str(bag)]) == 4  # equal where compared, data missing


def _restated(src: Path, dst: Path, formation_duration: float, **stated: str) -> None:
    """A copy of bag ``src`` whose formation file says ``formation_duration`` s and whose custom_data
    says of the run only ``stated`` (none: as formation-record --formation FILE writes it without --meta)."""
    with Bag(src) as bag:
        custom = {k: v for k, v in bag.custom_data.items() if k not in RUN_SETTING_KEYS}
    text = PAPER.read_text()
    assert "\n  duration: 5.0\n" in text
    custom[KEY_FORMATION_YAML] = text.replace("\n  duration: 5.0\n", f"\n  duration: {formation_duration!r}\n")
    _copy_without(src, dst, lambda _topic, _stamp: False, {**custom, **stated})


UNSAID = "the bag does not say what was run (no custom_data.duration: formation-record --meta duration=S)"


@pytest.mark.parametrize(
    ("file_duration", "stated", "code", "expected", "source", "requested", "note"),
    [
        # a 0.15 s run recorded without --meta from a file that says 0.05 s: checked to its end
        (0.05, {}, 0, 151, "recording", None,
         f"duration: {UNSAID}; its ground truth runs to 0.15 s, past the formation file's 0.05 s: analysed to 0.15 s"),
        # a bag that says less than it holds: its data wins, and it says so
        (5.0, {"duration": "0.05"}, 0, 151, "recording", None,
         "duration: the ground truth runs to 0.15 s, past the 0.05 s the bag says was run: analysed to 0.15 s"),
        # the bag says what was run (a command-line override of the file's duration)
        (0.05, {"duration": "0.15"}, 0, 151, "bag", 0.15,
         "duration: 0.15 s as the bag says; the formation file says 0.05 s"),
        # a bag that ends before the file's duration and does not say the run was shorter: never a PASS
        (5.0, {}, 4, 5001, "formation file", 5.0,
         f"duration: {UNSAID}; its ground truth ends at 0.15 s of the formation file's 5 s: the rest is missing data"),
    ],
)  # fmt: skip
def test_expected_samples_come_from_what_the_bag_says_was_run(
    short_bags, tmp_path: Path, capsys, file_duration: float, stated: dict[str, str], code: int, expected: int,
    source: str, requested: float | None, note: str,
) -> None:  # fmt: skip
    """The duration is the bag's (custom_data), else the recorded ground truth's where it runs past the
    formation file's, else the file's; a disagreement with the file is reported, a short bag is INCOMPLETE."""
    src, result = short_bags["mcap"]
    bag = tmp_path / "bag"
    _restated(src, bag, file_duration, **stated)
    out = tmp_path / "out"
    assert analysis.main([str(bag), "--out", str(out), "--no-plots"]) == code
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    b = summary["bag"]
    assert (b["ground_truth_samples"], b["ground_truth_expected"]) == (151, expected)
    # a sample per ms; the duration is a count of integer-ns stamps over 1e9: one rounding
    assert b["settings"]["duration"] == pytest.approx((expected - 1) / 1000, abs=1e-12)
    assert b["settings"]["from"]["duration"] == source and summary["requested_duration"] == requested
    assert note in b["settings"]["notes"]
    assert f"  note: {note}\n" in printed
    assert f"bag: 151 ground-truth samples of {expected} expected over " in printed
    if code == 0:  # every sample of the run checked: its margins, to the 1e-9 the analysis reproduces a run's
        assert summary["verdict"] == "PASS"
        assert summary["worst_margin"] == pytest.approx(result.summary["worst_margin"], abs=1e-9)
        assert b["missing"] == []
    else:
        assert summary["verdict"] == "INCOMPLETE" and summary["funnels_held"] is None
        assert b["missing"][0] == "ground truth: 4850 steps missing (0.1510-5.0000 s)"
    if not stated:  # nor does it say the control rate: the velocity stamps' (the file says 10 kHz)
        assert b["settings"]["control_rate"] == pytest.approx(1000.0, rel=1e-9)  # 1 ms stamps, integer ns
        assert (
            "control rate: 1000 Hz from the recorded stamps; the formation file says 10000 Hz" in b["settings"]["notes"]
        )


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("duration", "30 s", "custom_data.duration '30 s' is not a number"),
        ("control_rate", "-100", "custom_data.control_rate '-100' must be > 0"),
        ("mode", "fast", "custom_data.mode 'fast' is not one of lockstep, realtime"),
    ],
)
def test_a_bag_that_says_an_invalid_setting_is_refused(
    short_bags, tmp_path: Path, capsys, key: str, value: str, message: str
) -> None:
    """A bag whose custom_data states an invalid mode, rate or duration is bad input (exit 2), named."""
    src, _ = short_bags["mcap"]
    bag = tmp_path / "bag"
    with Bag(src) as b:
        custom = {**b.custom_data, key: value}
    _copy_without(src, bag, lambda _topic, _stamp: False, custom)
    assert analysis.main([str(bag), "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, err


_PEAK_RSS = """
import resource, subprocess, sys
code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
print(code, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def _analyze_peak_rss(bag: Path, out: Path) -> tuple[int, int]:
    """(exit status, peak RSS in KiB) of formation-analyze BAG, its only child measured by a fresh parent."""
    cmd = [sys.executable, "-c", _PEAK_RSS, sys.executable, "-m", "formation_sim.offline.analysis", str(bag)]
    done = subprocess.run([*cmd, "--out", str(out), "--no-plots"], capture_output=True, text=True, check=True)
    code, kib = done.stdout.split()
    return int(code), int(kib)


def test_analysis_memory_does_not_grow_with_the_bag(tmp_path: Path) -> None:
    """formation-analyze of a 5 s bag needs at most 60 MB more than of a 1 s bag (the decoded messages are
    kept compact), and its summary counts every topic the bag holds, /diagnostics, markers and funnels too."""
    from synth import write_run_bag

    peaks = {}
    for duration in (1.0, 5.0):
        bag = tmp_path / f"bag_{duration:g}s"
        spec = paper_spec(duration=duration, control_rate=1000.0, physics_rate=1000.0)
        write_run_bag(spec, bag, formation_text=PAPER.read_text(), segment_seconds=None, display_every=33)
        code, peaks[duration] = _analyze_peak_rss(bag, tmp_path / f"out_{duration:g}s")
        assert code in (0, 1)  # a verdict (the paper run at 1 kHz may leave a funnel), not an error
    # 80 000 more messages: ~134 MB more when each was held as Python objects, ~31 MB now (of which the
    # recorded trajectory at 1 kHz, an output, is most); 60 MB leaves room for the allocator's rounding
    assert peaks[5.0] - peaks[1.0] < 60 * 1024, peaks
    summary = json.loads((tmp_path / "out_5s" / "summary.json").read_text())
    with Bag(tmp_path / "bag_5s") as bag:
        listed = {t.name: t.count for t in bag.topics.values()}
    assert summary["bag"]["topics"] == listed
    assert listed["/diagnostics"] == listed["/formation/markers"] == listed["/formation/funnels"] == 152
    assert listed["/formation/ground_truth"] == 5001
