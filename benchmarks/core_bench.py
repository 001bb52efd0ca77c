"""Benchmarks of the ROS-free core (issue 2). Figures for BENCHMARKS.md, not asserted anywhere.

    .venv/bin/python benchmarks/core_bench.py [--quick] [--json FILE]

Times are CPU seconds of this process (and wall seconds for the runs): the machines are shared.

1. controller evaluation time per agent: a leaf (1 edge) and a 3-neighbour agent;
2. headless paper scenario (5 s): sampled at 10 kHz and continuous (physics 10 kHz): wall time
   and real-time factor;
3. halving the physics step of the sampled paper scenario: max |Δe_k|, |Δψ_k| over 5 s;
4. a 20-agent random tree (5 s at 1 kHz).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
import timeit
from pathlib import Path

import numpy as np

from formation_agent.controller import AgentController
from formation_msgs_py.spec import agent_view, load_formation, simulator_view
from formation_sim.headless import run_headless
from formation_sim.simulation import Simulation

REPO = Path(__file__).resolve().parents[1]


def controller_time(spec, agent_id: str, number: int = 20000, repeat: int = 7) -> float:
    """Median over ``repeat`` runs of the mean time of one compute() call, µs."""
    sim = Simulation(simulator_view(spec))
    meas = sim.sense()
    i = spec.agent(agent_id).index
    ctrl = AgentController(agent_view(spec, agent_id))
    rel, v = meas.relative_poses[agent_id], meas.velocities[i].tolist()
    ctrl.compute(0.0, rel, v)
    # CPU time, not wall: the machines are shared, and CPU time is far less sensitive to load
    times = timeit.repeat(lambda: ctrl.compute(0.1, rel, v), number=number, repeat=repeat, timer=time.process_time)
    return statistics.median(times) / number * 1e6


def headless(spec, mode: str) -> dict:
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_headless(spec, controller_mode=mode)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    s = res.summary
    return {
        "mode": mode,
        "control_rate": spec.simulation.control_rate,
        "physics_rate": spec.simulation.physics_rate,
        "duration": spec.simulation.duration,
        "wall_s": round(wall, 2),
        "real_time_factor": round(spec.simulation.duration / wall, 3),
        "cpu_s": round(cpu, 2),
        "cpu_real_time_factor": round(spec.simulation.duration / cpu, 3),
        "funnels_held": s["funnels_held"],
        "worst_margin": s["worst_margin"],
        "arrays": res.recorder.arrays(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 s horizons instead of 5 s")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    duration = 1.0 if args.quick else 5.0
    paper = load_formation(REPO / "config" / "paper_5agents.yaml", overrides={"duration": duration})
    results: dict = {
        "machine": f"{platform.processor() or platform.machine()}, {platform.python_version()}",
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    results["controller_us"] = {
        "leaf (agent 2, 1 edge)": round(controller_time(paper, "2"), 2),
        "agent 1 (2 edges)": round(controller_time(paper, "1"), 2),
        "agent 3 (3 edges)": round(controller_time(paper, "3"), 2),
    }
    print("controller evaluation [µs]:", results["controller_us"], flush=True)
    sampled = headless(paper, "sampled")
    print({k: v for k, v in sampled.items() if k != "arrays"}, flush=True)
    continuous = headless(paper, "continuous")
    print({k: v for k, v in continuous.items() if k != "arrays"}, flush=True)
    halved = headless(paper.with_simulation(physics_rate=20000.0), "sampled")
    print({k: v for k, v in halved.items() if k != "arrays"}, flush=True)
    results["paper"] = [{k: v for k, v in r.items() if k != "arrays"} for r in (sampled, continuous, halved)]
    results["step_halving"] = {
        "max_abs_delta_e": float(np.abs(sampled["arrays"]["e"] - halved["arrays"]["e"]).max()),
        "max_abs_delta_psi": float(np.abs(sampled["arrays"]["psi"] - halved["arrays"]["psi"]).max()),
    }
    print("step halving:", results["step_halving"], flush=True)
    tree = load_formation(REPO / "config" / "random_20agents.yaml", overrides={"duration": duration})
    results["random_20agents"] = {k: v for k, v in headless(tree, "sampled").items() if k != "arrays"}
    print(results["random_20agents"], flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
