"""The command lines of formation-record and -replay (their console scripts, :mod:`formation_bag.entry_points`,
parse them before the heavy imports; each command's module parses them again)."""

from __future__ import annotations

import argparse
from pathlib import Path

from formation_bag.contract import STORAGE_NAMES
from formation_core import options
from formation_core.options import byte_count

BAG_HELP = "bag directory (or a single .mcap/.db3 file)"
NAMESPACE_HELP = "namespace of the run's topics (default none)"
#: formation-replay --wait-settle [s]: longer than the recorder's discovery period and its wait before
#: it subscribes to the ground truth (formation-record --discovery-period, record_node.DEFER_SETTLE:
#: 0.5 s each), with room for a busy machine
REPLAY_SETTLE = 2.0


def record_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-record",
        description="Record a running formation's topics (docs/topics.md) into a ROS 2 bag (MCAP or sqlite3, "
        "metadata version 9), one file unless --max-bag-size or --segment-seconds splits it (a killed recorder "
        "loses at most the file it was writing). "
        "Stop with Ctrl-C (SIGINT) or SIGTERM: the bag is closed cleanly.",
    )
    p.add_argument("--out", type=Path, required=True, help="bag directory to create (must not exist)")
    p.add_argument("--storage", choices=STORAGE_NAMES, default="mcap", help="storage plugin (default mcap)")
    p.add_argument(
        "--topics", nargs="+", metavar="TOPIC", help="record exactly these topics (default: every docs/topics.md topic)"
    )
    p.add_argument(
        "--formation",
        type=Path,
        help="formation file: subscribe to its topics before they appear, and store the file in the bag "
        "(custom_data) so formation-analyze needs nothing else",
    )
    p.add_argument("--namespace", default="", help=NAMESPACE_HELP)
    p.add_argument(
        "--segment-seconds",
        type=float,
        default=None,
        help="also close a segment after S s of log time (simulated s with --log-time sim; default: by size only)",
    )
    p.add_argument(
        "--max-bag-size",
        type=byte_count,
        default=None,
        metavar="BYTES",
        help="also close a file after about BYTES bytes, as ros2 bag record -b (default: one file, unless "
        "--segment-seconds)",
    )
    p.add_argument(
        "--log-time",
        choices=("auto", "sim", "receive"),
        default="auto",
        help="log time of each message: sim (its stamp: simulation time) or receive (system clock); "
        "auto: sim for lockstep runs (--meta mode=lockstep, else the formation file's mode), receive otherwise",
    )
    p.add_argument("--stats", type=Path, help="also write the recorder's counts to this JSON file (atomically)")
    p.add_argument(
        "--decimate",
        nargs="+",
        default=[],
        metavar="TOPIC=N",
        help="keep every N-th message of TOPIC (a glob, e.g. '/agent_*/relative_pose/*=10'); analysis and "
        "re-run need every message of the ground truth, velocities, relative poses and wrenches",
    )
    p.add_argument("--meta", nargs="+", default=[], metavar="KEY=VALUE", help="extra custom_data in metadata.yaml")
    p.add_argument("--discovery-period", type=float, default=0.5, help="graph polling period [s] (default 0.5)")
    p.add_argument("--quiet", action="store_true", help="no periodic status lines")
    return p


def replay_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-replay",
        description="Publish a bag's messages with their recorded timing (and /clock). Waits for subscribers "
        "first; shows progress. Stop with Ctrl-C.",
    )
    p.add_argument("bag", type=Path, help=BAG_HELP)
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0)")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="replay only these topics (default all)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--start", type=float, help="start at S seconds after the bag's first message")
    p.add_argument("--end", type=float, help="stop at S seconds after the bag's first message")
    p.add_argument(
        "--clock-hz",
        type=float,
        default=100.0,
        help="if the bag has no /clock (or it is not selected): publish /clock from the bag time at this rate "
        "(default 100; 0 = none)",
    )
    p.add_argument(
        "--wait",
        choices=("any", "all", "none"),
        default="any",
        help="before starting, wait until any (default) / all replayed topics have a subscriber and every "
        "subscription seen on them has matched (none: start at once)",
    )
    p.add_argument("--wait-timeout", type=float, default=10.0, help="give up waiting after S s and start (default 10)")
    p.add_argument(
        "--wait-settle",
        type=float,
        default=REPLAY_SETTLE,
        help="start only once no subscription has appeared or matched for S s, so that a recorder subscribing "
        f"as it discovers the topics misses nothing (default {REPLAY_SETTLE:g})",
    )
    p.add_argument(
        "--foxglove",
        type=options.endpoint,
        metavar="[HOST:]PORT",
        help="live view: also serve the replayed /formation/markers, /formation/funnels, /diagnostics and /clock "
        "(at most 30 Hz of bag time, /diagnostics as recorded) over the Foxglove WebSocket protocol (subprotocol "
        'foxglove.sdk.v1) on [HOST:]PORT; host 127.0.0.1 unless given (docs/ros2.md, "Live view"). With no ROS '
        "subscriber, add --wait none",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p
