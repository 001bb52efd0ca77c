"""Benchmarks of the ROS-free core, before and after compiling it. Figures for BENCHMARKS.md, not asserted.

    .venv/bin/python benchmarks/core_bench.py [--before COMMIT] [--quick] [--json FILE]

Everything is measured in this one run, side by side: the current tree ("after") and, with
``--before COMMIT``, the core of that commit (``git archive`` into a temporary directory, run
with the same interpreter). CPU times are of the measured process (the machines are shared;
CPU time is far less sensitive to load than wall time), wall times are reported too.

1. controller evaluation: the compiled kernel (agent_step in a compiled loop), and
   ``AgentController.compute`` from Python, compiled and interpreted, and before;
2. agent process: import + first compute, compute per call, peak RSS: interpreted (what the
   agent node runs), compiled (cache warm), and before;
3. headless paper scenario (5 s, sampled 10 kHz): CPU and real-time factor, after and before;
   continuous mode after;
4. the whole ``formation-headless paper --no-plots`` process: wall time, after (cache warm),
   after with an empty numba cache (first-ever run, compiling), and before;
5. a 100-agent random tree (formation-generate, seed 11) at 1 kHz, 2 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "config" / "paper_5agents.yaml"
PY = sys.executable

AGENT_PROBE = r"""
import resource, sys, time
t0 = time.perf_counter()
import numpy as np
from formation_agent.controller import AgentController
from formation_msgs_py.spec import agent_view, load_formation
spec = load_formation(sys.argv[1])
ctrl = AgentController(agent_view(spec, "3"))
p = np.array([a.position for a in spec.agents]); R = np.array([a.R_world_body for a in spec.agents])
idx = {a.id: a.index for a in spec.agents}
rel = {j: ((R[2].T @ (p[idx[j]] - p[2])).tolist(), (R[2].T @ R[idx[j]]).tolist()) for j in ctrl.view.neighbours}
ctrl.compute(0.0, rel, [0.0] * 6)
start = time.perf_counter() - t0
n = 5000
c0 = time.process_time()
for k in range(n):
    ctrl.compute(1e-4 * k, rel, [0.0] * 6)
per_call = (time.process_time() - c0) / n * 1e6
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print({"start_s": round(start, 2), "compute_us": round(per_call, 1), "rss_mb": round(rss)})
"""

HEADLESS_PROBE = r"""
import sys, time
from formation_msgs_py.spec import load_formation
from formation_sim.headless import run_headless
spec = load_formation(sys.argv[1], overrides={"duration": float(sys.argv[2])})
mode = sys.argv[3]
run_headless(spec.with_simulation(duration=0.002), controller_mode=mode)  # compile / load outside the timing
c0, w0 = time.process_time(), time.perf_counter()
s = run_headless(spec, controller_mode=mode).summary
cpu, wall = time.process_time() - c0, time.perf_counter() - w0
d = spec.simulation.duration
print({"cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "rtf_cpu": round(d / cpu, 2), "rtf_wall": round(d / wall, 2),
       "funnels_held": s["funnels_held"], "worst_margin": s["worst_margin"]})
"""

KERNEL_PROBE = r"""
import time, numba, numpy as np
from formation_msgs_py.spec import load_formation, simulator_view
from formation_sim.simulation import Simulation
from formation_sim.loop import closed_loop, sense_and_control
from formation_agent.controller import agent_step
import sys
spec = load_formation(sys.argv[1])
sim = Simulation(simulator_view(spec))
loop = closed_loop(spec, sim)
sense_and_control(loop, 0.0, sim.state.p, sim.state.R, sim.state.v)

@numba.njit
def many(n, i, loop):
    for k in range(n):
        agent_step(0.1, i, loop.p_rel, loop.R_rel, loop.v_measured[i], loop.agents, loop.ends, loop.start, loop.out)

out = {}
for i, name in ((1, "leaf (agent 2, 1 edge)"), (0, "agent 1 (2 edges)"), (2, "agent 3 (3 edges)")):
    many(10, i, loop)
    best = min((lambda c0: (many(20000, i, loop), time.process_time() - c0)[1])(time.process_time()) for _ in range(5))
    out[name] = round(best / 20000 * 1e6, 3)
