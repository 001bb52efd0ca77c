"""The output directory of a run: refused when not empty, cleared of an earlier run by --force."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from formation_core.options import LAUNCH, RunOptions
from formation_sim import preflight
from formation_sim.preflight import (
    InvalidRunError,
    check_out_dir,
    duration_problem,
    load_spec,
    prepare_out_dir,
)


def _earlier_run(out: Path) -> None:
    """What formation-launch leaves in OUT (figures listed by its summary, a bag, an animation)."""
    (out / "bag").mkdir(parents=True)
    (out / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}")
    for name in ("trajectory.npz", "errors.png", "animation.gif"):
        (out / name).write_bytes(b"old")
    outputs = ["trajectory.npz", "errors.png", "../outside.txt", "/etc/hostname", "summary.json"]
    (out / "summary.json").write_text(json.dumps({"verdict": "PASS", "outputs": outputs}))


def test_a_non_empty_directory_needs_force(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _earlier_run(out)
    with pytest.raises(InvalidRunError, match="--force"):
        prepare_out_dir(out, force=False)
    assert (out / "summary.json").is_file()


def test_force_removes_the_earlier_run_and_nothing_else(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _earlier_run(out)
    (out / "notes.txt").write_text("mine")
    (out / "logs").mkdir()  # formation-launch clears its own logs; the simulator it starts must not
    (tmp_path / "outside.txt").write_text("not OUT's")
    prepare_out_dir(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["logs", "notes.txt"]
    assert (tmp_path / "outside.txt").read_text() == "not OUT's"  # a summary cannot name a path outside OUT


def test_force_without_a_readable_summary_still_removes_the_run_outputs(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _earlier_run(out)
    (out / "summary.json").write_text("{truncated")  # a full disk cut it short
    prepare_out_dir(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["errors.png"]  # only the summary named it


def _options(paper_path: Path, **kw) -> RunOptions:
    return RunOptions(command=LAUNCH, file=paper_path, **kw)


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ({"duration": 1e-12}, r"^--duration 1e-12 s is shorter than one control period: 0\.0001 s at 10000 Hz "),
        ({"duration": 1e12}, r"^--duration 1e\+12 s is longer than any run \(at most 604800 s, a week\)$"),
        ({"control_rate": 5e8}, r"^simulation\.duration in .*paper_5agents\.yaml 5 s at a physics rate of 5e\+08 Hz "
         r"\(--control-rate\) is 2\.5e\+09 steps, more than any run takes \(at most 1e\+09\)$"),
        ({"control_rate": 1e12}, r"^control rate 1e\+12 Hz \(--control-rate\) has a period under a nanosecond"),
        ({"duration": 5e4, "record_rate": 1e4}, r"^--duration 50000 s recorded at 10000 Hz \(--record-rate\) keeps "
         r"5e\+08 trajectory rows \(544 GB\), more than this machine's memory \(8 GB\)$"),
    ],
)  # fmt: skip
def test_durations_no_run_can_take_are_refused_naming_the_option(
    paper_path: Path, given: dict, expected: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No step, a period under a nanosecond, longer than a week, more than 1e9 physics steps, a trajectory
    beyond the machine's memory (8 GB here; a row is 5 agents × 192 B + 4 edges × 32 B)."""
    monkeypatch.setattr(preflight, "physical_memory", lambda: 8_000_000_000)
    options = _options(paper_path, **given)
    problem = duration_problem(load_spec(options), options)
    assert problem is not None and re.search(expected, problem), problem


def test_a_run_of_one_control_period_is_valid(paper_path: Path) -> None:
    """Exactly one control period (10 kHz: 1e-4 s) takes one step: accepted."""
    options = _options(paper_path, duration=1e-4)
    assert duration_problem(load_spec(options), options) is None


def test_out_that_cannot_be_a_directory_is_named_and_left_alone(tmp_path: Path) -> None:
    """--out FILE, a path below a file, a non-empty directory, an unwritable place: one reason each, nothing made."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(InvalidRunError, match=r"output directory .*afile is a file, not a directory$"):
        check_out_dir(afile, force=True)
    with pytest.raises(InvalidRunError, match=r"output directory .*afile/sub: .*afile is a file, not a directory$"):
        prepare_out_dir(afile / "sub", force=False)
    with pytest.raises(InvalidRunError, match=r"/proc/sys is not writable \(permission denied\)$"):
        check_out_dir(Path("/proc/sys/formation-out"), force=False)
    check_out_dir(tmp_path / "new" / "out", force=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
