"""ROS-free bookkeeping of a ROS 2 run, used by the simulator node (``sim_node``).

(The simulator's shadow of the agents' controllers is :class:`formation_sim.core.team.AgentTeam`.)
- :class:`Timing`: latency (measurements published -> wrench received, wall) and on-time counts.
  Per agent and step: ``answered`` (lockstep: every step; realtime: the wrench was in when the next
  tick applied it) and ``on_time`` (realtime: answered, and that tick within half a period of its
  wall-clock time; lockstep: never counted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from formation_sim.core.summary import RunnerKeys


@dataclass
class Timing:
    """Wall-clock statistics of a run (seconds internally, ms in the summary)."""

    n_agents: int
    latencies: list[float] = field(default_factory=list)
    on_time: list[int] = field(default_factory=list)
    answered: list[int] = field(default_factory=list)
    expected: int = 0
    lags: list[float] = field(default_factory=list)
    resends: int = 0
    duplicates: int = 0  # answers received again (an agent answering a resent step twice)

    def __post_init__(self) -> None:
        self.on_time = [0] * self.n_agents
        self.answered = [0] * self.n_agents

    def summary(self, ids: tuple[str, ...], period: float) -> RunnerKeys:
        """summary.json's timing keys: resends, duplicates, latency [ms], on-time fractions, realtime lag [s]."""
        out: RunnerKeys = {"resends": self.resends, "duplicate_answers": self.duplicates}
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
        return out


def finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None
