"""Benchmarks of the ROS-free core, before and after. Figures for BENCHMARKS.md ("Headless core"), not asserted.

    .venv/bin/python benchmarks/core_bench.py [--before COMMIT] [--part after|before|both]
                                              [--work DIR] [--quick] [--json FILE]

The current tree ("after") and, with ``--before COMMIT``, the core of that commit (``git archive``
into the work directory, run with the same interpreter), each side measuring (wall times: take
them on a quiet machine):

1. the compiled kernels of one control step, each timed in a compiled loop (controller of every
   agent, RKMK4 of every body, measurements, recording and funnel check);
2. the controller called from Python (the compiled kernel on arrays built once, and
   ``AgentController.compute``); an agent process's start, compute and peak RSS, interpreted
   and compiled;
3. the headless paper scenario (5 s, sampled 10 kHz, and continuous): wall and CPU time;
4. the whole ``formation-headless paper --no-plots`` process: with an empty numba cache (the
   first-ever run, compiling), then three times with the cache warm;
5. a 100-agent random tree (formation-generate, seed 11) at 1 kHz, 2 s.

``--part`` measures one side (each fits in one short quiet command); ``--work`` keeps the
archive and its numba cache between the two.
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

#: agent 3 of the paper (3 edges) and its measurements at t = 0, after its first compute
AGENT_SETUP = r"""
from formation_agent.controller import AgentController
from formation_core.spec import load_formation
from formation_core.formation import agent_view
spec = load_formation(sys.argv[1])
ctrl = AgentController(agent_view(spec, "3"))
p = np.array([a.position for a in spec.agents]); R = np.array([a.R_world_body for a in spec.agents])
idx = {a.id: a.index for a in spec.agents}
rel = {j: ((R[2].T @ (p[idx[j]] - p[2])).tolist(), (R[2].T @ R[idx[j]]).tolist()) for j in ctrl.view.neighbours}
ctrl.compute(0.0, rel, [0.0] * 6)
"""

AGENT_PROBE = (
    r"""
import resource, sys, time
t0 = time.perf_counter()
import numpy as np
"""
    + AGENT_SETUP
    + r"""
start = time.perf_counter() - t0
n = 5000
c0 = time.process_time()
for k in range(n):
    ctrl.compute(1e-4 * k, rel, [0.0] * 6)
per_call = (time.process_time() - c0) / n * 1e6
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print({"start_s": round(start, 2), "compute_us": round(per_call, 1), "rss_mb": round(rss)})
"""
)

HEADLESS_PROBE = r"""
import sys, time
from formation_core.spec import load_formation
from formation_sim.cli.headless import run_headless
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

BEST_US = r"""  # the time advances by 1 ns per call: no work can be hoisted out of the timed loops
import time


def best_us(f, *a, n=20000):
    f(10, *a)
    times = []
    for _ in range(5):
        c0 = time.perf_counter()
        f(n, *a)
        times.append(time.perf_counter() - c0)
    return round(min(times) / n * 1e6, 3)
"""

