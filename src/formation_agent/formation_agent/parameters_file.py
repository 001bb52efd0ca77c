"""The agents' gains in a ROS 2 parameters file, read as rclpy reads it for each agent node (no ROS).

A ROS user keeps one parameters file for a whole system and hands it to every node
(``--ros-args --params-file FILE``). :func:`agent_gains` gives what such a file sets of each
agent's live gains (``delta``, ``gamma``: :data:`formation_agent.synchroniser.LIVE_GAINS`), so that
a launcher can check it before anything starts and a headless run can use the same gains.

The reading follows rcl's (checked against rclpy in tests/ros/test_parameters_file.py): the top
level maps node names to ``ros__parameters``; a name may be written whole (``/agent_3/formation_agent``,
the leading ``/`` optional) or nested one level per namespace token (``agent_3: formation_agent:
ros__parameters:``); a token ``*`` matches one token of the node's full name and ``**`` any number;
every entry that matches applies, in the file's order, a later value replacing an earlier one.
Gains are doubles: an integer (``gamma: 12``) is refused, as rclpy refuses it for a parameter
declared as a double.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from formation_agent.synchroniser import LIVE_GAINS, live_gains
from formation_core.errors import FormationSpecError
from formation_msgs_py import topics

PARAMETERS_KEY = "ros__parameters"


def _entries(tree: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """(node-name tokens, the ros__parameters mapping) of every entry, in the file's order."""
    for key, value in tree.items():
        if key == PARAMETERS_KEY:
            yield prefix, value
        elif isinstance(value, Mapping):
            tokens = tuple(t for t in str(key).split("/") if t)
            yield from _entries(value, prefix + tokens)


def _pattern(tokens: Sequence[str]) -> re.Pattern[str]:
    """The full node names an entry's tokens match: ``*`` one token, ``**`` any number of them."""
    parts = []
    for token in tokens:
        if token == "**":
            parts.append(r"(?:/[^/]+)*")
        elif token == "*":
            parts.append(r"/[^/]+")
        else:
            parts.append("/" + re.escape(token))
    return re.compile("".join(parts) + r"\Z")


def _flatten(parameters: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested parameter names joined with dots, as rcl reads them."""
    out: dict[str, Any] = {}
    for name, value in parameters.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = value
    return out


def read_parameters_file(path: Path) -> list[tuple[tuple[str, ...], dict[str, Any]]]:
    """Every entry of a ROS 2 parameters file: (node-name tokens, {parameter: value}), in file order.

    Raises FormationSpecError naming the file for one that is not YAML or not a parameters file.
    """
    try:
        tree = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FormationSpecError("--params-file", f"{path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise FormationSpecError("--params-file", f"{path} is not YAML: {exc}") from None
    if not isinstance(tree, Mapping):
        raise FormationSpecError("--params-file", f"{path} is not a ROS 2 parameters file (a mapping of node names)")
    entries = []
    for tokens, parameters in _entries(tree):
        if not isinstance(parameters, Mapping):
            where = "/" + "/".join(tokens)
            raise FormationSpecError("--params-file", f"{path}: {where}: {PARAMETERS_KEY} is not a mapping")
        entries.append((tokens, _flatten(parameters)))
    if not entries:
        raise FormationSpecError("--params-file", f"{path} sets no {PARAMETERS_KEY} of any node")
    return entries


def agent_gains(path: Path, agent_ids: Sequence[str]) -> dict[str, dict[str, float]]:
    """{agent id: {gain: value}} of the live gains ``path`` sets for each agent's node
    (``/agent_<id>/formation_agent``); agents it sets nothing for are left out.

    Raises FormationSpecError naming the file, the entry and the value of a gain that is not a
    double, or out of its range (the formation file's rules for ``agents[].controller``).
    """
    entries = read_parameters_file(path)
    out: dict[str, dict[str, float]] = {}
    for agent in agent_ids:
        node = topics.agent_node(agent)
        values: dict[str, Any] = {}
        for tokens, parameters in entries:
            if _pattern(tokens).match(node):
                for name in LIVE_GAINS:
                    if name in parameters:
                        values[name] = (tokens, parameters[name])
        gains: dict[str, float] = {}
        for name, (tokens, value) in values.items():
            where = f"{path}: /{'/'.join(tokens)}: {name}"
            if isinstance(value, bool) or not isinstance(value, float):
                kind = "an integer" if isinstance(value, int) and not isinstance(value, bool) else type(value).__name__
                hint = f" (write {float(value)!r})" if kind == "an integer" else ""
                raise FormationSpecError("--params-file", f"{where}: {value!r} is {kind}, not a double{hint}")
            gains[name] = value
        try:
            checked = live_gains(agent, gains)
        except FormationSpecError as exc:
            raise FormationSpecError("--params-file", f"{path}: {exc}") from None
        if checked:
            out[agent] = checked
    return out
