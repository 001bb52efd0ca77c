"""The agents' gains in a ROS 2 parameters file (formation_agent.parameters_file), read without ROS."""

from __future__ import annotations

from pathlib import Path

import pytest

from formation_agent.parameters_file import agent_gains
from formation_core.errors import FormationSpecError

IDS = ("1", "2", "3", "4", "5")


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(text)
    return path


def test_wildcards_nesting_and_file_order(tmp_path: Path) -> None:
    """/** sets every agent, a later matching entry replaces an earlier value whatever its specificity, a
    nested entry names one node, an entry for another node changes nothing."""
    path = write(
        tmp_path,
        """
/**:
  ros__parameters:
    gamma: 12.0
    use_sim_time: true
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
  ros__parameters: {}
/formation_sim:
  ros__parameters:
    gamma: 99.0
""",
    )
    gains = agent_gains(path, IDS)
    assert gains["3"] == {"gamma": 20.0, "delta": 0.2}
    assert gains["4"] == {"gamma": 12.0, "delta": 0.3}
    assert gains["1"] == {"gamma": 12.0, "delta": 0.2}


def test_a_file_for_other_nodes_sets_nothing(tmp_path: Path) -> None:
    """A file without an entry matching an agent's node leaves every agent to its formation file."""
    path = write(tmp_path, "/robot/driver:\n  ros__parameters:\n    gamma: 3.0\n")
    assert agent_gains(path, IDS) == {}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("/**:\n  ros__parameters:\n    gamma: 12\n", "/**: gamma: 12 is an integer, not a double (write 12.0)"),
        ("/**:\n  ros__parameters:\n    gamma: -1.0\n", "gamma: -1.0 must be > 0"),
        ("/**:\n  ros__parameters:\n    delta: fast\n", "delta: 'fast' is str, not a double"),
        ("gamma: 12.0\n", "sets no ros__parameters of any node"),
        ("/**:\n  ros__parameters: [1, 2]\n", "/**: ros__parameters is not a mapping"),
        ("{", "is not YAML"),
    ],
)
def test_a_bad_file_is_named_with_the_entry_and_value(tmp_path: Path, text: str, message: str) -> None:
    """Every refusal names the file, the entry and the value (exit 2 where a runner reads it)."""
    path = write(tmp_path, text)
    with pytest.raises(FormationSpecError) as err:
        agent_gains(path, IDS)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(FormationSpecError, match=r"nothing\.yaml: No such file"):
        agent_gains(tmp_path / "nothing.yaml", IDS)
