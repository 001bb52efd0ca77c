"""The lockstep witness's cost per step in the simulator, in process, without DDS. Figures for
BENCHMARKS.md ("Lockstep ROS 2 runs", the witness), not asserted.

    .venv/bin/python benchmarks/witness_bench.py [--steps N] [--repeat R] [FILE ...]

Per formation file (default: the paper preset and config/random_20agents.yaml), a lockstep run's
simulator-side work is stepped as formation_sim.node.sim_node steps it, every agent answering
exactly the witness's wrench, and each part is timed per step: ``sense`` (the measurement model),
``encode`` (the messages' bytes), and the witness: ``decode`` (what the agents decode from the
bytes, their value checks included), ``shadow`` (every agent's controller in its code form, the
expectations), ``judge`` (every answer admitted) and ``answered`` (the step closed); then the
recorder and ``advance`` (the plant). A bit-for-bit agent costs its shadow's step and one
comparison; an agent judged within the round-off bound (``--bound``) also the bound of each step.
Wall times in µs: take them on a quiet machine. The median of ``--repeat`` runs is printed.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.node.step_messages import StepMessages
from formation_sim.node.stepping import WrenchBook, admit
from formation_sim.node.witness import AgentReport, Witness

REPO = Path(__file__).resolve().parents[1]
DEFAULT_FILES = (REPO / "config" / "paper_5agents.yaml", REPO / "config" / "random_20agents.yaml")
PARTS = ("sense", "encode", "decode", "shadow", "judge", "answered", "record", "advance")
WITNESS_PARTS = ("decode", "shadow", "judge", "answered")


def one_run(path: Path, steps: int, bound: bool) -> dict[str, float]:
    """µs per step of each part over ``steps`` lockstep steps of ``path``."""
    spec = load_formation(path)
    s = spec.simulation
    sim, messages, witness = Simulation(simulator_view(spec)), StepMessages(spec), Witness(spec)
    if bound:
        for i in range(len(spec.agents)):
            witness.agent_reported(i, AgentReport("compiled", "another host", None, None))
    every = max(1, round(s.control_rate / s.record_rate))
    recorder = RunRecorder(spec, record_every=every, control_rate=s.control_rate)
    totals = dict.fromkeys(PARTS, 0.0)
    clock = time.perf_counter
    n = len(spec.agents)
    for _ in range(steps):
        t0 = clock()
        meas = sim.sense()
        t1 = clock()
        messages.encode(meas)
        t2 = clock()
        received = messages.decoded(meas)
        t3 = clock()
        margin_v, _ = witness.step(received, recorder)
        t4 = clock()
        book = WrenchBook(n)
        for i in range(n):
            decision = admit(i, received.ns, witness.answers.expected[i].u, None, book, witness.answers)
            book.accept(i, received.ns, decision.u)
        t5 = clock()
        witness.answered(margin_v, meas.t)
        t6 = clock()
        u = np.array(book.value)
        recorder.add(meas.t, sim.state.p, sim.state.R, sim.state.v, None)
        recorder.set_inputs(u, margin_v)
        t7 = clock()
        sim.advance(u)
        t8 = clock()
        for part, dt in zip(PARTS, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6, t8 - t7)):
            totals[part] += dt
    return {part: total / steps * 1e6 for part, total in totals.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="*", type=Path, default=list(DEFAULT_FILES))
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--bound", action="store_true", help="every agent judged within the round-off bound")
    args = p.parse_args()
    for path in args.files:
        runs = [one_run(path, args.steps, args.bound) for _ in range(args.repeat)]
        median = {part: statistics.median(r[part] for r in runs) for part in PARTS}
        witness = sum(median[part] for part in WITNESS_PARTS)
        parts = ", ".join(f"{part} {median[part]:.1f}" for part in PARTS)
        judged = "within the bound" if args.bound else "bit for bit"
        print(f"{path.name} ({judged}): witness {witness:.1f} µs per step; {parts}", end="")
        print(f" (µs per step, median of {args.repeat})")


if __name__ == "__main__":
    main()
