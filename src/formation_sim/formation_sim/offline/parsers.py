"""The command lines of formation-analyze and formation-rerun (their console scripts,
:mod:`formation_sim.offline.entry_points`, parse them before the heavy imports; each command's module
parses them again)."""

from __future__ import annotations

import argparse
from pathlib import Path

from formation_bag.parsers import BAG_HELP, NAMESPACE_HELP
from formation_core.verdict import EXIT_STATUS_HELP

#: formation-analyze --velocity-margins
VELOCITY_MARGIN_MODES = ("rerun", "none")


def analyze_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-analyze",
        description="Analyse a recorded run without ROS: recompute e_k and ψ_k from /formation/ground_truth, check "
        "every funnel, write OUT as docs/outputs.md (summary.json, trajectory.npz, errors.png, orientation_errors.png, "
        "inputs.png, velocity_errors.png, clearance.png, foxglove_layout.json) plus errors.csv, inputs.csv, "
        "positions.csv, "
        "ages.json, ages.csv. Works on lockstep and realtime bags and on bags left by a killed recorder; missing "
        "data makes the verdict INCOMPLETE (never FAIL) and is listed. " + EXIT_STATUS_HELP + ".",
    )
    p.add_argument("bag", type=Path, help=BAG_HELP)
    p.add_argument("--out", type=Path, help="output directory (default: <bag>-analysis next to the bag)")
    p.add_argument("--formation", type=Path, help="formation file (default: the copy the recorder stored in the bag)")
    p.add_argument(
        "--velocity-margins",
        choices=VELOCITY_MARGIN_MODES,
        default="rerun",
        help="rerun: velocity-funnel margins and controller faults from re-running the agents' controllers on the "
        "recorded measurements (default); none: check the distance and orientation funnels only",
    )
    p.add_argument("--namespace", default="", help=NAMESPACE_HELP)
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.add_argument(
        "--animate",
        action="store_true",
        help="also write OUT/animation.gif: the formation in 3D and its funnel margins (~15 s for a 5 s run)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an existing non-empty output directory, removing an earlier analysis's outputs first",
    )
    return p


def rerun_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-rerun",
        description="Feed the recorded measurements of one or all agents to the agent's controller core "
        "(offline, no ROS) and compare the wrenches with the recorded ones; steps whose measurement or wrench "
        "the bag lacks are not compared and are counted. A wrench is equal within the round-off tolerance of its "
        "step (docs/controller.md: bit for bit from the same code on the same platform, within the bound from "
        "another host or code form), or within --tolerance. Exit status: 0 equal on complete "
        "data, 1 a recorded wrench differs, 2 bad input, 4 equal where compared but data missing.",
    )
    p.add_argument("bag", type=Path, help=BAG_HELP)
    p.add_argument("--agent", action="append", default=None, metavar="ID", help="agent id (repeatable; default all)")
    p.add_argument("--formation", type=Path, help="formation file (default: the copy stored in the bag)")
    p.add_argument(
        "--override",
        type=Path,
        help="YAML file changing gains/funnels: {agents: {ID: {...}}, edges: {TAIL-HEAD: {...}}, defaults: {...}}",
    )
    p.add_argument(
        "--tolerance",
        type=float,
        default=None,
        metavar="X",
        help="count |Δu| ≤ X [N, N·m] per component as equal (default: each step's round-off tolerance)",
    )
    p.add_argument("--namespace", default="", help=NAMESPACE_HELP)
    p.add_argument(
        "--out",
        type=Path,
        help="write rerun.json and rerun_<agent>.npz into this directory (new or empty; see --force)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an existing non-empty --out directory, removing an earlier re-run's outputs first",
    )
    return p
