"""A lockstep run with an outsider forging agent 3's wrench is never PASS (nor a FAIL blamed on the
controller): INCOMPLETE, untrusted input, the verdict block naming the outsider by node and GID."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from ros_helpers import REALTIME, executable, launch_beside_a_forger


@pytest.mark.parametrize("policy", ["report", "refuse"])
def test_lockstep_run_with_a_forged_wrench_is_untrusted(ros_env: dict[str, str], tmp_path: Path, policy: str) -> None:
    """Lockstep, 1 s: an outsider answers each of agent 3's steps with 50 N stamped like agent 3's own. Report:
    exit 4; refuse: agent 3's own wrenches are refused, so it may stop answering (exit 3); either way the
    verdict is INCOMPLETE with the untrusted input named (node, GID, topic, counts) in summary and output."""
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(REALTIME), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--mode", "lockstep", "--duration", "1", "--physics-rate", "100", "--intruder-policy", policy]
    cmd += ["--step-timeout", "2"]  # refuse: agent 3 counts as missing after 2 s, not the default's longer wait
    code, log, _ = launch_beside_a_forger(cmd, ros_env)
    assert code in ((4,) if policy == "report" else (3, 4)), log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"] == "INCOMPLETE", log
    assert "untrusted input: " in summary["incomplete_reason"], summary["incomplete_reason"]
    gid = next(i["gid"] for i in summary["security"]["intruders"] if i["node"] == "/outsider")
    named = rf"^  intruder: node /outsider gid {gid} on /agent_3/wrench \(\d+ applied, \d+ refused\)$"
    assert re.search(named, log, re.M), log