KERNEL_PROBE = (
    BEST_US
    + r"""
import sys, time, numba, numpy as np
from formation_core.spec import load_formation
from formation_core.formation import simulator_view
from formation_sim.core.simulation import Simulation
from formation_sim.core.loop import closed_loop, new_buffers, new_watch, record_step, check_step, sense_and_control
from formation_sim.core.measurement import relative_poses
from formation_sim.core.plant import measured_velocity_into, new_workspace, rkmk4_step
from formation_sim.core.judge import Judge
from formation_sim.core.team import team_step
from formation_agent.controller import U, agent_step
spec = load_formation(sys.argv[1])
sim = Simulation(simulator_view(spec), warm_up=False)
loop = closed_loop(spec, sim)
loop = loop._replace(noise=sim.sensors.draw_noise(20001), cursor=np.zeros(1, dtype=np.int64))
p, R, v = sim.state.p.copy(), sim.state.R.copy(), sim.state.v.copy()
N = len(p)
import inspect
# a step index first where the loop steps links (the trees since then), else only the times
step_first = "k" in inspect.signature(sense_and_control).parameters
sense_and_control(loop, *((0,) if step_first else ()), 0.0, 0.0, p, R, v)
work, watch = new_workspace(N), new_watch(spec, Judge(spec))
buf = new_buffers(2000, N, len(loop.ends), len(spec.edges))
J = numba.njit(_nrt=False)

@J
def team(n, l):
    for k in range(n):
        t = 0.1 + 1e-9 * k
        team_step(t, l.p_rel, l.R_rel, l.in_range, l.v_measured, l.first_end, l.agents, l.ends, l.start, l.out,
                  l.edge_out)

@J
def agent(n, l, i):
    lo, hi = l.first_end[i], l.first_end[i + 1]
    for k in range(n):
        t = 0.1 + 1e-9 * k
        agent_step(t, i, lo, hi, l.p_rel, l.R_rel, l.v_measured[i], l.agents, l.ends, l.start, l.out, l.edge_out)

@J
def rk(n, l, p, R, v, work):
    for k in range(n):
        rkmk4_step(0.1 + 1e-9 * k, p, R, v, l.out[:, U : U + 6], 1e-9, l.plant, work)

@J
def meas(n, l, p, R, v):
    for k in range(n):
        relative_poses(p, R, l.sensing, l.noise[k], l.p_rel, l.q_rel, l.R_rel, l.in_range)
        measured_velocity_into(0.1 + 1e-9 * k, p, R, v, l.plant.noise, l.v_measured)

@J
def rec(n, l, w, p, R, v, buf):
    for k in range(n):
        record_step(buf, k % 2000, 0.1 + 1e-9 * k, p, R, v, l.out, l.in_range)
        check_step(w, buf, k % 2000, 0.1 + 1e-9 * k, p, R, l.out)

out = {"team_step, 5 agents": best_us(team, loop)}
for i in range(N):
    edges = loop.first_end[i + 1] - loop.first_end[i]
    out[f"agent_step, agent {spec.agents[i].id} ({edges} edges)"] = best_us(agent, loop, i)
out["rkmk4_step, 5 bodies"] = best_us(rk, loop, p, R, v, work)
out["measurements (relative poses + noisy twists)"] = best_us(meas, loop, p, R, v)
out["recording buffers + funnel check"] = best_us(rec, loop, watch, p, R, v, buf)
print(out)
"""
)

BEFORE_KERNEL_PROBE = (
    BEST_US
    + r"""
import sys, time, numba, numpy as np
from formation_core.spec import load_formation
from formation_core.formation import simulator_view
from formation_sim.core.simulation import Simulation
from formation_sim.core.loop import closed_loop, sense_and_control
from formation_sim.core.measurement import relative_poses
from formation_sim.core.plant import measured_velocity_into, new_workspace, rkmk4_step
from formation_sim.core.team import team_step
from formation_agent.controller import agent_step
spec = load_formation(sys.argv[1])
sim = Simulation(simulator_view(spec))
loop = closed_loop(spec, sim)
loop = loop._replace(noise=sim.sensors.draw_noise(20001), cursor=np.zeros(1, dtype=np.int64))
p, R, v = sim.state.p.copy(), sim.state.R.copy(), sim.state.v.copy()
N = len(p)
sense_and_control(loop, 0.0, p, R, v)
work = new_workspace(N)

@numba.njit
def team(n, l):
    for k in range(n):
        team_step(0.1 + 1e-9 * k, l.p_rel, l.R_rel, l.in_range, l.v_measured, l.agents, l.ends, l.start, l.out)

@numba.njit
def agent(n, l, i):
    for k in range(n):
        agent_step(0.1 + 1e-9 * k, i, l.p_rel, l.R_rel, l.v_measured[i], l.agents, l.ends, l.start, l.out)

@numba.njit
def rk(n, l, p, R, v, work):
    for k in range(n):
        rkmk4_step(0.1 + 1e-9 * k, p, R, v, l.out.u, 1e-9, l.plant, work)

@numba.njit
def meas(n, l, p, R, v):
    for k in range(n):
        relative_poses(p, R, l.sensing, l.noise[k], l.p_rel, l.R_rel, l.in_range)
        measured_velocity_into(0.1 + 1e-9 * k, p, R, v, l.plant.noise, l.v_measured)

out = {"team_step, 5 agents": best_us(team, loop)}
for i in range(N):
    out[f"agent_step, agent {spec.agents[i].id}"] = best_us(agent, loop, i)
out["rkmk4_step, 5 bodies"] = best_us(rk, loop, p, R, v, work)
out["measurements (relative poses + noisy twists)"] = best_us(meas, loop, p, R, v)
print(out)
"""
)

