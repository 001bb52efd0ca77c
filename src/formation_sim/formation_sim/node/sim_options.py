"""``formation-sim``'s options and pre-flight, without rclpy or numba: the command line
(:mod:`formation_sim.cli.sim`) checks them before the node is imported, and the node takes them
from there (or checks them itself when started another way)."""

from __future__ import annotations

import sys
from pathlib import Path

from formation_core import options
from formation_core.errors import FormationError
from formation_core.options import OptionParser
from formation_core.verdict import EXIT_STATUS_HELP, ExitCode
from formation_sim.preflight import Prepared, preflight


def sim_parser() -> OptionParser:
    return options.build_parser(
        options.SIM,
        "formation-sim",
        "The simulator node of a ROS 2 formation run (docs/ros2.md): publishes /clock, relative "
        "poses, velocities and ground truth, collects every agent's wrench, checks the funnels at every "
        "control step and writes OUT (docs/outputs.md). Agents are separate processes (formation-agent). "
        + EXIT_STATUS_HELP
        + ". ROS arguments may follow --ros-args.",
    )


def sim_preflight(raw: list[str]) -> Prepared:
    """``raw`` (sys.argv form, ROS arguments included) parsed and pre-flighted; exits 2 when invalid."""
    opts = options.parse(options.SIM, sim_parser(), options.without_ros_args(raw)[1:])
    try:
        return preflight(opts, lambda spec, o: Path("out") / f"{spec.name}-ros2-{o.mode}")
    except FormationError as exc:
        print(f"formation-sim: {exc}", file=sys.stderr)
        sys.exit(ExitCode.INVALID)
