"""ROS parameters with descriptors, declared the same way by every node (imports rcl_interfaces: nodes only).

Every parameter has a type, a description, a range where one applies, and ``read_only`` when a
change could not apply at run time (``ros2 param set`` on it then fails with "read-only").
Live parameters are applied by a node's set-parameters callback, which validates them and
returns the reason when it refuses a value.
"""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType

_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER}
_TYPES.update({float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING})


def declare(
    node: Any,
    name: str,
    default: Any,
    description: str,
    *,
    read_only: bool = False,
    low: float | None = None,
    high: float | None = None,
    any_type: bool = False,
    fixed: bool = False,
) -> Any:
    """Declare ``name`` (typed like ``default``, or any type) and return its value (overrides applied,
    except for a ``fixed`` one: a fact the node reports, which no parameters file or command line sets)."""
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only, dynamic_typing=any_type)
    if not any_type:
        desc.type = _TYPES[type(default)]
    if low is not None and high is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    return node.declare_parameter(name, default, desc, ignore_override=fixed).value
