"""Every agent's controller stepped together on one step's measurements (no ROS), and the fault policy.

:func:`team_step` is the one closed-loop control step: the run core (headless runs, campaigns)
calls it compiled on its measurement arrays; :class:`AgentTeam` calls it on the measurements the
simulator node published (its *shadow* of the agents: in lockstep these are what the agents
answer, so the velocity-funnel margins and faults it records are the agents' own) and on the
decoded messages of a synthesised bag. The fault policy is the same everywhere (:func:`step_faults`):
an agent missing a neighbour's pose answers a zero wrench at ERROR (:func:`fault_wrench`) and is a
``measurement`` fault (:func:`note_missing`); every other agent at ERROR (saturated: outside a
funnel) is a ``controller`` fault (:func:`note_errors`), counted per agent and step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from formation_agent.controller import (
    AGENT_COLUMNS,
    END_COLUMNS,
    ERROR,
    LEVEL,
    MARGIN_V,
    REASON,
    REASON_MESSAGES,
    REASON_MISSING,
    U,
    agent_step,
    fault_wrench,
    gains,
    new_funnel_start,
    new_outputs,
)
from formation_msgs_py.compiled import kernel
from formation_msgs_py.spec import FormationSpec, agent_view
from formation_sim.core.measurement import Ends
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements


@kernel
def team_step(t, p_rel, R_rel, in_range, v_measured, first_end, agents, ends, start, out, edge_out):
    """Every agent's step at t [s] on end-indexed measurements; an agent missing a pose gets the fault wrench."""
    for i in range(v_measured.shape[0]):
        lo, hi = first_end[i], first_end[i + 1]
        measured = True
        for k in range(lo, hi):
            measured = measured and in_range[k]
        if measured:
            agent_step(t, i, lo, hi, p_rel, R_rel, v_measured[i], agents, ends, start, out, edge_out)
        else:
            fault_wrench(i, lo, hi, REASON_MISSING, out, edge_out)


def load_team_step() -> None:
    """Load (or compile into numba's cache) :func:`team_step` for the types every caller passes,
    on one agent without edges (what it computes is thrown away)."""
    first_end, agents, ends = np.zeros(2, dtype=np.int64), np.zeros((1, AGENT_COLUMNS)), np.zeros((0, END_COLUMNS))
    p_rel, R_rel, in_range = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.bool_)
    outputs = (new_funnel_start(1), *new_outputs(1, 0))
    team_step(0.0, p_rel, R_rel, in_range, np.zeros((1, 6)), first_end, agents, ends, *outputs)


def step_faults(
    first_end: Sequence[int] | np.ndarray,
    neighbours: Sequence[str],
    in_range: Sequence[bool] | np.ndarray,
    level: Sequence[float] | np.ndarray,
    reason: Sequence[float] | np.ndarray,
) -> tuple[dict[int, list[str]], list[tuple[int, str]]]:
    """The fault policy of one step from the kernels' outputs: ({agent index: neighbours whose pose
    is missing}, [(agent index, reason) of every other agent at ERROR]); ``neighbours`` by end."""
    missing: dict[int, list[str]] = {}
    for i in range(len(first_end) - 1):
        gone = [neighbours[k] for k in range(first_end[i], first_end[i + 1]) if not in_range[k]]
        if gone:
            missing[i] = gone
    errors = [(i, REASON_MESSAGES[int(reason[i])]) for i in range(len(level)) if level[i] == ERROR and i not in missing]
    return missing, errors


def note_missing(
    recorder: RunRecorder, t: float, agent_ids: Sequence[str], missing: Mapping[int, Sequence[str]]
) -> None:
    """Agents missing a neighbour's pose ({agent index: neighbour ids}) are ``measurement`` faults.

    Recorded before the step's funnel check (``recorder.add``), so they come first at equal times.
    """
    for i, neighbours in missing.items():
        recorder.fault(t, "measurement", agent_ids[i], ",".join(neighbours))


def note_errors(recorder: RunRecorder, t: float, agent_ids: Sequence[str], errors: Sequence[tuple[int, str]]) -> None:
    """Every agent at ERROR for its controller (saturated: outside a funnel, or a non-finite wrench)
    is a ``controller`` fault: ``errors`` (agent index, reason) excludes agents missing a pose."""
    for i, message in errors:
        recorder.fault(t, "controller", agent_ids[i], message)


class AgentTeam:
    """Every agent's controller of ``spec``, in formation-file order."""

    def __init__(self, spec: FormationSpec) -> None:
        self.ids = spec.agent_ids
        views = [agent_view(spec, a) for a in self.ids]
        self.first_end, self.agents, self.ends = gains(views)
        self.end_neighbours = [ie.neighbour for v in views for ie in v.edges]
        self._pairs = [(v.agent_id, ie.neighbour) for v in views for ie in v.edges]
        self._checked: Ends | None = None
        self.start = new_funnel_start(len(self.ids))
        n = len(self.end_neighbours)
        self.out, self.edge_out = new_outputs(len(self.ids), n)
        # load (or compile) the kernels now, on scratch outputs: not at a realtime run's first step
        p, R, v = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((len(self.ids), 6))
        everyone = np.ones(n, dtype=np.bool_)  # every agent steps (a missing pose would skip agent_step)
        scratch = (new_funnel_start(len(self.ids)), *new_outputs(len(self.ids), n))
        team_step(0.0, p, R, everyone, v, self.first_end, self.agents, self.ends, *scratch)

    def evaluate(
        self, meas: Measurements, recorder: RunRecorder | None
    ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, str]]]:
        """(u (N,6), margin_v (N,6), errors) at ``meas.t``; ``errors`` lists (agent index, reason) of
        the agents at ERROR for their controller (:meth:`note_errors` records them). With a recorder,
        the agents missing a pose are recorded now (``measurement`` faults)."""
        if meas.ends is not self._checked:  # the measurements' end order must be the kernels'
            if list(zip(meas.ends.observer, meas.ends.target)) != self._pairs:
                raise ValueError("measurements by edge end in another order than the team's controllers")
            self._checked = meas.ends
        out, in_range = self.out, meas.in_range
        team_step(
            meas.t, meas.p_rel, meas.R_rel, in_range, meas.velocities,
            self.first_end, self.agents, self.ends, self.start, out, self.edge_out,
        )  # fmt: skip
        errors: list[tuple[int, str]] = []
        if not in_range.all() or out[:, LEVEL].max() == ERROR:
            missing, errors = step_faults(self.first_end, self.end_neighbours, in_range, out[:, LEVEL], out[:, REASON])
            if recorder is not None:
                note_missing(recorder, meas.t, self.ids, missing)
        return out[:, U : U + 6].copy(), out[:, MARGIN_V : MARGIN_V + 6].copy(), errors

    def note_errors(self, t: float, errors: Sequence[tuple[int, str]], recorder: RunRecorder) -> None:
        """Record :meth:`evaluate`'s ``errors`` (``controller`` faults)."""
        note_errors(recorder, t, self.ids, errors)
