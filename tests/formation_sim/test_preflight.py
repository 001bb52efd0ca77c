"""The output directory of a run: refused when not empty, cleared of an earlier run by --force."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from formation_sim.core.preflight import InvalidRunError, prepare_out_dir


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