print(out)
"""


def run(cmd: list[str], env: dict[str, str] | None = None, cwd: Path | None = None) -> tuple[str, float]:
    """(stdout's last line, wall seconds) of a subprocess."""
    w0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    wall = time.perf_counter() - w0
    if r.returncode not in (0, 1):
        raise RuntimeError(f"{cmd[:3]} failed ({r.returncode}): {r.stderr[-2000:]}")
    lines = r.stdout.strip().splitlines()
    return (lines[-1] if lines else ""), wall


def env_for(src: Path | None, **extra: str) -> dict[str, str]:
    """The environment of a probe: the current tree (None) or an archived ``src`` tree first on the path."""
    env = {**os.environ, **extra}
    if src is not None:
        packages = ("formation_msgs_py", "formation_agent", "formation_sim")
        env["PYTHONPATH"] = os.pathsep.join(str(src / p) for p in packages)
    return env


def probe(code: str, *args: str, src: Path | None = None, **extra: str) -> dict:
    out, _ = run([PY, "-c", code, *map(str, args)], env_for(src, **extra))
    return eval(out)  # the probes print a dict literal


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="commit to compare with (its src/ is archived to a temporary directory)")
    parser.add_argument("--quick", action="store_true", help="1 s horizons instead of 5 s")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    duration = 1.0 if args.quick else 5.0
    results: dict = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "load_average_1min_start": round(os.getloadavg()[0], 2),
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }
    tmp = Path(tempfile.mkdtemp(prefix="core_bench_"))
    before = None
    if args.before:
        subprocess.run(f"git archive {args.before} src | tar -x -C {tmp}", shell=True, check=True, cwd=REPO)
        before = tmp / "src"
        results["before_commit"] = args.before

    def show(key: str, value) -> None:
        results[key] = value
        print(f"{key}: {value}", flush=True)

    show("controller_kernel_us (compiled, in a compiled loop)", probe(KERNEL_PROBE, PAPER))
    show("agent_process interpreted (agent node)", probe(AGENT_PROBE, PAPER, NUMBA_DISABLE_JIT="1"))
    show("agent_process compiled (cache warm)", probe(AGENT_PROBE, PAPER, NUMBA_DISABLE_JIT="0"))
    if before:
        show("agent_process before", probe(AGENT_PROBE, PAPER, src=before))
    show(f"paper {duration:g} s sampled 10 kHz, after", probe(HEADLESS_PROBE, PAPER, duration, "sampled"))
    if before:
        before_run = probe(HEADLESS_PROBE, PAPER, duration, "sampled", src=before)
        show(f"paper {duration:g} s sampled 10 kHz, before", before_run)
    show(f"paper {duration:g} s continuous, after", probe(HEADLESS_PROBE, PAPER, duration, "continuous"))

    cli = [str(REPO / ".venv" / "bin" / "formation-headless"), str(PAPER), "--no-plots", "--force", "--quiet"]
    cli += ["--duration", str(duration)]
    _, wall = run([*cli, "--out", str(tmp / "cli")])
    show("formation-headless --no-plots wall s, after (cache warm)", round(wall, 2))
    cold = tmp / "numba_cache"
    _, wall = run([*cli, "--out", str(tmp / "cli_cold")], env_for(None, NUMBA_CACHE_DIR=str(cold)))
    show("formation-headless --no-plots wall s, after, empty numba cache (first run, compiling)", round(wall, 2))
    if before:
        code = "import sys; from formation_sim.headless import main; sys.exit(main(sys.argv[1:]))"
        _, wall = run([PY, "-c", code, *cli[1:], "--out", str(tmp / "cli_before")], env_for(before))
        show("formation-headless --no-plots wall s, before", round(wall, 2))

    tree = tmp / "random_100.yaml"
    gen = [str(REPO / ".venv" / "bin" / "formation-generate"), "100", "--topology", "random", "--seed", "11"]
    gen += ["--control-rate", "1000", "--duration", "2"]
    subprocess.run([*gen, "--out", str(tree)], check=True, capture_output=True)
    show("random 100-agent tree, 2 s sampled 1 kHz, after", probe(HEADLESS_PROBE, tree, 2.0, "sampled"))
    results["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
