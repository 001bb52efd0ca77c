"""The console scripts of formation-analyze and formation-rerun: each parses its command line and checks a
``--formation`` file (:func:`formation_bag.entry_points.refused_early`) before it imports its command's
module, so that ``--help`` and a bad option end before numpy, rosbags or the cores are imported."""

from __future__ import annotations

from formation_bag.entry_points import refused_early
from formation_sim.offline.parsers import analyze_parser, rerun_parser


def analyze(argv: list[str] | None = None) -> int:
    """formation-analyze: :func:`formation_sim.offline.analysis.main`."""
    if (code := refused_early(analyze_parser, argv)) is not None:
        return code
    from formation_sim.offline.analysis import main

    return main(argv)


def rerun(argv: list[str] | None = None) -> int:
    """formation-rerun: :func:`formation_sim.offline.rerun.main`."""
    if (code := refused_early(rerun_parser, argv)) is not None:
        return code
    from formation_sim.offline.rerun import main

    return main(argv)
