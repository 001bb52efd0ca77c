"""The simulated world stepped at the control rate: shared by the headless runner and the
simulator node, so both produce the same trajectory from the same file and seed.

One control period: :meth:`Simulation.sense` gives every agent's measurements at t_k, the
agents answer with wrenches, :meth:`Simulation.advance` integrates ``substeps`` physics steps
with the wrenches held (zero-order hold) and moves to t_{k+1}. The run core
(:mod:`formation_sim.core.loop`) steps the same plant and measurement kernels many steps at a time.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from formation_msgs_py.spec import SimulatorView
from formation_sim.core.measurement import Ends, MeasurementModel, RelativePoses, relative_poses
from formation_sim.core.plant import Plant, PlantState


@dataclass(frozen=True)
class Measurements:
    """Everything the agents receive at one step, by edge end (:class:`Ends`, the controllers'
    order): relative poses p_rel (n_ends,3) [m, observer's frame] and R_rel (n_ends,3,3), which
    ends are in range (only those are received), and the noisy body twists (N,6)."""

    t: float
    step: int
    p_rel: np.ndarray
    R_rel: np.ndarray
    in_range: np.ndarray
    velocities: np.ndarray
    ends: Ends

    @property
    def relative_poses(self) -> RelativePoses:
        """{agent_id: {neighbour_id: (p_i_j_in_i, R_i_j)}} of the ends in range (views of the arrays)."""
        out: RelativePoses = {a: {} for a in self.ends.agent_ids}
        for k, (i, j) in enumerate(zip(self.ends.observer, self.ends.target)):
            if self.in_range[k]:
                out[i][j] = (self.p_rel[k], self.R_rel[k])
        return out

    @classmethod
    def from_poses(
        cls, t: float, step: int, poses: Mapping[str, Mapping[str, Any]], velocities: Any, ends: Ends
    ) -> Measurements:
        """The measurements of ``poses`` ({agent_id: {neighbour_id: (p, R)}}, the ends received)."""
        n = len(ends.observer)
        p_rel, R_rel, in_range = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros(n, dtype=np.bool_)
        for k, (i, j) in enumerate(zip(ends.observer, ends.target)):
            pose = poses.get(i, {}).get(j)
            if pose is not None:
                p_rel[k], R_rel[k] = pose
                in_range[k] = True
        return cls(t, step, p_rel, R_rel, in_range, np.asarray(velocities, dtype=np.float64), ends)


class Simulation:
    """Plant + measurement model + clock, advanced one control period at a time."""

    def __init__(
        self,
        view: SimulatorView,
        *,
        physics_rate: float | None = None,
        control_rate: float | None = None,
        warm_up: bool = True,
    ) -> None:
        """``warm_up``: load (or compile) the kernels of :meth:`sense` and :meth:`advance` now (the
        run core, which calls neither, says False)."""
        sim = view.simulation
        self.view = view
        self.control_rate = float(control_rate or sim.control_rate)
        self.physics_rate = float(physics_rate or sim.physics_rate)
        ratio = self.physics_rate / self.control_rate
        if ratio < 1 - 1e-9 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"physics_rate {self.physics_rate:g} Hz is not an integer multiple "
                f"of control_rate {self.control_rate:g} Hz"
            )
        self.substeps = round(ratio)
        self.h = 1.0 / self.physics_rate
        rng = np.random.default_rng(sim.seed)
        # Separate streams: adding measurement noise must not change the plant's draws.
        seed_seq = rng.bit_generator.seed_seq
        assert isinstance(seed_seq, np.random.SeedSequence)  # default_rng(int) makes one
        plant_rng, meas_rng = (np.random.default_rng(s) for s in seed_seq.spawn(2))
        self.plant = Plant(view, plant_rng)
        self.sensors = MeasurementModel(view, meas_rng)
        self.state: PlantState = self.plant.initial_state(view)
        self.step_index = 0
        self.agent_ids = tuple(a.id for a in view.agents)
        if warm_up:
            self._warm_up()

    def _warm_up(self) -> None:
        """Load (or compile) the kernels now, not at the first step a realtime clock is running for.

        Every call works on copies: the state and the noise stream are untouched.
        """
        s = self.state.copy()
        self.plant.step(0.0, s, np.zeros((len(self.agent_ids), 6)), self.h)
        self.plant.measured_velocity(0.0, s)
        m = self.sensors
        relative_poses(s.p, s.R, m.sensing, np.zeros((0, 0, 3)) if not m.noisy else np.zeros((2, m.n_links, 3)),
                       m.p_rel.copy(), m.R_rel.copy(), m.in_range.copy())  # fmt: skip

    @property
    def t(self) -> float:
        """Simulation time of the current step (s); exact multiple of the control period."""
        return self.step_index / self.control_rate

    def sense(self) -> Measurements:
        s = self.state
        p_rel, R_rel, in_range = self.sensors.measure(s.p, s.R)
        v = self.plant.measured_velocity(self.t, s)
        return Measurements(self.t, self.step_index, p_rel, R_rel, in_range, v, self.sensors.ends)

    def advance(self, wrench: np.ndarray) -> None:
        """Integrate one control period with ``wrench`` (N,6) held (zero-order hold)."""
        t0 = self.t
        for i in range(self.substeps):
            self.state = self.plant.step(t0 + i * self.h, self.state, wrench, self.h)
        self.step_index += 1
