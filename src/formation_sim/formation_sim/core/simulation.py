"""The simulated world stepped at the control rate: shared by the headless runner and the
simulator node, so both produce the same trajectory from the same file and seed.

One control period: :meth:`Simulation.sense` gives every agent's measurements at t_k, the
agents answer with wrenches, :meth:`Simulation.advance` integrates ``substeps`` physics steps
with the wrenches held (zero-order hold) and moves to t_{k+1}. The run core
(:mod:`formation_sim.core.loop`) steps the same plant and measurement kernels many steps at a time.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from formation_msgs_py.spec import SimulatorView
from formation_msgs_py.wire import control_time, step_stamp_ns
from formation_sim.core.measurement import Ends, MeasurementModel, RelativePoses, relative_poses
from formation_sim.core.plant import Plant, PlantState


@dataclass(frozen=True)
class Measurements:
    """Everything the agents receive at one step, by edge end (:class:`Ends`, the controllers'
    order): relative poses p_rel (n_ends,3) [m, observer's frame], the messages' quaternions q_rel
    (n_ends,4) (x, y, z, w) and the matrices R_rel (n_ends,3,3) an agent decodes from them, which
    ends are in range (only those are received), and the noisy body twists (N,6).

    ``ns`` is the step's stamp (:func:`formation_msgs_py.wire.step_stamp_ns`) and ``t`` its time
    [s] (:func:`formation_msgs_py.wire.control_time`): the time every agent, record and analysis gives
    the step (the plant integrates from k / control_rate, within half a nanosecond of it).
    """

    t: float
    step: int
    ns: int
    p_rel: np.ndarray
    q_rel: np.ndarray
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

    def received(
        self, ns: int, p_rel: np.ndarray, R_rel: np.ndarray, velocities: np.ndarray, in_range: np.ndarray | None = None
    ) -> Measurements:
        """These measurements as received: stamped ``ns``, with the relative poses and twists decoded
        from the messages (the quaternions stay the ones sent) and, if given, the ends received."""
        in_range = self.in_range if in_range is None else in_range
        return replace(
            self, ns=ns, t=control_time(ns), p_rel=p_rel, R_rel=R_rel, velocities=velocities, in_range=in_range
        )


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
                       m.p_rel.copy(), m.q_rel.copy(), m.R_rel.copy(), m.in_range.copy())  # fmt: skip

    @property
    def t(self) -> float:
        """The current step's time [s]: its stamp's (:func:`formation_msgs_py.wire.control_time`)."""
        return control_time(step_stamp_ns(self.step_index, self.control_rate))

    @property
    def plant_time(self) -> float:
        """The plant's time of the current step [s]: k / control_rate (disturbances, noise, integration)."""
        return self.step_index / self.control_rate

    def sense(self) -> Measurements:
        s = self.state
        p_rel, q_rel, R_rel, in_range = self.sensors.measure(s.p, s.R)
        v = self.plant.measured_velocity(self.plant_time, s)
        ns = step_stamp_ns(self.step_index, self.control_rate)
        ends = self.sensors.ends
        return Measurements(control_time(ns), self.step_index, ns, p_rel, q_rel, R_rel, in_range, v, ends)

    def advance(self, wrench: np.ndarray) -> None:
        """Integrate one control period with ``wrench`` (N,6) held (zero-order hold)."""
        t0 = self.plant_time
        for i in range(self.substeps):
            self.state = self.plant.step(t0 + i * self.h, self.state, wrench, self.h)
        self.step_index += 1
