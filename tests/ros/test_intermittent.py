"""Failures seen only now and then, made measurable: each scenario run many times beside two busy loops.

- ``killed_agent``: tests/ros/test_lockstep.py's killed agent (SIGKILL of agent 3 mid-run in a paper
  lockstep run): the simulator names it and exits 3 within its step timeout and the last call.
- ``forty_agents``: tests/ros/test_discovery_server.py's 40-agent lockstep run through a discovery
  server (42 processes starting at once): it ends with exit 0 and no process needs SIGKILL.
- ``secure_outsiders``: tests/ros/test_secure.py's secure realtime launch in a private network namespace
  beside four outsiders: it ends (exit 4, untrusted input: the member), the outsiders reach nothing.

Opt-in (10-30 s a run, beside the busy loops): ``FORMATION_STRESS=1 .venv/bin/python -m pytest
tests/ros/test_intermittent.py -s``; ``FORMATION_STRESS_RUNS=N`` runs each scenario N times (default
20); ``FORMATION_STRESS_REPORT=DIR`` also writes DIR/SCENARIO.json and .txt (runs, failures by kind,
wall time per run, the 1-minute load at each run's start) and keeps each failed run's files in
DIR/SCENARIO/run_NN. The report is printed either way; a scenario with any failure fails.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
from ros_helpers import (
    Procs,
    forty_agents_through_a_discovery_server,
    lockstep_with_a_killed_agent,
    secure_run_beside_outsiders,
)

from formation_sim.launch.dds_env import netns_available, transport_environment

pytestmark = pytest.mark.skipif(
    os.environ.get("FORMATION_STRESS") != "1",
    reason="opt-in (each intermittent scenario 20 times beside two busy loops, long): FORMATION_STRESS=1",
)

RUNS = int(os.environ.get("FORMATION_STRESS_RUNS", "20"))


def _report_dir() -> Path | None:
    given = os.environ.get("FORMATION_STRESS_REPORT")
    return Path(given) if given else None


def _stress(scenario: str, tmp_path: Path, run_once: Callable[[Path], tuple[list[str], dict]]) -> None:
    """Run ``run_once(WORK)`` (the failures of one run, ``kind: detail`` each, and what it measured)
    RUNS times in fresh directories; print and write the report; assert no run failed."""
    rows = []
    for k in range(RUNS):
        work = tmp_path / f"run_{k:02d}"
        work.mkdir()
        load = os.getloadavg()[0]
        started = time.monotonic()
        failures, measured = run_once(work)
        wall = time.monotonic() - started
        rows.append({"run": k, "wall_s": wall, "load_1min": load, "failures": failures, **measured})
        print(f"{scenario} run {k}: {failures or 'ok'} {measured} ({wall:.1f} s, load {load:.1f})", flush=True)
        kept = _report_dir()
        if failures and kept is not None:
            shutil.copytree(work, kept / scenario / f"run_{k:02d}", symlinks=True, dirs_exist_ok=True)
    kinds = Counter(f.split(":", 1)[0] for row in rows for f in row["failures"])
    walls, loads = [row["wall_s"] for row in rows], [row["load_1min"] for row in rows]
    report = {
        "scenario": scenario,
        "runs": len(rows),
        "failed_runs": sum(1 for row in rows if row["failures"]),
        "failures_by_kind": dict(kinds),
        "wall_s": {"min": min(walls), "median": statistics.median(walls), "max": max(walls)},
        "load_1min": {"min": min(loads), "median": statistics.median(loads), "max": max(loads)},
        "rows": rows,
    }
    text = (
        f"{scenario}: {report['failed_runs']} of {len(rows)} runs failed{f' {dict(kinds)}' if kinds else ''}; "
        f"wall per run {min(walls):.1f}/{statistics.median(walls):.1f}/{max(walls):.1f} s (min/median/max), "
        f"1-minute load {min(loads):.1f}/{statistics.median(loads):.1f}/{max(loads):.1f}"
    )
    print(text, flush=True)
    kept = _report_dir()
    if kept is not None:
        kept.mkdir(parents=True, exist_ok=True)
        (kept / f"{scenario}.json").write_text(json.dumps(report, indent=1) + "\n")
        (kept / f"{scenario}.txt").write_text(text + "\n")
    failed = [(row["run"], row["failures"]) for row in rows if row["failures"]]
    assert not failed, (text, failed)


def test_a_killed_agent_is_named_in_every_run(busy_loops: list[int], ros_env: dict[str, str], tmp_path: Path) -> None:
    """SIGKILL of agent 3 mid-run, RUNS times beside two busy loops: every time the simulator names it, exit 3."""
    env = dict(ros_env, PYTHONFAULTHANDLER="1")  # a simulator stopped by SIGABRT writes its Python stacks

    def run_once(work: Path) -> tuple[list[str], dict]:
        (work / "proclogs").mkdir()
        procs = Procs(transport_environment(env), work / "proclogs")  # as the procs fixture
        try:
            run = lockstep_with_a_killed_agent(procs, work / "out")
        finally:
            procs.stop_all()
        return run.failures(), {"exit": run.code, "kill_to_exit_s": round(run.elapsed, 2)}

    _stress("killed_agent", tmp_path, run_once)


def test_a_secure_run_beside_outsiders_ends_in_every_run(
    busy_loops: list[int], ros_domain_id: int, tmp_path: Path
) -> None:
    """The secure realtime launch beside four outsiders in a private network namespace, RUNS times beside
    two busy loops: every time it ends, exit 4 (untrusted input: the member), no outsider reached it."""
    reason = netns_available()
    if reason is not None:
        pytest.skip(reason)

    def run_once(work: Path) -> tuple[list[str], dict]:
        run = secure_run_beside_outsiders(work, ros_domain_id)
        return run.failures(), {"launch_exit": (run.result() or {}).get("launch"), "driver_s": round(run.elapsed, 1)}

    _stress("secure_outsiders", tmp_path, run_once)


def test_forty_agents_through_a_discovery_server_end_cleanly_in_every_run(
    busy_loops: list[int], ros_env: dict[str, str], tmp_path: Path
) -> None:
    """The 40-agent discovery-server run, RUNS times beside two busy loops: every time exit 0, and every
    process stopped by itself (no SIGKILL)."""

    def run_once(work: Path) -> tuple[list[str], dict]:
        run = forty_agents_through_a_discovery_server(ros_env, work)
        return run.failures(), {"exit": run.code}

    _stress("forty_agents", tmp_path, run_once)
