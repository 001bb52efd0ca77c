"""formation-param's reading of VALUE (as `ros2 param set`, integers made floats for double parameters)."""

from __future__ import annotations

import pytest

from formation_ros.param_cli import build_parser, parse_value

DOUBLE, STRING, NOT_SET, DOUBLE_ARRAY = 3, 4, 0, 8  # rcl_interfaces/msg/ParameterType


@pytest.mark.parametrize(
    ("text", "declared", "expected"),
    [
        ("2", DOUBLE, 2.0),
        ("2.5", DOUBLE, 2.5),
        ("true", NOT_SET, True),
        ("7", NOT_SET, 7),
        ("best-effort", STRING, "best-effort"),
        ("3", STRING, "3"),
        ("[1, 2.5]", DOUBLE_ARRAY, [1.0, 2.5]),
        ("a: [", NOT_SET, "a: ["),
    ],
)
def test_values_read_as_declared(text: str, declared: int, expected: object) -> None:
    """YAML scalars, typed by the declaration where it says double or string; invalid YAML is text."""
    value = parse_value(text, declared)
    assert value == expected and type(value) is type(expected)


def test_verbs_take_their_arguments() -> None:
    """set needs NODE NAME VALUE; list NODE alone."""
    args = build_parser().parse_args(["set", "/agent_3/formation_agent", "gamma", "12"])
    assert (args.verb, args.node, args.name, args.value) == ("set", "/agent_3/formation_agent", "gamma", "12")
    assert build_parser().parse_args(["list", "/formation_sim"]).node == "/formation_sim"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["set", "/formation_sim", "marker_rate"])
