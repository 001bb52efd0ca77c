"""Every agent's controller core stepped together on one step's measurements (no ROS).

The headless runner uses it as the agents; the simulator node uses it as a *shadow* of the
agents (the same cores on exactly the measurements it published: in lockstep these are what
the agents answer, so the velocity-funnel margins and faults it records are the agents' own).
Both record faults the same way, so their summaries agree.
"""

from __future__ import annotations

import numpy as np

from formation_agent.controller import ERROR, AgentController, ControlOutput, MissingMeasurementError
from formation_msgs_py.spec import FormationSpec, agent_view
from formation_sim.report import RunRecorder
from formation_sim.simulation import Measurements


class AgentTeam:
    """One :class:`AgentController` per agent of ``spec``, in formation-file order."""

    def __init__(self, spec: FormationSpec) -> None:
        self.ids = spec.agent_ids
        self.controllers = [AgentController(agent_view(spec, a)) for a in self.ids]

    def evaluate(
        self, meas: Measurements, recorder: RunRecorder | None
    ) -> tuple[np.ndarray, np.ndarray, list[ControlOutput]]:
        """(u (N,6), margin_v (N,6), outputs) at ``meas.t``.

        A missing neighbour gives that agent a zero wrench (level ERROR) and, with a recorder, a
        ``measurement`` fault naming the agent and the neighbours.
        """
        outputs = []
        for i, ctrl in enumerate(self.controllers):
            try:
                out = ctrl.compute(meas.t, meas.relative_poses[ctrl.agent_id], meas.velocities[i])
            except MissingMeasurementError as exc:
                out = ctrl.fault_output(meas.t, str(exc))
                if recorder is not None:
                    recorder.fault(meas.t, "measurement", ctrl.agent_id, ",".join(exc.neighbours))
            outputs.append(out)
        u = np.array([o.wrench for o in outputs])
        return u, np.array([o.margin_v for o in outputs]), outputs

    def note_errors(self, t: float, outputs: list[ControlOutput], recorder: RunRecorder) -> None:
        """Every agent at ERROR (saturated: outside a funnel on its measurements) counts a
        ``controller`` fault; the funnels on ground truth decide the verdict."""
        for aid, o in zip(self.ids, outputs):
            if o.level == ERROR:
                recorder.fault(t, "controller", aid, o.message)
