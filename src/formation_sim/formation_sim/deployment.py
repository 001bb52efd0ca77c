"""ROS-free bookkeeping of a ROS 2 run, used by the simulator node (``sim_node``).

- :class:`ShadowControllers`: the simulator re-runs every agent's controller core on exactly
  the measurements it published. In lockstep these are the measurements the agents answer, so
  the velocity-funnel margins (and the ``measurement``/``controller`` faults) recorded in
  ``summary.json`` are the agents' own, step for step, as in the headless runner. In realtime
  they are the margins the agent would have at the simulator's sample times.
- :class:`Timing`: latency (measurements published -> wrench received, wall) and on-time counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from formation_agent.controller import ERROR, AgentController, ControlOutput, MissingMeasurementError
from formation_msgs_py.spec import FormationSpec, agent_view
from formation_sim.report import RunRecorder
from formation_sim.simulation import Measurements


class ShadowControllers:
    """Every agent's controller core, evaluated on the published measurements (no ROS)."""

    def __init__(self, spec: FormationSpec) -> None:
        self.ids = spec.agent_ids
        self.controllers = [AgentController(agent_view(spec, a)) for a in self.ids]

    def evaluate(self, meas: Measurements, recorder: RunRecorder | None) -> tuple[np.ndarray, list[ControlOutput]]:
        """(margin_v (N,6), outputs); records ``measurement`` faults as the headless runner does."""
        outputs = []
        for i, ctrl in enumerate(self.controllers):
            try:
                out = ctrl.compute(meas.t, meas.relative_poses[ctrl.agent_id], meas.velocities[i])
            except MissingMeasurementError as exc:
                out = ctrl.fault_output(meas.t, str(exc))
                if recorder is not None:
                    recorder.fault(meas.t, "measurement", ctrl.agent_id, ",".join(exc.neighbours))
            outputs.append(out)
        return np.array([o.margin_v for o in outputs]), outputs

    def note_errors(self, t: float, outputs: list[ControlOutput], recorder: RunRecorder) -> None:
        """A controller at ERROR (saturated) is a violation, as in the headless runner."""
        if recorder.first_violation is None:
            for aid, o in zip(self.ids, outputs):
                if o.level == ERROR:
                    recorder.fault(t, "controller", aid, o.message)
                    return


@dataclass
class Timing:
    """Wall-clock statistics of a run (seconds internally, ms in the summary)."""

    n_agents: int
    latencies: list[float] = field(default_factory=list)
    on_time: list[int] = field(default_factory=list)
    answered: list[int] = field(default_factory=list)
    expected: int = 0
    lags: list[float] = field(default_factory=list)
    stale: list[int] = field(default_factory=list)
    resends: int = 0

    def __post_init__(self) -> None:
        self.on_time = [0] * self.n_agents
        self.answered = [0] * self.n_agents
        self.stale = [0] * self.n_agents

    def summary(self, ids: tuple[str, ...], period: float) -> dict[str, Any]:
        out: dict[str, Any] = {"resends": self.resends}
        if self.latencies:
            lat = np.array(self.latencies) * 1e3
            out["latency_ms"] = {
                "p50": float(np.percentile(lat, 50)),
                "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max()),
                "samples": int(lat.size),
            }
        if self.expected:
            out["on_time_fraction"] = {a: self.on_time[i] / self.expected for i, a in enumerate(ids)}
            out["on_time_fraction_all"] = sum(self.on_time) / (self.expected * self.n_agents)
            out["answered_fraction_all"] = sum(self.answered) / (self.expected * self.n_agents)
        if self.lags:
            lags = np.array(self.lags)
            out["realtime_lag_s"] = {
                "max": float(lags.max()),
                "mean": float(lags.mean()),
                "final": float(lags[-1]),
                "late_ticks_fraction": float(np.mean(lags > 0.5 * period)),
            }
        if any(self.stale):
            out["stale_commands"] = {a: self.stale[i] for i, a in enumerate(ids) if self.stale[i]}
        return out


def finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None
