"""``formation-sim``'s command line, checked before rclpy and the cores are imported.

``--help``, a bad option and a bad formation file end here (exit 0, 2, 2) in a fraction of a
second, without rclpy or numba; a valid run goes on in :mod:`formation_sim.sim_node` with the
pre-flight result (the file is read once).
"""

from __future__ import annotations

import sys
from pathlib import Path

from formation_msgs_py import options
from formation_msgs_py.errors import FormationError
from formation_msgs_py.options import OptionParser
from formation_msgs_py.outcome import EXIT_STATUS_HELP, ExitCode, guarded
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


@guarded("formation-sim")
def sim(argv: list[str] | None = None) -> int:
    """Entry point of ``formation-sim``."""
    raw = list(sys.argv if argv is None else [sys.argv[0], *argv])
    run = sim_preflight(raw)
    from formation_sim.sim_node import main

    return main(argv, prepared=run)
