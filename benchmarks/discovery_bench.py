"""Discovery time and traffic: simple discovery vs a Fast DDS discovery server, 5, 20 and 40 agents.

    sudo .venv/bin/python benchmarks/discovery_bench.py [--agents 5 20 40] [--modes simple server] [--json FILE]

For each size, a random formation (``formation-generate N --topology random``, 1 kHz) runs through
``formation-launch --discovery MODE`` for 0.01 s (lockstep, nothing recorded). The whole benchmark
runs inside a private network namespace (``unshare -n``: a loopback of its own with multicast on,
so needs root) so that the loopback's counters hold this run's traffic only; every process uses UDP
(no shared memory), simple discovery multicasts on that loopback (the launcher's namespace settings).
Per run it reports:

- ``start_to_matched_s``: wall seconds from starting formation-launch until the simulator has matched
  every agent (``launch.wall_start_s``: process start-up included, ~1.3 s CPU per process);
- ``sim_discovery_s``: the simulator's own wait, from its node's creation (``discovery_s``);
- ``packets``, ``bytes``: what crossed the loopback from the start until that moment (discovery,
  plus the few messages of a first step that may already be under way).

Nothing is asserted. One run per cell: on a shared machine the start-up times vary with the load.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
IN_NS = "DISCOVERY_BENCH_NETNS"


def loopback_counters() -> tuple[int, int]:
    """(packets, bytes) received on ``lo`` so far (every packet sent on the loopback is received on it)."""
    for line in Path("/proc/net/dev").read_text().splitlines()[2:]:
        name, data = line.split(":", 1)
        if name.strip() == "lo":
            fields = data.split()
            return int(fields[1]), int(fields[0])
    raise RuntimeError("no loopback in /proc/net/dev")


def run_one(formation: Path, mode: str, work: Path) -> dict[str, Any]:
    out = work / f"{formation.stem}-{mode}"
    cmd = [str(BIN / "formation-launch"), str(formation), "--out", str(out), "--duration", "0.01"]
    cmd += ["--no-record", "--no-plots", "--quiet", "--force", "--discovery", mode]
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_DOMAIN_ID", "ROS_DISCOVERY_SERVER")}
    packets0, bytes0 = loopback_counters()
    log = (work / f"{out.name}.log").open("wb")
    proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    matched: tuple[int, int] | None = None
    sim_log = out / "logs" / "sim.log"
    while proc.poll() is None:
        if matched is None and sim_log.exists() and "agents matched in" in sim_log.read_text(errors="replace"):
            matched = loopback_counters()
        time.sleep(0.05)
    log.close()
    summary = json.loads((out / "summary.json").read_text())
    row: dict[str, Any] = {
        "agents": int(formation.stem.split("_")[1]),
        "mode": mode,
        "exit_status": proc.returncode,
        "start_to_matched_s": summary["launch"].get("wall_start_s"),
        "sim_discovery_s": summary.get("discovery_s"),
    }
    if matched is not None:
        row.update(packets=matched[0] - packets0, bytes=matched[1] - bytes0)
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", type=int, nargs="+", default=[5, 20, 40])
    p.add_argument("--modes", nargs="+", default=["simple", "server"], choices=["simple", "server"])
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    if os.environ.get(IN_NS) != "1":
        script = 'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec "$@"'
        env = dict(os.environ, **{IN_NS: "1", "FORMATION_IN_NETNS": "1"})  # the launcher's namespace settings
        cmd = ["unshare", "-n", "sh", "-c", script, "sh", sys.executable, *sys.argv]
        return subprocess.run(cmd, env=env).returncode
    rows = []
    with tempfile.TemporaryDirectory(prefix="discovery-bench-") as tmp:
        work = Path(tmp)
        for n in args.agents:
            formation = work / f"random_{n}_agents.yaml"
            subprocess.run(
                [str(BIN / "formation-generate"), str(n), "--topology", "random", "--out", str(formation)],
                check=True,
                capture_output=True,
            )
            for mode in args.modes:
                row = run_one(formation, mode, work)
                rows.append(row)
                print(json.dumps(row), flush=True)
    print(
        f"\n{'agents':>6} {'mode':>7} {'exit':>4} {'start→matched s':>16} {'sim wait s':>10} {'packets':>8} {'kB':>8}"
    )
    for r in rows:
        print(
            f"{r['agents']:>6} {r['mode']:>7} {r['exit_status']:>4} {r['start_to_matched_s'] or float('nan'):>16.2f} "
            f"{r['sim_discovery_s'] or float('nan'):>10.2f} {r.get('packets', -1):>8} {r.get('bytes', 0) / 1e3:>8.0f}"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
