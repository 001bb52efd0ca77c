"""Cost of secure mode: the same runs with and without ``--secure``; results in BENCHMARKS.md ("Secure mode").

    .venv/bin/python benchmarks/secure_bench.py [--repeat 2] [--out DIR]

- lockstep: the paper preset at 10 kHz for 0.2 s (2000 steps), no recording: wall and CPU per
  step (CPU of every process, from wait4, over the steps; start-up included), and the
  measurement-to-wrench latency p50/p99 of the simulator's summary.
- realtime: config/realtime_5agents_100hz.yaml for 10 s with ``--physics-rate 100``: latency
  p50/p99, on-time fraction, real-time lag.

Each configuration runs ``--repeat`` times, alternating plain and secure, so that the machine's
load affects both alike. Runs go through formation-launch (ros_bench.launch); nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ros_bench import PAPER, REALTIME, launch

LOCKSTEP = ("--duration", "0.2", "--no-record")
REALTIME_ARGS = ("--duration", "10", "--physics-rate", "100", "--no-record")


def figures(res: dict[str, Any]) -> dict[str, Any]:
    s = res["summary"]
    steps = max(1, int(s.get("steps", 0)))
    cpu = sum(p.get("cpu_user_s", 0.0) + p.get("cpu_system_s", 0.0) for p in res["processes"])
    lat = s.get("latency_ms") or {}
    return {
        "exit": res["exit"],
        "funnels_held": s.get("funnels_held"),
        "steps": steps,
        "wall_per_step_ms": 1e3 * s.get("wall_time", 0.0) / steps,
        "cpu_per_step_ms": 1e3 * cpu / steps,
        "latency_p50_ms": lat.get("p50"),
        "latency_p99_ms": lat.get("p99"),
        "on_time_fraction_all": s.get("on_time_fraction_all"),
        "realtime_lag_mean_s": (s.get("realtime_lag_s") or {}).get("mean"),
        "discovery_s": s.get("discovery_s"),
        "load": [round(x, 2) for x in (*res["load_before"], *res["load_after"])],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--out", type=Path, help="keep the run directories here (default: a temporary directory)")
    args = p.parse_args()
    base = args.out or Path(tempfile.mkdtemp(prefix="secure-bench-"))
    results: dict[str, list[dict[str, Any]]] = {}
    for k in range(args.repeat):
        for name, formation, extra in (("lockstep", PAPER, LOCKSTEP), ("realtime", REALTIME, REALTIME_ARGS)):
            for secure in (False, True):
                key = f"{name}{'-tls' if secure else ''}"
                res = launch(formation, base / f"{key}-{k}", *extra, *(("--secure",) if secure else ()))
                results.setdefault(key, []).append(figures(res))
                print(key, json.dumps(results[key][-1]), flush=True)
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
