"""Benchmarks of the ROS 2 deployment; results in BENCHMARKS.md ("Lockstep ROS 2 runs", "Realtime ROS 2 runs").

    .venv/bin/python benchmarks/ros_bench.py [--only lockstep,realtime,scale] [--out DIR]

Every run goes through ``formation-launch`` (what ``ros2_ws/run.sh`` runs): real processes, a
picked free ROS_DOMAIN_ID, discovery on this host over UDP loopback (a private network namespace above 30 processes).
Figures come from each run's ``summary.json`` (wall time, real-time factor, latency from the
measurements' publication to each wrench's reception, on-time fraction, real-time lag) and
``logs/processes.json`` (CPU time and peak RSS of every process, from wait4). Nothing is asserted:
the numbers depend on the machine and its load, which is printed with them.

- lockstep: the paper preset at its 10 kHz control rate (``--lockstep-duration``, default 0.5 s;
  ``--full`` for the whole 5 s).
- step_cpu: the lockstep acceptance figure: CPU of all the run's processes (simulator, agents,
  recorder; ``logs/processes.json``) of a ``--duration 0.55`` run minus that of a ``--duration
  0.05`` run, divided by the 5 000 steps between them, per variant of ``--variants`` (``NAME=LAUNCH
  [ARG ...]``: another checkout's formation-launch gives the "before" of a side-by-side comparison;
  ``profile=FILE`` in the arguments names a Fast DDS profile of one's own, which the launcher leaves
  alone with the rmw's LOCALHOST, shared memory included; ``profile=off``: an empty one, Fast DDS's
  defaults), ``--repeat`` times, interleaved.
- realtime: config/realtime_5agents_100hz.yaml as written and with ``--physics-rate 100`` (one
  integrator step per tick), 10 s each.
- sweep: the realtime preset at 200, 500, 1000 Hz control (physics = control rate), 10 s: the
  control rate five realtime agents sustain.
- scale: config/realtime_20agents_100hz.yaml and realtime_50agents_50hz.yaml (formation-generate
  --preset realtime), 10 s each.
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

import numpy as np

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / ".venv" / "bin" / "formation-launch"
PAPER = REPO / "config" / "paper_5agents.yaml"
REALTIME = REPO / "config" / "realtime_5agents_100hz.yaml"
#: formation-generate --preset realtime: 20 agents at 100 Hz, 50 agents at 50 Hz
SCALE_PRESETS = (REPO / "config" / "realtime_20agents_100hz.yaml", REPO / "config" / "realtime_50agents_50hz.yaml")


def launch(
    formation: Path, out: Path, *extra: str, timeout: float = 1800, launcher: Path = LAUNCH, env: dict | None = None
) -> dict[str, Any]:
    """Run one formation through formation-launch; return summary, process table and timings."""
    load_before = os.getloadavg()
    t0 = time.monotonic()
    r = subprocess.run(
        [str(launcher), str(formation), "--out", str(out), "--no-plots", "--quiet", "--force", *extra],
        capture_output=True,
        text=True,
        timeout=timeout,
        start_new_session=True,
        env=env,
    )
    total = time.monotonic() - t0
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    table = out / "logs" / "processes.json"
    procs = json.loads(table.read_text()) if table.exists() else []
    return {
        "exit": r.returncode,
        "total_wall_s": total,
        "load_before": load_before,
        "load_after": os.getloadavg(),
        "summary": summary,
        "processes": procs,
        "stderr_tail": r.stderr[-2000:],
    }


def cpu_table(procs: list[dict[str, Any]], sim_time: float) -> dict[str, Any]:
    """CPU seconds per process (total, including start-up) and per simulated second; peak RSS."""

    def cpu(p: dict[str, Any]) -> float:
        return p.get("cpu_user_s", 0.0) + p.get("cpu_system_s", 0.0)

    sim = [p for p in procs if p["role"] == "sim"]
    agents = [p for p in procs if p["role"] == "agent"]
    out: dict[str, Any] = {}
    if sim:
        out["sim_cpu_s"] = cpu(sim[0])
        out["sim_rss_mb"] = sim[0].get("max_rss_mb")
    if agents:
        a = np.array([cpu(p) for p in agents])
        out["agent_cpu_s_mean"] = float(a.mean())
        out["agent_cpu_s_max"] = float(a.max())
        out["agent_rss_mb_mean"] = float(np.mean([p.get("max_rss_mb", 0.0) for p in agents]))
        out["total_rss_mb"] = float(sum(p.get("max_rss_mb", 0.0) for p in procs))
    out["sim_time_s"] = sim_time
    return out


def brief(res: dict[str, Any]) -> dict[str, Any]:
    s = res["summary"]
    keep = (
        "duration",
        "wall_time",
        "real_time_factor",
        "funnels_held",
        "worst_margin",
        "latency_ms",
        "on_time_fraction_all",
        "answered_fraction_all",
        "realtime_lag_s",
        "resends",
        "discovery_s",
        "physics_rate",
        "control_rate",
    )
    out = {k: s.get(k) for k in keep if k in s}
    out["exit"] = res["exit"]
    out["total_wall_s"] = res["total_wall_s"]
    out["load"] = [round(x, 2) for x in (*res["load_before"], *res["load_after"])]
    out["launch"] = s.get("launch")
    out.update(cpu_table(res["processes"], s.get("duration", 0.0)))
    return out


def total_cpu(procs: list[dict[str, Any]]) -> dict[str, float]:
    """CPU seconds (user + system) by role (sim, agent, recorder) and in total."""
    out: dict[str, float] = {}
    for p in procs:
        out[p["role"]] = out.get(p["role"], 0.0) + p.get("cpu_user_s", 0.0) + p.get("cpu_system_s", 0.0)
    out["total"] = sum(out.values())
    return out


def own_profile(base: Path, given: str) -> Path:
    """The Fast DDS profile file of ``profile=given``: ``off`` an empty one written into ``base``."""
    if given != "off":
        return Path(given).resolve()
    empty = base / "empty_fastdds_profile.xml"
    empty.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"/>\n'
    )
    return empty


def step_cpu(base: Path, variants: list[str], repeat: int) -> dict[str, Any]:
    """CPU per lockstep step of the paper preset, (CPU(0.55 s) − CPU(0.05 s)) / 5000, per variant."""
    runs: dict[str, list[dict[str, Any]]] = {}
    for v in variants:  # warm every variant's caches (numba compiles on a checkout's first run)
        name, _, rest = v.partition("=")
        words = rest.split()
        launch(
            PAPER,
            base / f"stepcpu_{name}_warmup",
            "--duration",
            "0.01",
            "--no-record",
            launcher=Path(words[0]) if words else LAUNCH,
        )
    for r in range(repeat):
        for v in variants:
            name, _, rest = v.partition("=")
            words = rest.split()
            launcher = Path(words[0]) if words else LAUNCH
            extra = [w for w in words[1:] if not w.startswith("profile=")]
            env = dict(os.environ)
            for w in words[1:]:
                if w.startswith("profile="):
                    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(own_profile(base, w.partition("=")[2]))
            res = {}
            for d in (0.05, 0.55):
                res[d] = launch(
                    PAPER, base / f"stepcpu_{name}_{r}_{d}", "--duration", str(d), *extra, launcher=launcher, env=env
                )
            short, long_ = total_cpu(res[0.05]["processes"]), total_cpu(res[0.55]["processes"])
            per_step = {k: 1e3 * (long_.get(k, 0.0) - short.get(k, 0.0)) / 5000 for k in long_}
            s = res[0.55]["summary"]
            row = {
                "cpu_ms_per_step": per_step,
                "exit": [res[0.05]["exit"], res[0.55]["exit"]],
                "real_time_factor_0.55": s.get("real_time_factor"),
                "load": [round(x, 2) for x in (*res[0.05]["load_before"], *res[0.55]["load_after"])],
            }
            runs.setdefault(name, []).append(row)
            print(
                f"step_cpu {name} #{r}: total {per_step['total']:.2f} ms/step "
                f"({', '.join(f'{k} {v:.2f}' for k, v in per_step.items() if k != 'total')}), "
                f"rtf {row['real_time_factor_0.55']}, load {row['load']}, exit {row['exit']}",
                flush=True,
            )
    return runs


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", default="lockstep,realtime,sweep,scale", help="comma-separated sections")
    p.add_argument("--rates", default="200,500,1000", help="control rates [Hz] of the sweep section")
    p.add_argument("--lockstep-duration", type=float, default=0.5, help="simulated seconds of the paper preset")
    p.add_argument("--full", action="store_true", help="the whole 5 s paper scenario in lockstep")
    p.add_argument("--out", type=Path, help="keep the run directories here (default: a temporary directory)")
    p.add_argument("--variants", nargs="*", default=["this="], help="step_cpu: NAME=[LAUNCH [ARG ...]] per variant")
    p.add_argument("--repeat", type=int, default=2, help="step_cpu: runs of each variant (interleaved)")
    args = p.parse_args(argv)
    sections = set(args.only.split(","))
    base = args.out or Path(tempfile.mkdtemp(prefix="ros_bench_"))
    base.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]}}

    def record(name: str, res: dict[str, Any]) -> None:
        results[name] = brief(res)
        print(f"== {name}\n{json.dumps(results[name], indent=1)}", flush=True)

    if "lockstep" in sections:
        d = 5.0 if args.full else args.lockstep_duration
        record("lockstep_paper_10kHz", launch(PAPER, base / "lockstep", "--duration", str(d)))
    if "step_cpu" in sections:
        results["step_cpu"] = step_cpu(base, args.variants, args.repeat)
    if "realtime" in sections:
        record("realtime_5agents_100Hz_as_written", launch(REALTIME, base / "rt5_file"))
        record("realtime_5agents_100Hz_physics100", launch(REALTIME, base / "rt5_p100", "--physics-rate", "100"))
    if "sweep" in sections:
        for rate in (float(x) for x in args.rates.split(",")):
            res = launch(REALTIME, base / f"sweep{rate:g}", "--control-rate", str(rate), "--physics-rate", str(rate))
            record(f"realtime_5agents_{rate:g}Hz", res)
    if "scale" in sections:
        for preset in SCALE_PRESETS:
            record(preset.stem, launch(preset, base / preset.stem))
    (base / "ros_bench.json").write_text(json.dumps(results, indent=2) + "\n")
    print(f"results: {base / 'ros_bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
