"""Every agent's controller stepped together on one step's measurements (no ROS), and the fault policy.

:func:`team_step` is the one closed-loop control step: the run core (headless runs, campaigns)
calls it compiled on its measurement arrays; :class:`AgentTeam` calls it on the measurements the
simulator node published (its *shadow* of the agents: in lockstep these are what the agents
answer, so the velocity-funnel margins and faults it records are the agents' own) and on the
decoded messages of a synthesised bag. The fault policy is the same everywhere: an agent missing
a neighbour's pose answers a zero wrench at ERROR (:func:`fault_wrench`) and is a ``measurement``
fault (:func:`note_missing`); every other agent at ERROR (saturated: outside a funnel) is a
``controller`` fault (:func:`note_errors`), counted per agent and step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from formation_agent.controller import (
    AGENT_COLUMNS,
    END_COLUMNS,
    ERROR,
    MARGIN_V,
    REASON_MISSING,
    ControlOutput,
    U,
    agent_step,
    control_output,
    fault_wrench,
    gains,
    new_funnel_start,
    new_outputs,
)
from formation_msgs_py.compiled import kernel
from formation_msgs_py.spec import FormationSpec, agent_view
from formation_sim.report import RunRecorder
from formation_sim.simulation import Measurements


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


def note_missing(
    recorder: RunRecorder, t: float, agent_ids: Sequence[str], missing: Mapping[int, Sequence[str]]
) -> None:
    """Agents missing a neighbour's pose ({agent index: neighbour ids}) are ``measurement`` faults.

    Recorded before the step's funnel check (``recorder.add``), so they come first at equal times.
    """
    for i, neighbours in missing.items():
        recorder.fault(t, "measurement", agent_ids[i], ",".join(neighbours))


def note_errors(
    recorder: RunRecorder, t: float, agent_ids: Sequence[str], errors: Sequence[bool], messages: Sequence[str]
) -> None:
    """Every agent at ERROR for its controller (saturated: outside a funnel, or a non-finite wrench)
    is a ``controller`` fault; ``errors`` excludes agents already recorded by :func:`note_missing`."""
    for aid, error, message in zip(agent_ids, errors, messages):
        if error:
            recorder.fault(t, "controller", aid, message)


class AgentTeam:
    """Every agent's controller of ``spec``, in formation-file order."""

    def __init__(self, spec: FormationSpec) -> None:
        self.ids = spec.agent_ids
        views = [agent_view(spec, a) for a in self.ids]
        self.first_end, self.agents, self.ends = gains(views)
        self.end_neighbours = [ie.neighbour for v in views for ie in v.edges]
        self.start = new_funnel_start(len(self.ids))
        n = len(self.end_neighbours)
        self.out, self.edge_out = new_outputs(len(self.ids), n)
        self._p = np.zeros((n, 3))
        self._R = np.tile(np.eye(3), (n, 1, 1))
        self._in_range = np.zeros(n, dtype=np.bool_)
        # load (or compile) the kernels now, on scratch outputs: not at a realtime run's first step
        v = np.zeros((len(self.ids), 6))
        everyone = np.ones(n, dtype=np.bool_)  # every agent steps (a missing pose would skip agent_step)
        scratch = (new_funnel_start(len(self.ids)), *new_outputs(len(self.ids), n))
        team_step(0.0, self._p, self._R, everyone, v, self.first_end, self.agents, self.ends, *scratch)

    def evaluate(
        self, meas: Measurements, recorder: RunRecorder | None
    ) -> tuple[np.ndarray, np.ndarray, list[ControlOutput]]:
        """(u (N,6), margin_v (N,6), outputs) at ``meas.t``; with a recorder, its ``measurement`` faults."""
        missing: dict[int, list[str]] = {}
        first = self.first_end
        for i, aid in enumerate(self.ids):
            poses = meas.relative_poses[aid]
            for k in range(first[i], first[i + 1]):
                pose = poses.get(self.end_neighbours[k])
                self._in_range[k] = pose is not None
                if pose is None:
                    missing.setdefault(i, []).append(self.end_neighbours[k])
                else:
                    self._p[k], self._R[k] = pose
        v = np.asarray(meas.velocities, dtype=np.float64)
        team_step(
            meas.t, self._p, self._R, self._in_range, v,
            first, self.agents, self.ends, self.start, self.out, self.edge_out,
        )  # fmt: skip
        if recorder is not None:
            note_missing(recorder, meas.t, self.ids, missing)
        outputs = []
        for i, aid in enumerate(self.ids):
            msg = None
            if i in missing:
                msg = f"agent {aid}: no relative pose of neighbour(s) {', '.join(missing[i])}"
            outputs.append(control_output(meas.t, i, first[i], first[i + 1], self.out, self.edge_out, msg))
        return self.out[:, U : U + 6].copy(), self.out[:, MARGIN_V : MARGIN_V + 6].copy(), outputs

    def note_errors(self, t: float, outputs: list[ControlOutput], recorder: RunRecorder) -> None:
        """Every agent at ERROR (not for a missing pose: :meth:`evaluate` recorded those) is a ``controller`` fault."""
        errors = [o.level == ERROR and "no relative pose" not in o.message for o in outputs]
        note_errors(recorder, t, self.ids, errors, [o.message for o in outputs])
