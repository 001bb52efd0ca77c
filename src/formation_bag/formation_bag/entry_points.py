"""The console scripts of formation-record and formation-replay.

Each parses its command line and checks a ``--formation`` file before it imports its command's
module: ``--help`` and a bad option end before rclpy, rosbags, numpy or the cores are imported
(``--help`` answers in a fraction of a second; tests/test_entry_points.py), a bad file (exit 2)
before rclpy, rosbags or numba. The module then parses the same arguments again (microseconds) and
loads the file again (milliseconds).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from formation_bag.parsers import record_parser, replay_parser
from formation_core.errors import FormationError


def refused_early(parser: Callable[[], argparse.ArgumentParser], argv: list[str] | None) -> int | None:
    """2 for a bad ``--formation`` file (named on stderr), else None; exits on ``--help`` or a bad option
    (before rclpy, rosbags, numpy or the cores are imported)."""
    p = parser()
    args = p.parse_args(argv)
    if getattr(args, "formation", None) is None:
        return None
    from formation_core.spec import load_formation

    try:
        load_formation(args.formation)
    except FormationError as exc:
        print(f"{p.prog}: {exc}", file=sys.stderr)
        return 2
    return None


def record(argv: list[str] | None = None) -> int:
    """formation-record: :func:`formation_bag.record_node.main`."""
    if (code := refused_early(record_parser, argv)) is not None:
        return code
    from formation_bag.record_node import main

    return main(argv)


def replay(argv: list[str] | None = None) -> int:
    """formation-replay: :func:`formation_bag.replay_node.main`."""
    if (code := refused_early(replay_parser, argv)) is not None:
        return code
    from formation_bag.replay_node import main

    return main(argv)
