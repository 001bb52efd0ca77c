"""``formation-bag info|check|repair BAG``: inspect, interop-check and repair bags (no ROS)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from formation_core.errors import BagError
from formation_core.verdict import guarded


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-bag",
        description="Inspect (info), check interoperability (check: rosbags and, for MCAP, the independent "
        "mcap + mcap_ros2 readers; Jazzy metadata.yaml format) and repair (rebuild metadata.yaml of a bag "
        "left by a killed recorder) ROS 2 bags, without ROS. Exit status: 0 fine, 1 problems found, 2 bad input.",
    )
    sub = p.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="topics, types, counts, time range, files, lost files")
    info.add_argument("bag", type=Path)
    info.add_argument("--json", action="store_true", help="machine-readable output")
    check = sub.add_parser(
        "check",
        help="read every message back with rosbags and (MCAP) mcap, compare their bytes; mcap_ros2 decodes "
        "the first 100 of every channel like rosbags; check metadata.yaml",
    )
    check.add_argument("bag", type=Path)
    check.add_argument("--json", action="store_true", help="machine-readable output")
    check.add_argument(
        "--decode-all",
        action="store_true",
        help="have mcap_ros2 decode every message, not the first 100 of every channel (slower: each is decoded twice)",
    )
    rep = sub.add_parser(
        "repair",
        help="salvage the file a killed writer left open (MCAP); write metadata.yaml for the readable files. "
        "Given one MCAP file (OUT/view.mcap of a crashed run), complete it in place",
    )
    rep.add_argument("bag", type=Path, help="a bag directory, or one MCAP file")
    rep.add_argument("--force", action="store_true", help="replace an existing metadata.yaml")
    return p


@guarded("formation-bag")
def main(argv: list[str] | None = None) -> int:
    return _run(argv)


def _run(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    from formation_bag import messages as m  # rosbags: not for --help
    from formation_bag.interop_check import DECODE_SAMPLE, check_bag
    from formation_bag.reader import Bag, repair, repair_file

    try:
        if args.command == "info":
            with Bag(args.bag) as bag:
                info: dict[str, Any] = {
                    "path": str(args.bag),
                    "storage": bag.storage,
                    "segments": [s.name for s in bag.segments],
                    "lost": bag.lost,
                    "recovered_without_metadata": bag.recovered,
                    "messages": bag.message_count,
                    "start": bag.start_time / m.NS_PER_S,
                    "duration": (bag.end_time - bag.start_time) / m.NS_PER_S,
                    "topics": {t.name: {"type": t.msgtype, "count": t.count} for t in bag.topics.values()},
                    "custom_data_keys": sorted(bag.custom_data),
                }
            if args.json:
                print(json.dumps(info, indent=2))
            else:
                print(
                    f"bag {info['path']}: {info['storage']}, {len(info['segments'])} file(s), "
                    f"{info['messages']} messages over {info['duration']:.3f} s"
                )
                for lost in info["lost"]:
                    print(f"  lost: {lost}")
                for name, t in sorted(info["topics"].items()):
                    print(f"  {name:<45} {t['type']:<36} {t['count']:>9}")
            return 0
        if args.command == "check":
            report = check_bag(args.bag, sample=None if args.decode_all else DECODE_SAMPLE)
            if args.json:
                print(json.dumps(report.as_dict(), indent=2))
            else:
                n = sum(report.counts_rosbags.values())
                readers = "rosbags" + (
                    f" and mcap ({report.decoded_mcap_ros2} decoded by mcap_ros2 as by rosbags)"
                    if report.counts_mcap is not None
                    else ""
                )
                print(f"{args.bag}: {n} messages on {len(report.counts_rosbags)} topics read with {readers}")
                for lost in report.lost:
                    print(f"  lost: {lost}")
                for prob in report.problems:
                    print(f"  PROBLEM: {prob}")
                print("OK" if report.ok else "PROBLEMS FOUND")
            return 0 if report.ok else 1
        if args.bag.is_file():
            print(f"repaired {args.bag}: {repair_file(args.bag)}")
            return 0
        meta, lost = repair(args.bag, force=args.force)
        print(f"wrote {meta}")
        for item in lost:
            print(f"  lost: {item}")
        return 0
    except (BagError, FileExistsError) as exc:
        print(f"formation-bag: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
