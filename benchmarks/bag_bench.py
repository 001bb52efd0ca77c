"""Benchmarks of formation_bag: writer, recorder and analysis throughput.

    .venv/bin/python benchmarks/bag_bench.py [--duration 5.0] [--skip-ros] [--results FILE]

1. writer: SegmentedBagWriter, pre-serialized PoseStamped messages, mcap and sqlite3 (msgs/s);
2. the paper run (config/paper_5agents.yaml, 10 kHz) written as a lockstep bag by tests/formation_bag/synth.py
   for ``--duration`` s, then the analysis (load + re-run + funnel check + ages), the interop check,
   and a check that the analysis reproduces the run's own summary;
3. recorder (ROS): formation-record fed by a publisher that sends pre-serialized messages as fast
   as it can on 20 topics; msgs/s received and written, and how many were lost.

Writes a Markdown table to ``--results`` (default benchmarks/RESULTS_bags.md) and prints it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

from formation_bag import messages as m
from formation_bag.dataset import load_run
from formation_bag.interop_check import check_bag
from formation_bag.writer import SegmentedBagWriter
from formation_core.spec import load_formation
from formation_sim.offline.analysis import analyze_run, message_ages

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "formation_bag"))  # the test fixture that writes lockstep bags
from synth import write_run_bag  # noqa: E402

PAPER = ROOT / "config" / "paper_5agents.yaml"
VENV_BIN = ROOT / ".venv" / "bin"

BLASTER = textwrap.dedent(
    """
    import json, sys, time
    import rclpy
    from rclpy.duration import Duration
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    from formation_msgs_py.ros import qos
    n, topics, rate = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = rclpy.create_node("bag_bench_blaster")
    pubs = [node.create_publisher(PoseStamped, f"/agent_{k}/relative_pose/agent_x", qos.CONTROL)
            for k in range(topics)]
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in pubs):
        time.sleep(0.02)
    time.sleep(1.0)
    data = serialize_message(PoseStamped())
    t0 = time.perf_counter()
    for i in range(n):
        pubs[i % topics].publish(data)
        if rate and i % 100 == 99:
            left = t0 + (i + 1) / rate - time.perf_counter()
            if left > 0:
                time.sleep(left)  # no busy wait: the recorder needs the CPU
    t1 = time.perf_counter()
    for p in pubs:
        p.wait_for_all_acked(Duration(seconds=20))
    print(json.dumps({"published": n, "publish_s": t1 - t0}), flush=True)
    rclpy.shutdown()
    """
)


def bench_writer(work: Path, n: int = 200_000) -> list[tuple[str, str]]:
    enc = m.Encoder()
    data = enc.relative_pose(0, "1", [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0])
    rows = []
    for storage in ("mcap", "sqlite3"):
        bag = work / f"writer_{storage}"
        t0 = time.perf_counter()
        with SegmentedBagWriter(bag, storage=storage, segment_seconds=2.0) as w:
            for k in range(20):
                w.add_topic(f"/agent_{k}/relative_pose/agent_x", m.POSE_STAMPED)
            names = [f"/agent_{k}/relative_pose/agent_x" for k in range(20)]
            ts = 1_700_000_000 * m.NS_PER_S
            for i in range(n):
                w.write(names[i % 20], ts + i * 10_000, data)  # 100 k msgs/s of log time: 1 segment / 2 s
        dt = time.perf_counter() - t0
        rows.append((f"writer, {storage}, {n} msgs of {len(data)} B, 20 topics", f"{n / dt:,.0f} msgs/s"))
    return rows


def bench_paper(work: Path, duration: float) -> tuple[list[tuple[str, str]], dict]:
    spec = load_formation(PAPER, overrides={"duration": duration})
    bag = work / "paper"
    t0 = time.perf_counter()
    res = write_run_bag(spec, bag, formation_text=PAPER.read_text(), segment_seconds=2.0, wall_step=1e-4)
    t_write = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in bag.iterdir())
    t0 = time.perf_counter()
    run = load_run(bag)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, summary, reruns = analyze_run(run)
    t_analyze = time.perf_counter() - t0
    t0 = time.perf_counter()
    message_ages(run)
    t_ages = time.perf_counter() - t0
    t0 = time.perf_counter()
    report = check_bag(bag)
    t_check = time.perf_counter() - t0
    worst = max(
        abs(summary["edges"][k]["min_margin_e"] - res.summary["edges"][k]["min_margin_e"]) for k in summary["edges"]
    )
    rows = [
        (
            f"paper run {duration:g} s @ 10 kHz as a lockstep bag (synth: simulation + controllers + writing)",
            f"{t_write:.1f} s, {res.messages:,} msgs, {size / 2**20:.1f} MiB, {res.steps:,} steps",
        ),
        ("analysis: read + decode every message", f"{t_load:.1f} s ({res.messages / t_load:,.0f} msgs/s)"),
        ("analysis: re-run 5 controllers + funnel check of every step", f"{t_analyze:.1f} s"),
        ("analysis: message ages", f"{t_ages:.1f} s"),
        ("analysis total (formation-analyze without plots)", f"{t_load + t_analyze + t_ages:.1f} s"),
        (
            "interop check (rosbags and mcap read every message, mcap_ros2 decodes a sample)",
            f"{t_check:.1f} s, ok={report.ok}",
        ),
        (
            "analysis vs the run's own summary",
            f"verdict {summary['funnels_held']} = {res.summary['funnels_held']}, max abs Δ min_margin_e {worst:.1e}, "
            f"re-run max abs Δu {max(r.max_abs_diff for r in reruns.values()):.1e}",
        ),
    ]
    return rows, summary


def bench_recorder(work: Path, n: int, rate: float) -> list[tuple[str, str]]:
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(215 + os.getpid() % 18),  # Fast DDS accepts ≤ 232; below 215 may hit ephemeral ports
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_LOG_DIR=str(work / "ros_log"),
    )
    bag = work / f"recorded_{rate:g}"
    rec = subprocess.Popen(
        [str(VENV_BIN / "formation-record"), "--out", str(bag), "--quiet", "--discovery-period", "0.2"],
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    blaster = None
    try:
        for line in rec.stdout:  # Fast DDS may log to stdout first
            if "formation-record: recording" in line:
                break
        else:
            raise RuntimeError("formation-record did not start")
        blaster = subprocess.Popen(
            [sys.executable, "-c", BLASTER, str(n), "20", str(rate)],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        out, _ = blaster.communicate(timeout=600)
        pub = json.loads(out.strip().splitlines()[-1])
        time.sleep(1.0)
    finally:
        for proc in (blaster, rec):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(30)
                except subprocess.TimeoutExpired:
                    proc.send_signal(signal.SIGTERM)
                    proc.wait(10)
        rec.stdout.close()
    from formation_bag.reader import Bag

    with Bag(bag) as b:
        counts = json.loads(b.custom_data["recorder_counts"])
        logs = [msg.log_time for msg in b.messages()]
    received = sum(counts["received"].values())
    written = sum(counts["written"].values())
    span = max((max(logs) - min(logs)) / 1e9, pub["publish_s"]) if logs else float("nan")
    return [
        (
            f"recorder (ROS): {n:,} pre-serialized msgs on 20 topics (keep-last-10 reliable), publisher "
            + (f"paced at {rate:,.0f} msgs/s" if rate else "as fast as it can"),
            f"{received / span:,.0f} msgs/s received, {written:,} written of {received:,} received, "
            f"{pub['published']:,} published in {pub['publish_s']:.2f} s: {pub['published'] - received:,} lost",
        )
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=5.0, help="simulated seconds of the paper run (default 5)")
    ap.add_argument("--messages", type=int, default=100_000, help="messages for the recorder benchmark")
    ap.add_argument("--skip-ros", action="store_true", help="skip the recorder benchmark")
    ap.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "RESULTS_bags.md")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows: list[tuple[str, str]] = []
    with tempfile.TemporaryDirectory(prefix="bag_bench_") as tmp:
        work = Path(tmp)
        rows += bench_writer(work)
        print("\n".join(f"{a}: {b}" for a, b in rows), flush=True)
        paper_rows, _ = bench_paper(work, args.duration)
        rows += paper_rows
        print("\n".join(f"{a}: {b}" for a, b in paper_rows), flush=True)
        if not args.skip_ros:
            rec_rows = bench_recorder(work, args.messages, 0.0)
            for rate in (10_000.0, 20_000.0):
                rec_rows += bench_recorder(work, args.messages, rate)
            rows += rec_rows
            print("\n".join(f"{a}: {b}" for a, b in rec_rows), flush=True)
    load1 = os.getloadavg()[0]
    text = [
        "# formation_bag benchmarks",
        "",
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} by `benchmarks/bag_bench.py"
        f" --duration {args.duration:g}`; {os.cpu_count()} CPUs, Python {platform.python_version()},"
        f" load average {load0:.1f} at start / {load1:.1f} at end (the machine was shared).",
        "",
        "| what | result |",
        "|---|---|",
        *[f"| {a} | {b} |" for a, b in rows],
        "",
    ]
    args.results.write_text("\n".join(text), encoding="utf-8")
    print(f"results in {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
