"""One spelling per option: a command-line option, the node parameter it sets and docs/ros2.md agree
(name with ``_`` for ``-``, the same values, the same default), checked on the nodes' declared
parameters."""

from __future__ import annotations

import re
import tokenize

import pytest
from rclpy.node import Node
from ros_helpers import PAPER, REPO, ros_context

from formation_agent.agent_node import AgentNode
from formation_agent.entry_point import USAGE
from formation_core import options
from formation_sim.node.display import declare_simulator_parameters
from formation_sim.node.sim_options import sim_parser, sim_preflight

OPTION = {o.dest: o for o in options.OPTIONS}
ROS_OWN = {"use_sim_time", "start_type_description_service"}  # declared by rclpy itself
_DOC = (REPO / "docs" / "ros2.md").read_text(encoding="utf-8")
PARAMETERS_DOC = _DOC[_DOC.index("## Parameters") : _DOC.index("\n## ", _DOC.index("## Parameters") + 1)]
#: agent parameters formation-launch sets from its own options (``-p NAME:=VALUE``)
LAUNCHED = set(
    re.findall(r'f"(\w+):=\{args\.\1\}"', (REPO / "src/formation_sim/formation_sim/launch/launcher.py").read_text())
)


def declared(node: Node) -> dict[str, tuple[object, str]]:
    """{name: (value, description)} of every parameter the node declared."""
    names = [n for n in node.list_parameters([], 0).names if n not in ROS_OWN]
    values = [p.value for p in node.get_parameters(names)]
    return {n: (v, d.description) for n, v, d in zip(names, values, node.describe_parameters(names))}


def check_spelling(params: dict[str, tuple[object, str]], command_line: str) -> None:
    for name, (_, description) in params.items():
        assert description, f"{name} has no description"
        assert f"`{name}`" in PARAMETERS_DOC, f"docs/ros2.md, Parameters: `{name}` missing"
        option = OPTION.get(name)
        if option is None:
            continue
        for choice in option.choices:
            for where, text in (("description", description), ("docs/ros2.md", PARAMETERS_DOC), ("", command_line)):
                assert re.search(rf"\b{choice}\b", text), f"{name}: {option.flag} value {choice!r} not in {where}"


def test_agent_parameters_spelled_as_the_options(ros_env: dict[str, str]) -> None:
    """Every agent parameter the launcher sets from an option has that option's name, values and default,
    and the agent accepts each of the option's values."""
    assert LAUNCHED == {"measurement_qos", "intruder_policy"}, LAUNCHED
    with ros_context(ros_env, ["-p", f"formation_file:={PAPER}"]) as context:
        node = AgentNode("3", context=context)
        params = declared(node)
        node.destroy_node()
    check_spelling(params, USAGE)
    for name in LAUNCHED:
        assert params[name][0] == OPTION[name].default, (name, params[name][0], OPTION[name].default)
        for choice in OPTION[name].choices:
            with ros_context(ros_env, ["-p", f"formation_file:={PAPER}", "-p", f"{name}:={choice}"]) as context:
                node = AgentNode("3", context=context)
                assert node.get_parameter(name).value == choice
                node.destroy_node()


def test_simulator_parameters_spelled_as_the_options(ros_env: dict[str, str]) -> None:
    """The simulator's parameters are its options' names with their values, as formation-sim declares them."""
    run = sim_preflight(["formation-sim", str(PAPER), "--measurement-qos", "reliable", "--marker-rate", "12.5"])
    with ros_context(ros_env) as context:
        node = Node("formation_sim", context=context)
        declare_simulator_parameters(node, run.spec, run.options)
        params = declared(node)
        node.destroy_node()
    assert params["measurement_qos"][0] == "reliable" and params["marker_rate"][0] == 12.5
    assert params["mode"][0] == "lockstep" and params["formation_file"][0] == str(PAPER)
    for name in params:
        assert name == "formation_file" or options.SIM in OPTION[name].commands, f"formation-sim has no --{name}"
    check_spelling(params, sim_parser().format_help())


@pytest.mark.parametrize(
    "option", [o for o in options.OPTIONS if any("-" in c for c in o.choices)], ids=lambda o: o.flag
)
def test_no_other_spelling_of_option_values(option: options.Option) -> None:
    """A value spelled with ``-`` (best-effort) has no ``_`` twin in what users read (README, docs,
    scripts) or in a string of the code (help texts, parameter values)."""
    texts = {f: f.read_text(encoding="utf-8") for f in [REPO / "README.md", *(REPO / "docs").glob("*.md")]}
    texts.update({f: f.read_text(encoding="utf-8") for f in (REPO / "ros2_ws").glob("*.sh")})
    for f in (REPO / "src").rglob("*.py"):
        with f.open("rb") as stream:
            tokens = tokenize.tokenize(stream.readline)
            texts[f] = "\n".join(t.string for t in tokens if t.type == tokenize.STRING)
    for choice in (c for c in option.choices if "-" in c):
        twin = choice.replace("-", "_")
        found = [str(f.relative_to(REPO)) for f, text in texts.items() if twin in text]
        assert not found, f"{option.flag} {choice}: spelled {twin} in {found}"
