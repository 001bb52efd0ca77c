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

from formation_core.formation import SimulatorView
from formation_msgs_py.codec import control_time, step_stamp_ns
from formation_sim.core.links import (
    LinkSet,
    deliver_step,
    draw_rows,
    first_ends,
    link_ages,
    link_stream,
    n_links,
    new_link_set,
    receive_step,
)
from formation_sim.core.measurement import Ends, MeasurementModel, RelativePoses, relative_poses
from formation_sim.core.plant import Plant, PlantState


@dataclass(frozen=True)
class Measurements:
    """Everything the agents receive at one step, by edge end (:class:`Ends`, the controllers'
    order): relative poses p_rel (n_ends,3) [m, observer's frame], the messages' quaternions q_rel
    (n_ends,4) (x, y, z, w) and the matrices R_rel (n_ends,3,3) an agent decodes from them, which
    ends are in range (only those are received), and the noisy body twists (N,6).

    ``ns`` is the step's stamp (:func:`formation_msgs_py.codec.step_stamp_ns`) and ``t`` its time
    [s] (:func:`formation_msgs_py.codec.control_time`): the time every agent, record and analysis gives
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
        #: the link model (formation_sim.core.links), None without one: every sample at once
        self.links: LinkSet | None = None
        #: the ages of :meth:`link_ages` at the step :meth:`advance` integrated last
        self.closed_step_link_ages = np.zeros(0)
        if view.has_links:
            self.links = new_link_set(view)
            self._link_rng = link_stream(seed_seq)
            self._first_end = first_ends(view)
            self._link_uniforms = np.zeros((0, n_links(self.links), 3))
            self._applied = np.zeros((len(view.agents), 6))
            self._ages = np.zeros(n_links(self.links))
        if warm_up:
            self._warm_up(view)

    def draw_link_uniforms(self, steps: int) -> np.ndarray:
        """The links' uniforms of the next ``steps`` control steps (the run core draws a chunk at a time;
        :meth:`sense` one step at a time, from the same stream)."""
        assert self.links is not None
        return draw_rows(self._link_rng, steps, self.links)

    def _warm_up(self, view: SimulatorView) -> None:
        """Load (or compile) the kernels now, not at the first step a realtime clock is running for (on a
        cold cache the link kernels took 1.9 s inside the first tick of a realtime run).

        Every call works on copies: the state, the links' held samples and the noise streams are untouched.
        """
        s = self.state.copy()
        n = len(self.agent_ids)
        self.plant.step(0.0, s, np.zeros((n, 6)), self.h)
        v = self.plant.measured_velocity(0.0, s)
        m = self.sensors
        p_rel, q_rel, R_rel, in_range = m.p_rel.copy(), m.q_rel.copy(), m.R_rel.copy(), m.in_range.copy()
        relative_poses(s.p, s.R, m.sensing, np.zeros((0, 0, 3)) if not m.noisy else np.zeros((2, m.n_links, 3)),
                       p_rel, q_rel, R_rel, in_range)  # fmt: skip
        if self.links is not None:  # a link set of its own, with the run's types: sense, deliver, link_ages
            links = new_link_set(view)
            uniforms = np.zeros((n_links(links), 3))  # draw_rows(..., 1)[0]: float64, C order
            receive_step(links, 0, uniforms, p_rel, q_rel, R_rel, in_range, v, self._first_end)
            deliver_step(links, 0, uniforms, np.zeros((n, 6)), np.zeros_like(self._applied), np.zeros_like(self._ages))
            link_ages(links, 0)

    @property
    def t(self) -> float:
        """The current step's time [s]: its stamp's (:func:`formation_msgs_py.codec.control_time`)."""
        return control_time(step_stamp_ns(self.step_index, self.control_rate))

    @property
    def plant_time(self) -> float:
        """The plant's time of the current step [s]: k / control_rate (disturbances, noise, integration)."""
        return self.step_index / self.control_rate

    def sense(self) -> Measurements:
        """The current step's measurements as the agents receive them: through the links, if any (the
        newest sample each agent holds; a pose or velocity too old or never received is missing)."""
        s = self.state
        p_rel, q_rel, R_rel, in_range = self.sensors.measure(s.p, s.R)
        v = self.plant.measured_velocity(self.plant_time, s)
        if self.links is not None:
            self._link_uniforms = self.draw_link_uniforms(1)[0]
            receive_step(self.links, self.step_index, self._link_uniforms, p_rel, q_rel, R_rel, in_range, v,
                         self._first_end)  # fmt: skip
        ns = step_stamp_ns(self.step_index, self.control_rate)
        ends = self.sensors.ends
        return Measurements(control_time(ns), self.step_index, ns, p_rel, q_rel, R_rel, in_range, v, ends)

    def deliver(self, wrench: np.ndarray) -> np.ndarray:
        """The wrenches (N,6) the plant applies at the current step, given the agents' answers ``wrench``:
        the answers themselves, or what the wrench links deliver (after :meth:`sense` of the same step;
        once per step: :meth:`advance` calls it, the last step of a run calls it alone)."""
        if self.links is None:
            return wrench
        commanded = np.ascontiguousarray(wrench, dtype=np.float64)
        deliver_step(self.links, self.step_index, self._link_uniforms, commanded, self._applied, self._ages)
        return self._applied

    def link_ages(self) -> np.ndarray:
        """(n_links,) every link's held sample's age [s] at the current step (NaN: none yet), after its
        deliveries (:meth:`sense`, :meth:`deliver`); empty without a link model."""
        return np.zeros(0) if self.links is None else link_ages(self.links, self.step_index)

    def advance(self, wrench: np.ndarray) -> None:
        """Integrate one control period with the agents' answers ``wrench`` (N,6) held (zero-order hold),
        through the wrench links if any (:meth:`deliver`)."""
        wrench = self.deliver(wrench)
        if self.links is not None:
            self.closed_step_link_ages = self._ages.copy()
        t0 = self.plant_time
        for i in range(self.substeps):
            self.state = self.plant.step(t0 + i * self.h, self.state, wrench, self.h)
        self.step_index += 1
