"""formation_agent.parameters_file reads a parameters file as rclpy does: the gains of every agent node equal
what an rclpy node of that name declares from the same file; a lockstep run with such a file equals the
headless run with the same gains, and its summary says where each agent's gains came from."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rclpy.node import Node
from ros_helpers import PAPER, assert_equals_headless, executable, ros_context, run

from formation_agent.parameters_file import agent_gains
from formation_core.spec import load_formation
from formation_msgs_py import topics

IDS = load_formation(PAPER).agent_ids

FILES = {
    "wildcards and order": """
/**:
  ros__parameters:
    gamma: 12.0
/agent_3/formation_agent:
  ros__parameters:
    gamma: 20.0
/**/formation_agent:
  ros__parameters:
    delta: 0.2
agent_4:
  formation_agent:
    ros__parameters:
      delta: 0.3
/*/formation_agent:
  ros__parameters:
    gamma: 14.0
/agent_5/formation_agent:
  ros__parameters:
    gamma: 18.0
""",
    "one agent": "agent_2/formation_agent:\n  ros__parameters:\n    delta: 0.05\n",
}


@pytest.mark.parametrize("name", sorted(FILES))
def test_gains_as_rclpy_reads_them(ros_env: dict[str, str], tmp_path: Path, name: str) -> None:
    """For every agent, delta and gamma declared by an rclpy node /agent_<id>/formation_agent from the file
    are what agent_gains gives (the formation file's where the file sets none)."""
    path = tmp_path / "params.yaml"
    path.write_text(FILES[name])
    ours = agent_gains(path, IDS)
    spec = load_formation(PAPER)
    with ros_context(ros_env, ("--params-file", str(path))) as context:
        for agent in IDS:
            file_gains = spec.agent(agent).controller
            node = Node(topics.AGENT_NODE_NAME, namespace="/" + topics.agent_frame(agent), context=context)
            try:
                got = {g: node.declare_parameter(g, float(getattr(file_gains, g))).value for g in ("delta", "gamma")}
            finally:
                node.destroy_node()
            expected = {"delta": file_gains.delta, "gamma": file_gains.gamma, **ours.get(agent, {})}
            assert got == expected, agent


def test_a_lockstep_run_with_a_parameters_file_equals_the_headless_one(ros_env: dict[str, str], tmp_path: Path) -> None:
    """formation-launch --params-file hands the file to every agent: the run equals formation-headless's with
    the same file, bit for bit, and summary.json says agent 3 used γ = 20 and agent 4 δ = 0.3 from its
    parameters from t = 0."""
    path = tmp_path / "params.yaml"
    path.write_text(FILES["wildcards and order"])
    out = tmp_path / "out"
    duration = 0.1
    code, log = run(
        [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--no-record", "--quiet",
         "--duration", str(duration), "--record-rate", "10000", "--params-file", str(path)],
        ros_env,
    )  # fmt: skip
    assert code == 0, log
    gains = agent_gains(path, IDS)
    assert_equals_headless(out / "trajectory.npz", duration, gains=gains)
    witness = json.loads((out / "summary.json").read_text())["witness"]["agents"]
    for agent in IDS:
        (used,) = witness[agent]["gains"]
        assert (used["delta"], used["gamma"]) == (gains[agent]["delta"], gains[agent]["gamma"]), used
        assert used["source"] == "parameters" and used["from_t"] == 0.0, used
        assert witness[agent]["judged"] == "bit for bit", witness[agent]
