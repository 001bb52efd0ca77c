"""Faults counted per agent and kind, merged across processes, printed with first and last."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from formation_core.faults import FaultLog, fault_lines, fault_meanings, write_atomic, write_json


def test_every_fault_is_counted_with_its_first_and_last() -> None:
    log = FaultLog()
    assert log.add(0.5, "2", "stale_command", "held the wrench of t=0.4900 s")
    for k in range(1, 100):
        assert not log.add(0.5 + k * 0.01, "2", "stale_command", f"tick {k}")
    log.add(0.2, "3", "reset", "clock back")
    got = log.as_dict()
    assert got["2"]["stale_command"] == {
        "count": 100,
        "first_t": 0.5,
        "last_t": 0.5 + 99 * 0.01,  # the time given, stored as is
        "first": "held the wrench of t=0.4900 s",
        "last": "tick 99",
    }
    assert got["3"]["reset"]["count"] == 1


def test_merge_adds_counts_and_keeps_the_earliest_first_and_latest_last() -> None:
    """An agent's own log merged into the simulator's: counts add, the extremes win, kinds stay apart."""
    sim, agent = FaultLog(), FaultLog()
    sim.add(1.0, "1", "stale_command", "a")
    sim.add(2.0, "1", "stale_command", "b")
    agent.add(0.5, "1", "stale_command", "early")
    agent.add(1.5, "1", "stale_command", "middle")
    agent.add(0.7, "1", "refused_non_finite", "NaN")
    sim.merge(agent.as_dict())
    got = sim.as_dict()["1"]
    assert got["stale_command"] == {"count": 4, "first_t": 0.5, "last_t": 2.0, "first": "early", "last": "b"}
    assert got["refused_non_finite"] == {"count": 1, "first_t": 0.7, "last_t": 0.7, "first": "NaN", "last": "NaN"}


def test_fault_lines_print_count_first_and_last() -> None:
    log = FaultLog()
    log.add(0.25, "4", "missing_pose", "3")
    log.add(0.75, "4", "missing_pose", "3, 5")
    log.add(0.1, "simulator", "late_tick", "6.0 ms late")
    assert fault_lines(log.as_dict()) == [
        "  fault: agent 4: missing_pose x2: first t=0.2500 s (3), last t=0.7500 s (3, 5)",
        "  fault: agent simulator: late_tick x1: first t=0.1000 s (6.0 ms late)",
    ]


def test_write_json_is_strict_and_atomic(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    write_json(path, {"nan": math.nan, "inf": np.float64(np.inf), "n": np.int64(3), "a": np.arange(2)})
    assert json.loads(path.read_text()) == {"nan": None, "inf": None, "n": 3, "a": [0, 1]}
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"]  # no temporary file left


def test_fault_meanings_explain_each_kind_once_in_words() -> None:
    """Every kind present gets one line of meaning (a refused kind by its prefix); none when no fault."""
    log = FaultLog()
    for agent in ("1", "2"):
        log.add(0.1, agent, "resent_step")
    log.add(0.2, "3", "refused_wrench_non_finite")
    lines = fault_meanings(log.as_dict())
    assert lines[0] == "  what the faults mean (none is a funnel violation):"
    assert [x.split(":")[0].strip() for x in lines[1:]] == ["refused_wrench_non_finite", "resent_step"]
    assert "simulator refused an agent's wrench" in lines[1] and "trajectory is the same" in lines[2]
    assert fault_meanings({}) == []


def test_write_atomic_follows_the_umask(tmp_path: Path) -> None:
    """Outputs get 0666 & ~umask like any new file (mkstemp alone gives 0600); an explicit mode wins."""
    old = os.umask(0o027)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
        os.umask(0o002)
        write_atomic(tmp_path / "b.bin", b"x")
        write_atomic(tmp_path / "c.bin", b"x", mode=0o600)
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "b.bin").stat().st_mode & 0o777 == 0o664
    assert (tmp_path / "c.bin").stat().st_mode & 0o777 == 0o600
