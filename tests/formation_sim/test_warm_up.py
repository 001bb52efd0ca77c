"""The simulator compiles (or loads) its kernels when it is built, before discovery, not inside
lockstep step 0 or a realtime run's first tick (on a cold numba cache that took longer than the
step timeout, and the link kernels 1.9 s of a realtime run's 1 s lag budget), and the warm-up has
no side effect on the run (noise streams, state, the links' held samples, the agents' funnel start)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_sim.core.links import link_summary
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"
LINKS = REPO / "config" / "links_5agents_100hz.yaml"

#: A fresh process (its dispatchers know no signature yet) builds what formation_sim.node.runner.Runner builds
#: before discovery, then steps as run_lockstep does and lists the kernels that compiled then.
STEPS_AFTER_CONSTRUCTION = r"""
import json, sys
import numpy as np
from formation_sim.core import links, measurement, plant, team
from formation_core.spec import load_formation
from formation_core.formation import simulator_view
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
spec = load_formation(sys.argv[1])
sim, shadow = Simulation(simulator_view(spec)), team.AgentTeam(spec)
kernels = {"team_step": team.team_step, "rkmk4_step": plant.rkmk4_step,
           "measured_velocity_into": plant.measured_velocity_into, "relative_poses": measurement.relative_poses}
if sim.links is not None:
    kernels.update(receive_step=links.receive_step, deliver_step=links.deliver_step, ages_step=links.ages_step)
built = {name: len(k.signatures) for name, k in kernels.items()}
rec = RunRecorder(spec, record_every=1, mode="ros2-lockstep", control_rate=spec.simulation.control_rate)
for k in range(3):
    meas = sim.sense()
    _, margin_v, _ = shadow.evaluate(meas, rec)
    rec.add(meas.t, sim.state.p, sim.state.R, sim.state.v, None, margin_v)
    u = np.zeros((len(spec.agents), 6))
    rec.set_inputs(u)
    sim.advance(u)
    sim.link_ages()
print(json.dumps({"built": built, "new": {n: len(k.signatures) - built[n] for n, k in kernels.items()}}))
"""


@pytest.mark.parametrize("preset", [PAPER, LINKS], ids=["paper", "links"])
def test_simulator_compiles_its_kernels_when_built(preset: Path) -> None:
    """Every kernel a step calls (with a link model, the links' too) has its signature after Simulation
    and AgentTeam are built: no compilation inside a step (compiled mode, as the simulator runs)."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "0"}
    out = subprocess.run(
        [sys.executable, "-c", STEPS_AFTER_CONSTRUCTION, str(preset)],
        capture_output=True, text=True, check=True, env=env, timeout=600,
    )  # fmt: skip
    result = json.loads(out.stdout.splitlines()[-1])
    assert all(n >= 1 for n in result["built"].values()), result
    assert result["new"] == dict.fromkeys(result["built"], 0), result


@pytest.mark.parametrize("preset", [PAPER, LINKS], ids=["paper", "links"])
def test_warm_up_has_no_side_effect(preset: Path) -> None:
    """A simulator that warmed up gives exactly the measurements, link ages and states of one that did
    not (same noise and link draws); a shadow team that warmed up has started no agent's velocity funnel."""
    spec = load_formation(preset)
    warm, cold = Simulation(simulator_view(spec)), Simulation(simulator_view(spec), warm_up=False)
    team = AgentTeam(spec)
    assert np.isnan(team.start).all()
    for _ in range(20):  # the links preset's samples arrive after a few steps: ages held, not only NaN
        a, b = warm.sense(), cold.sense()
        np.testing.assert_array_equal(a.velocities, b.velocities)
        for name in ("p_rel", "R_rel", "in_range"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        u, _, _ = team.evaluate(a, None)
        warm.advance(u)
        cold.advance(u)
        np.testing.assert_array_equal(warm.link_ages(), cold.link_ages())
        np.testing.assert_array_equal(warm.state.p, cold.state.p)
        np.testing.assert_array_equal(warm.state.R, cold.state.R)
    if warm.links is not None:  # every sample sent, lost, delivered and superseded counted alike
        view = simulator_view(spec)
        assert link_summary(warm.links, view) == link_summary(cold.links, view)
