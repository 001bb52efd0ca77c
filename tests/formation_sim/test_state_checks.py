"""The plant state the simulator goes on with (offline): a non-finite state ends the run INCOMPLETE,
naming the agents, and never reaches summary.json."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from formation_sim.core import state_checks


def test_non_finite_state_names_the_agent() -> None:
    p, R, v = np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 6))
    assert state_checks.non_finite_agents(("1", "2", "3"), p, R, v) == []
    v[1, 4] = math.nan
    R[2, 0, 0] = math.inf
    assert state_checks.non_finite_agents(("1", "2", "3"), p, R, v) == ["2", "3"]


def test_blown_up_plant_ends_the_run_incomplete_naming_the_agent(tmp_path) -> None:
    """An initial spin of 1e200 rad/s overflows the integrator: INCOMPLETE (exit 4), agent named, strict JSON."""
    import yaml

    from formation_core.verdict import ExitCode
    from formation_sim.cli import headless

    agent = {"radius": 0.5, "sensing_radius": 3.0, "dynamics": {"mass": 1.0, "inertia": [0.1, 0.2, 0.3]}}
    doc = {
        "simulation": {"duration": 0.01, "physics_rate": 1000.0, "control_rate": 1000.0, "rate_check": "warn"},
        "agents": [
            {"id": "a", "position": [0, 0, 0], "angular_velocity": [1e200, 1e200, 0], **agent},
            {"id": "b", "position": [2, 0, 0], **agent},
        ],
        "edges": [{"tail": "a", "head": "b", "distance": 1.5}],
    }
    path = tmp_path / "spin.yaml"
    path.write_text(yaml.safe_dump(doc))
    out = tmp_path / "out"
    assert headless.main([str(path), "--out", str(out), "--no-plots", "--quiet"]) == ExitCode.INCOMPLETE
    summary = json.loads((out / "summary.json").read_text())
    # the compiled plant never raises: the overflow shows as a non-finite state of agent a
    assert "non-finite plant state of agent(s) a" in summary["incomplete_reason"]
    json.dumps(summary, allow_nan=False)


class _Sim:
    """What advance_checked needs of a Simulation: advance() moves to the given state."""

    agent_ids = ("1", "2", "3")
    t = 0.001

    def __init__(self, p: np.ndarray, R: np.ndarray, v: np.ndarray) -> None:
        self._next = (p, R, v)

    def advance(self, u: np.ndarray) -> None:
        from formation_sim.core.plant import PlantState

        self.state = PlantState(*self._next)


@pytest.mark.parametrize(
    ("agent", "field", "value", "reason"),
    [
        (None, None, None, ""),
        (1, "v", math.nan, "non-finite plant state of agent(s) 2"),
        (2, "R", -math.inf, "non-finite plant state of agent(s) 3"),
        # finite values whose sum overflows: no agent is non-finite, nothing to report
        (0, "p", 1e308, ""),
    ],
)
def test_advance_checked_names_non_finite_agents_only(agent, field, value, reason) -> None:
    state = {"p": np.zeros((3, 3)), "R": np.tile(np.eye(3), (3, 1, 1)), "v": np.zeros((3, 6))}
    if agent is not None:
        state[field][agent].flat[:2] = value  # two entries: 1e308 + 1e308 overflows the sum
    sim = _Sim(state["p"], state["R"], state["v"])
    got = state_checks.advance_checked(sim, np.zeros((3, 6)))
    assert got == (f"t=0.001000 s: {reason}" if reason else "")
