"""Smoke test of the image (run by docker/check.sh inside it): the paper preset, shortened, as a
simulator process (ros2_ws/sim.sh) and one process per agent (ros2_ws/agent.sh); its trajectory
must equal the headless runner's to rounding (lockstep is deterministic).

    python docker/smoke_ros.py --headless OUT_HEADLESS [--duration S] [--out DIR] [--timeout S]

Exit status: 0 same result, 1 different result or a process failed (logs printed), 2 bad usage.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "config" / "paper_5agents.yaml"
SIM_FLAGS = ("--no-plots", "--quiet", "--force", "--out")


def stop(procs: list[subprocess.Popen[bytes]]) -> None:
    """SIGINT, then SIGTERM, then SIGKILL to the process groups started here."""
    for sig, grace in ((signal.SIGINT, 5.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
        running = [p for p in procs if p.poll() is None]
        for p in running:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass
        end = time.monotonic() + grace
        while time.monotonic() < end and any(p.poll() is None for p in running):
            time.sleep(0.05)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--headless", type=Path, required=True, help="run directory of formation-headless to compare with")
    p.add_argument("--duration", type=float, default=0.05, help="simulated seconds (default 0.05)")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "smoke-ros", help="run directory of the simulator")
    p.add_argument("--timeout", type=float, default=300.0, help="wall seconds before giving up (default 300)")
    args = p.parse_args(argv)
    if not (args.headless / "trajectory.npz").is_file():
        print(f"smoke_ros: error: {args.headless}/trajectory.npz does not exist (--headless)", file=sys.stderr)
        return 2
    logs = args.out.parent / f"{args.out.name}-logs"
    logs.mkdir(parents=True, exist_ok=True)
    procs: list[subprocess.Popen[bytes]] = []
    names: list[str] = []

    def start(name: str, cmd: list[str]) -> subprocess.Popen[bytes]:
        with (logs / f"{name}.log").open("wb") as log:
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        procs.append(proc)
        names.append(name)
        return proc

    t0 = time.monotonic()
    try:
        for i in range(1, 6):
            start(f"agent_{i}", [str(ROOT / "ros2_ws" / "agent.sh"), str(PAPER), str(i)])
        sim = start(
            "sim",
            [str(ROOT / "ros2_ws" / "sim.sh"), str(PAPER), "--duration", str(args.duration), *SIM_FLAGS, str(args.out)],
        )
        try:
            status = sim.wait(timeout=args.timeout)
        except subprocess.TimeoutExpired:
            status = -1
    finally:
        stop(procs)
    wall = time.monotonic() - t0
    if status != 0:
        for name in names:
            text = (logs / f"{name}.log").read_text(errors="replace").splitlines()
            print(f"--- {name} ---", *text[-20:], sep="\n", file=sys.stderr)
        print(f"smoke_ros: simulator exited {status} after {wall:.1f} s", file=sys.stderr)
        return 1
    ros, ref = np.load(args.out / "trajectory.npz"), np.load(args.headless / "trajectory.npz")
    # Same steps, same numbers to rounding (the ROS path converts through messages): rtol 1e-9.
    different = [
        k
        for k in ("t", "p", "R", "v", "u")
        if ros[k].shape != ref[k].shape or not np.allclose(ros[k], ref[k], rtol=1e-9, atol=1e-12)
    ]
    same = [k for k in ("p", "R", "v", "u") if k not in different]
    worst = max((float(np.max(np.abs(ros[k] - ref[k]))) for k in same), default=0.0)
    summary = json.loads((args.out / "summary.json").read_text())
    print(
        f"smoke_ros: sim + 5 agents, {args.duration:g} s simulated in {wall:.1f} s wall, "
        f"funnels_held={summary.get('funnels_held')}, "
        + (
            f"trajectory equals the headless run (max |difference| {worst:.1e})"
            if not different
            else f"DIFFERENT from headless in {different}"
        )
    )
    return 1 if different else 0


if __name__ == "__main__":
    sys.exit(main())