CALL_PROBE = (
    r"""
import sys, time, numpy as np
from formation_agent.controller import agent_step
"""
    + AGENT_SETUP
    + r"""
n = len(ctrl.neighbours)
args = (ctrl._p, ctrl._R, np.zeros(6), ctrl._agents, ctrl._ends, ctrl._start, ctrl._out, ctrl._edge_out)

def per_call(f, n=20000):
    times = []
    for _ in range(5):
        c0 = time.perf_counter()
        for k in range(n):
            f(k)
        times.append(time.perf_counter() - c0)
    return round(min(times) / n * 1e6, 2)

print({
    "agent_step from Python (arrays built once), 3 edges": per_call(lambda k: agent_step(1e-4 * k, 0, 0, n, *args)),
    "AgentController.compute (dict of poses -> ControlOutput), 3 edges": per_call(
        lambda k: ctrl.compute(1e-4 * k, rel, [0.0] * 6)),
})
"""
)


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


def side(name: str, src: Path | None, tmp: Path, duration: float, show) -> None:
    """Every figure of one side: the current tree (``src`` None) or an archived ``before`` tree."""
    try:
        kernels = probe(KERNEL_PROBE, PAPER, src=src)
    except SyntaxError:  # an older tree: its kernels' older signatures (the probe printed no dict)
        kernels = probe(BEFORE_KERNEL_PROBE, PAPER, src=src)
    show(f"{name}: kernels in a compiled loop [us per call]", kernels)
    show(f"{name}: agent process, interpreted", probe(AGENT_PROBE, PAPER, src=src, NUMBA_DISABLE_JIT="1"))
    show(f"{name}: agent process, compiled (cache warm)", probe(AGENT_PROBE, PAPER, src=src, NUMBA_DISABLE_JIT="0"))
    if src is None:
        show(f"{name}: controller called from Python [us]", probe(CALL_PROBE, PAPER))
    show(f"{name}: paper {duration:g} s sampled 10 kHz", probe(HEADLESS_PROBE, PAPER, duration, "sampled", src=src))
    show(f"{name}: paper {duration:g} s continuous", probe(HEADLESS_PROBE, PAPER, duration, "continuous", src=src))
    code = "import sys; from formation_sim.cli.headless import main; sys.exit(main(sys.argv[1:]))"
    cli = [PY, "-c", code, str(PAPER), "--no-plots", "--force", "--quiet", "--duration", str(duration)]
    cold = tmp / f"numba_cache_{name}"
    _, wall = run([*cli, "--out", str(tmp / f"cli_cold_{name}")], env_for(src, NUMBA_CACHE_DIR=str(cold)))
    show(f"{name}: formation-headless --no-plots, wall s, empty numba cache (first run, compiling)", round(wall, 2))
    walls = []
    for _ in range(3):
        _, wall = run([*cli, "--out", str(tmp / f"cli_{name}")], env_for(src, NUMBA_CACHE_DIR=str(cold)))
        walls.append(round(wall, 2))
    show(f"{name}: formation-headless --no-plots, wall s, cache warm (3 runs)", walls)
    tree = tmp / "random_100.yaml"
    if not tree.exists():
        gen = [str(REPO / ".venv" / "bin" / "formation-generate"), "100", "--topology", "random", "--seed", "11"]
        gen += ["--control-rate", "1000", "--duration", "2"]
        subprocess.run([*gen, "--out", str(tree)], check=True, capture_output=True)
    show(f"{name}: random 100-agent tree, 2 s sampled 1 kHz", probe(HEADLESS_PROBE, tree, 2.0, "sampled", src=src))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="commit to compare with (its src/ is archived to the work directory)")
    parser.add_argument("--part", choices=("after", "before", "both"), default="both", help="which side to measure")
    parser.add_argument("--work", type=Path, help="work directory (default: a new temporary one)")
    parser.add_argument("--quick", action="store_true", help="1 s horizons instead of 5 s")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    duration = 1.0 if args.quick else 5.0
    results: dict = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "load_average_1min_start": round(os.getloadavg()[0], 2),
        "started": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }
    tmp = args.work or Path(tempfile.mkdtemp(prefix="core_bench_"))
    tmp.mkdir(parents=True, exist_ok=True)

    def show(key: str, value) -> None:
        results[key] = value
        print(f"{key}: {value}", flush=True)

    if args.part in ("after", "both"):
        side("after", None, tmp, duration, show)
    if args.before and args.part in ("before", "both"):
        before = tmp / "before" / "src"
        if not before.exists():
            before.parent.mkdir(parents=True)
            subprocess.run(
                f"git archive {args.before} src | tar -x -C {before.parent}", shell=True, check=True, cwd=REPO
            )
        results["before_commit"] = args.before
        side("before", before, tmp, duration, show)
    results["load_average_1min_end"] = round(os.getloadavg()[0], 2)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
