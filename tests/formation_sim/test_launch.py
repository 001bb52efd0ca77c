"""formation-launch's own part of summary.json (no processes): the agents' fault counts merged in."""

from __future__ import annotations

from pathlib import Path

from formation_msgs_py.faults import FaultLog, write_json
from formation_sim.launch.launcher import agent_faults_file, merge_agent_faults


def test_agent_fault_files_are_merged_and_missing_ones_named(tmp_path: Path) -> None:
    sim = FaultLog()
    sim.add(0.1, "1", "resent_step")
    agent1 = FaultLog()
    agent1.add(0.3, "1", "refused_bad_quaternion", "norm 2")
    agent1.add(0.4, "1", "refused_bad_quaternion", "norm 0")
    agent1.add(0.5, "1", "reset", "/clock jumped by -0.5 s")
    write_json(agent_faults_file(tmp_path, "1"), agent1.as_dict())
    write_json(agent_faults_file(tmp_path, "2"), {})  # an agent without faults
    summary = {"faults": sim.as_dict()}
    merge_agent_faults(summary, tmp_path, ["1", "2", "3"])
    assert set(summary["faults"]["1"]) == {"resent_step", "refused_bad_quaternion", "reset"}
    refused = summary["faults"]["1"]["refused_bad_quaternion"]
    assert (refused["count"], refused["first_t"], refused["last_t"]) == (2, 0.3, 0.4)
    assert summary["agent_faults_unknown"] == ["3"]  # killed before it could write its counts
