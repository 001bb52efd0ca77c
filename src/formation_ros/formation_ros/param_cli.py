"""``formation-param list|get|set NODE [NAME [VALUE]]``: a node's parameters through rclpy's parameter
services (``rcl_interfaces/srv/ListParameters``, ``DescribeParameters``, ``GetParameters``,
``SetParameters``), for an install without the ``ros2`` command line (the project's venv).

``set`` reads VALUE as ``ros2 param set`` does (YAML: ``2.0``, ``true``, ``[1, 2]``, text) and
converts an integer to a float for a parameter declared as double (``gamma 2``). A refused set
(read-only, out of range, invalid: the node's reason) exits 1; a node whose services do not
answer within ``--timeout`` seconds exits 3. The command line is parsed before rclpy is imported.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

EXIT_REFUSED = 1
EXIT_USAGE = 2
EXIT_NO_NODE = 3


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-param",
        description="List, read or change a running node's parameters (what `ros2 param list|get|set` does), "
        "e.g. formation-param set /agent_3/formation_agent gamma 12. The node is found in ROS_DOMAIN_ID "
        "(formation-launch prints the run's) with ROS_AUTOMATIC_DISCOVERY_RANGE as for the run. Exit status: 0 "
        "done, 1 refused (the node's reason: read-only, out of range, invalid), 2 bad usage, 3 no answer from "
        'NODE. Parameters of each node: docs/ros2.md, "Parameters".',
    )
    p.add_argument("--timeout", type=float, default=10.0, help="wall s to wait for NODE's services (default 10)")
    sub = p.add_subparsers(dest="verb", required=True, metavar="list|get|set")
    ls = sub.add_parser("list", help="every parameter of NODE: name, value, read-only or live")
    ls.add_argument("node", metavar="NODE", help="full node name, e.g. /agent_3/formation_agent or /formation_sim")
    get = sub.add_parser("get", help="the value of NAME")
    get.add_argument("node", metavar="NODE")
    get.add_argument("name", metavar="NAME")
    put = sub.add_parser("set", help="set NAME to VALUE (YAML: 2.0, true, text)")
    put.add_argument("node", metavar="NODE")
    put.add_argument("name", metavar="NAME")
    put.add_argument("value", metavar="VALUE")
    return p


def parse_value(text: str, declared_type: int | None) -> Any:
    """VALUE as ``ros2 param set`` reads it (YAML scalar or list), an integer made a float for a double
    parameter (``declared_type``: rcl_interfaces ParameterType, None or 0 if not declared)."""
    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    if value is None:
        value = text
    if declared_type == 3 and isinstance(value, int) and not isinstance(value, bool):  # PARAMETER_DOUBLE
        value = float(value)
    if declared_type == 4 and not isinstance(value, str):  # PARAMETER_STRING: the text as given
        value = text
    if declared_type == 8 and isinstance(value, list):  # PARAMETER_DOUBLE_ARRAY
        value = [float(v) if isinstance(v, int) and not isinstance(v, bool) else v for v in value]
    return value


class ParamClient:
    """Blocking calls to one node's parameter services."""

    def __init__(self, target: str, timeout: float) -> None:
        import rclpy
        from rclpy.node import Node
        from rclpy.parameter_client import AsyncParameterClient

        rclpy.init(args=None)
        self.node = Node("formation_param", start_parameter_services=False)
        self.client = AsyncParameterClient(self.node, target)
        self.target = target
        self.timeout = timeout

    def ready(self) -> bool:
        return self.client.wait_for_services(timeout_sec=self.timeout)

    def call(self, future: Any) -> Any:
        import rclpy

        rclpy.spin_until_future_complete(self.node, future, timeout_sec=self.timeout)
        if not future.done():
            raise TimeoutError(f"{self.target} did not answer within {self.timeout:g} s")
        return future.result()

    def close(self) -> None:
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown()


def _show(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def run(args: argparse.Namespace) -> int:
    from rclpy.parameter import Parameter, parameter_value_to_python

    pc = ParamClient(args.node, args.timeout)
    try:
        if not pc.ready():
            print(
                f"formation-param: no node {args.node} answered within {args.timeout:g} s "
                "(is it running, in this ROS_DOMAIN_ID?)",
                file=sys.stderr,
            )
            return EXIT_NO_NODE
        if args.verb == "list":
            names = sorted(pc.call(pc.client.list_parameters()).result.names)
            descriptors = pc.call(pc.client.describe_parameters(names)).descriptors
            values = pc.call(pc.client.get_parameters(names)).values
            for name, desc, value in zip(names, descriptors, values):
                kind = "read-only" if desc.read_only else "live"
                print(f"{name} = {_show(parameter_value_to_python(value))}  ({kind})")
            return 0
        names = pc.call(pc.client.list_parameters()).result.names
        if args.name not in names:
            known = ", ".join(sorted(names))
            print(f"formation-param: {args.node} has no parameter {args.name!r} (has: {known})", file=sys.stderr)
            return EXIT_REFUSED
        descriptor = pc.call(pc.client.describe_parameters([args.name])).descriptors
        if args.verb == "get":
            value = pc.call(pc.client.get_parameters([args.name])).values[0]
            print(_show(parameter_value_to_python(value)))
            return 0
        declared = descriptor[0].type if descriptor else None
        value = parse_value(args.value, declared)
        result = pc.call(pc.client.set_parameters([Parameter(args.name, value=value)])).results[0]
        if not result.successful:
            print(
                f"formation-param: {args.node} refused {args.name} = {_show(value)}: {result.reason}", file=sys.stderr
            )
            return EXIT_REFUSED
        print(f"{args.node}: {args.name} = {_show(value)}")
        return 0
    except TimeoutError as exc:
        print(f"formation-param: {exc}", file=sys.stderr)
        return EXIT_NO_NODE
    finally:
        pc.close()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``formation-param``."""
    args = build_parser().parse_args(argv)
    if args.timeout <= 0:
        print(f"formation-param: --timeout must be > 0, got {args.timeout}", file=sys.stderr)
        return EXIT_USAGE
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
