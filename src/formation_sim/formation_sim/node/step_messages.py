"""One step's measurement messages as the simulator sends them, and what each agent makes of them (no ROS).

:meth:`StepMessages.encode` writes the CDR bytes of every relative pose (position and the
measurement model's quaternion, :mod:`formation_msgs_py.codec`) and every velocity of a step;
:meth:`StepMessages.decoded` reads them back as the agents do: their decoder
(:func:`formation_msgs_py.codec.relative_pose_from_values`) and their check of values
(:class:`formation_msgs_py.measurement_checks.InputCheck`: a pose an agent refuses, e.g. one beyond its
sensing radius, is answered with the fault wrench, as a pose not received). The simulator node sends
these bytes and its witness computes on what :meth:`~StepMessages.decoded` gives.
"""

from __future__ import annotations

import numpy as np

from formation_core.formation import FormationSpec, simulator_view
from formation_msgs_py import codec
from formation_msgs_py.measurement_checks import InputCheck
from formation_sim.core.measurement import measurement_ends
from formation_sim.core.simulation import Measurements


class StepMessages:
    """The bytes of the current step's measurements: ``poses[k]`` of edge end k (in the measurement
    model's order), ``velocities[i]`` of agent i (formation-file order)."""

    def __init__(self, spec: FormationSpec) -> None:
        ends = measurement_ends(simulator_view(spec))
        self.ids = spec.agent_ids
        self.observer = ends.observer
        self.target = ends.target
        self.pose_codecs = [codec.relative_pose_codec(obs) for obs in ends.observer]
        self.twist_codecs = [codec.twist_codec(a) for a in self.ids]
        # value checks only: stamps are judged against an agent's own time, which genuine steps keep
        self.checks = {
            a.id: InputCheck(a.sensing_radius, round(a.controller.measurement_timeout * codec.NS_PER_S))
            for a in spec.agents
        }
        self.poses: list[bytes] = [b""] * len(ends.observer)
        self.velocities: list[bytes] = [b""] * len(self.ids)

    def encode(self, meas: Measurements) -> None:
        """The bytes of every message of ``meas``, stamped ``meas.ns`` (every end, in range or not)."""
        ns = meas.ns
        p_rel, q_rel, vel = meas.p_rel.tolist(), meas.q_rel.tolist(), meas.velocities.tolist()
        for k, item_codec in enumerate(self.pose_codecs):
            self.poses[k] = item_codec.encode(ns, (*p_rel[k], *q_rel[k]))
        for i, item_codec in enumerate(self.twist_codecs):
            self.velocities[i] = item_codec.encode(ns, vel[i])

    def decoded(self, meas: Measurements) -> Measurements:
        """``meas`` as the agents receive it: stamp, relative poses and twists decoded from the bytes by
        the agents' own decoder; an end out of range, or whose value its observer refuses, is not received."""
        p_rows, R_rows, in_range = meas.p_rel.tolist(), meas.R_rel.tolist(), meas.in_range.tolist()
        from_values = codec.relative_pose_from_values
        refused = False
        for k, received in enumerate(in_range):
            if not received:
                continue
            _, values = self.pose_codecs[k].decode(self.poses[k])
            if self.checks[self.observer[k]].pose(self.target[k], meas.ns, values) is not None:
                in_range[k], refused = False, True
                continue
            p_rows[k], R_rows[k] = from_values(values)
        twists = [twist.decode(data) for twist, data in zip(self.twist_codecs, self.velocities)]
        return meas.received(
            twists[0][0],
            np.array(p_rows),
            np.array(R_rows),
            np.array([v for _, v in twists]),
            np.array(in_range) if refused else None,
        )
