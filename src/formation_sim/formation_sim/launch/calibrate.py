"""``formation-check --calibrate``: measure this host's CPU per message and store it.

Runs the floor (:mod:`formation_sim.node.calibration_chain`: a realtime run's messages with no work) of a
chain of :data:`AGENTS` agents at :data:`RATE` Hz for :data:`TICKS` ticks after :data:`WARMUP`
(20-40 s with start-up on two cores), in a reserved ROS domain, and divides each process's CPU
by the messages it sent and took: the simulator's cost per message and an agent's (their mean),
which :func:`formation_sim.capacity.calibrated` turns into the host's costs. The result goes
to :func:`formation_sim.capacity.calibration_path` with the host name, its cores and the
date; :func:`formation_sim.capacity.load_costs` reads it back.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from formation_core.errors import CalibrationError
from formation_sim import capacity
from formation_sim.launch.dds_env import run_environment
from formation_sim.launch.supervisor import die_with_parent

#: the calibration floor: agents of a chain, tick rate [Hz], ticks measured after the warm-up ticks;
#: 20 agents at 100 Hz, as the floor figures the built-in message costs come from
AGENTS, RATE, TICKS, WARMUP = 20, 100.0, 300, 100
#: wall s a floor process may take, start-up and discovery included
TIMEOUT_S = 180.0


def measure(agents: int = AGENTS, rate: float = RATE, ticks: int = TICKS, warmup: int = WARMUP) -> dict[str, Any]:
    """Run the floor; {"sim": {...}, "agents": {id: {...}}} as each process reported it."""
    from formation_sim.capacity import chain_ids

    with tempfile.TemporaryDirectory(prefix="formation-calibrate-") as logs:
        env = run_environment(dict(os.environ), log_dir=Path(logs))
        common = ["--agents", str(agents), "--rate", str(rate), "--ticks", str(ticks), "--warmup", str(warmup)]
        roles = [f"agent:{a}" for a in chain_ids(agents)] + ["sim"]
        procs: dict[str, subprocess.Popen[str]] = {}
        try:
            for role in roles:
                procs[role] = subprocess.Popen(
                    [sys.executable, "-m", "formation_sim.node.calibration_chain", role, *common],
                    env=env,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                    start_new_session=True,
                    preexec_fn=die_with_parent,
                )
            results: dict[str, Any] = {}
            for role in reversed(roles):  # the simulator's error first
                try:
                    stdout, stderr = procs[role].communicate(timeout=TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    raise CalibrationError(
                        f"calibration: floor process {role} took more than {TIMEOUT_S:g} s"
                    ) from None
                if procs[role].returncode != 0:
                    why = stderr.strip()[-600:]
                    raise CalibrationError(f"calibration: floor process {role} exited {procs[role].returncode}: {why}")
                results[role] = json.loads(stdout.strip().splitlines()[-1])
        finally:  # only ours, by PID: SIGINT (Fast DDS frees its shared memory), then SIGKILL
            for p in procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            for p in procs.values():
                try:
                    p.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    return {"sim": results.pop("sim"), "agents": {r.split(":", 1)[1]: v for r, v in results.items()}}


def calibrate(path: Path | None = None) -> tuple[Path, capacity.Costs, dict[str, Any]]:
    """Measure and store this host's message costs; (file written, costs, the measurement)."""
    m = measure(AGENTS, RATE, TICKS, WARMUP)
    sim = m["sim"]
    sim_cost = sim["cpu_s"] / sim["messages"]
    agent_cost = sum(a["cpu_s"] / a["messages"] for a in m["agents"].values()) / len(m["agents"])
    detail = {
        "floor": f"chain of {AGENTS} agents at {RATE:g} Hz, {TICKS} ticks after {WARMUP}",
        "load_1min": os.getloadavg()[0],
        "on_time_fraction": sim["on_time_fraction"],
        "sim_cpu_per_tick_s": sim["cpu_s"] / TICKS,
        "agent_cpu_per_tick_s": {a: v["cpu_s"] / TICKS for a, v in m["agents"].items()},
    }
    written = capacity.save_calibration(sim_cost, agent_cost, detail, path or capacity.calibration_path())
    return written, capacity.load_costs(written), detail
