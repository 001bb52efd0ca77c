"""What the link model costs. Figures for BENCHMARKS.md ("Links"), not asserted.

    .venv/bin/python benchmarks/links_bench.py [--repeat R] [--lockstep-repeat R] [--no-lockstep]
                                               [--sweep-samples N] [--no-sweep]

1. Headless: per formation (the paper preset at 10 kHz, the 100 Hz preset), the compiled closed
   loop's wall time per control step without a link model and with one on every link of every
   channel (2 % independent loss everywhere, which the runs take without leaving a funnel: the
   machinery at full work, the same trajectory length), warm, the best of ``--repeat`` runs.
2. The simulator's per-step link work in a lockstep run (``Simulation.sense`` and ``advance``, one
   step at a time, as formation_sim.node.sim_node calls them), without and with the link model.
3. Lockstep: the CPU of every process of a paper-preset run per control step, without and with that
   link model, (CPU of 0.55 s − CPU of 0.05 s) / 5 000 steps as ``ros_bench.py`` step_cpu takes it,
   ``--lockstep-repeat`` pairs interleaved (``--no-lockstep`` skips it).
4. A tolerance sweep of about 1 000 runs of the paper scenario on two local workers:
   config/campaigns/paper_links.yaml's grid (54 delay × loss cells) with ``--sweep-samples`` plants
   (default 19: 1 026 runs), the wall time of ``formation-campaign``.

Wall times: take them on a quiet machine.
"""

from __future__ import annotations

import argparse
import copy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from formation_core.formation import simulator_view
from formation_core.spec import formation_from_dict
from formation_sim.cli.headless import run_headless
from formation_sim.core.simulation import Simulation

REPO = Path(__file__).resolve().parents[1]
FILES = (REPO / "config" / "paper_5agents.yaml", REPO / "config" / "realtime_5agents_100hz.yaml")
LOSSY = {"model": "independent", "probability": 0.02}
ALL_LINKS = {"poses": {"loss": LOSSY}, "velocity": {"loss": LOSSY}, "wrench": {"loss": LOSSY}}


def spec_of(path: Path, links: bool):
    doc = yaml.safe_load(path.read_text())
    doc = copy.deepcopy(doc)
    doc.setdefault("defaults", {}).setdefault("agent", {})
    doc["defaults"]["agent"]["links"] = ALL_LINKS if links else {}
    return formation_from_dict(doc, source=str(path))


def headless_us(spec, repeat: int) -> float:
    steps = round(spec.simulation.duration * spec.simulation.control_rate) + 1
    run_headless(spec)  # compile or load the kernels
    best = min(run_headless(spec).summary["wall_time"] for _ in range(repeat))
    return best / steps * 1e6


def stepped_us(spec, steps: int) -> float:
    sim = Simulation(simulator_view(spec))
    u = np.zeros((len(spec.agents), 6))
    sim.sense()
    sim.advance(u)  # warm
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.sense()
        sim.advance(u)
    return (time.perf_counter() - t0) / steps * 1e6


def lockstep_ms(links: bool, base: Path, tag: str) -> float:
    """CPU [ms] of every process per lockstep step of the paper preset, with or without the link model."""
    from ros_bench import launch, total_cpu

    doc = yaml.safe_load(FILES[0].read_text())
    doc.setdefault("defaults", {}).setdefault("agent", {})["links"] = ALL_LINKS if links else {}
    formation = base / f"paper_links_{'on' if links else 'off'}.yaml"
    formation.write_text(yaml.safe_dump(doc))
    cpu = {}
    for d in (0.05, 0.55):
        res = launch(formation, base / f"{tag}_{d}", "--mode", "lockstep", "--duration", str(d), "--no-record")
        assert res["exit"] == 0, res["stderr_tail"]
        cpu[d] = total_cpu(res["processes"])["total"]
    return 1e3 * (cpu[0.55] - cpu[0.05]) / 5000


def sweep(samples: int) -> tuple[int, float]:
    doc = yaml.safe_load((REPO / "config" / "campaigns" / "paper_links.yaml").read_text())
    doc["formation"] = str(REPO / "config" / "paper_5agents.yaml")
    doc["samples"] = samples
    runs = samples * len(doc["links"]["delay"]) * len(doc["links"]["loss"]) * len(doc["control_rates"])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sweep.yaml"
        path.write_text(yaml.safe_dump(doc))
        t0 = time.perf_counter()
        cmd = [str(Path(sys.executable).with_name("formation-campaign")), str(path), "--out", f"{tmp}/out"]
        subprocess.run([*cmd, "--workers", "2", "--quiet"], check=True, capture_output=True)
        return runs, time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--sweep-samples", type=int, default=19)
    p.add_argument("--no-sweep", action="store_true")
    p.add_argument("--lockstep-repeat", type=int, default=2)
    p.add_argument("--no-lockstep", action="store_true")
    args = p.parse_args()
    for path in FILES:
        off, on = spec_of(path, False), spec_of(path, True)
        a, b = headless_us(off, args.repeat), headless_us(on, args.repeat)
        print(f"headless {path.name}: {a:.2f} µs/step without links, {b:.2f} with ({b / a:.2f}x)")
        s_off, s_on = stepped_us(off, 2000), stepped_us(on, 2000)
        print(f"  simulator, sense + advance one step at a time: {s_off:.1f} µs/step without, {s_on:.1f} with")
    if not args.no_lockstep:
        sys.path.insert(0, str(Path(__file__).parent))
        with tempfile.TemporaryDirectory() as tmp:
            base = Path(tmp)
            lockstep_ms(True, base, "warm")  # compile the agents' kernels of this code once
            for r in range(args.lockstep_repeat):
                off, on = lockstep_ms(False, base, f"off{r}"), lockstep_ms(True, base, f"on{r}")
                line = f"lockstep paper_5agents.yaml #{r}: {off:.3f} ms CPU/step without links, {on:.3f} with"
                print(line, flush=True)
    if not args.no_sweep:
        runs, wall = sweep(args.sweep_samples)
        print(f"sweep: {runs} runs of the paper scenario (paper_links grid) in {wall:.1f} s on 2 workers")


if __name__ == "__main__":
    main()
