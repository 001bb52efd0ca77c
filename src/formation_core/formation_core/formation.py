"""What a formation is, once its file is read: the typed formation and the views of it.

:class:`FormationSpec` (agents, edges, simulation: immutable, every value checked by
:mod:`formation_core.spec`, which builds it from a file). An agent process uses :func:`agent_view`
only: its own gains and velocity funnel and the specification of its incident edges (what the paper
lets an agent know). The simulator uses :func:`simulator_view`: the true plant, disturbances and noise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from formation_core.errors import FormationSpecError
from formation_core.schema import (
    AGENT_FIELDS,
    EDGE_FIELDS,
    MEASUREMENT_LINK_FIELDS,
    SIMULATION_FIELDS,
    WRENCH_LINK_FIELDS,
    block,
    documented,
)

# Every object a block of the file builds is a frozen dataclass whose attributes are the block's fields
# in the schema (schema.py, the one declaration): same names, order and types (a test checks it), no
# defaults (the loader fills every attribute; the schema holds the defaults). ``documented`` appends
# the schema's description of each attribute to the docstring.


@documented(block(AGENT_FIELDS, "controller", "velocity_funnel"))
@dataclass(frozen=True)
class VelocityFunnel:
    """ρ_v per channel [vx, vy, vz, wx, wy, wz]; ``rho_0 is None`` means auto."""

    rho_0: tuple[float, ...] | None
    auto_scale: float
    auto_offset: float
    rho_inf: tuple[float, ...]
    decay: tuple[float, ...]


@documented(block(AGENT_FIELDS, "controller"))
@dataclass(frozen=True)
class ControllerGains:
    """What agent i knows of itself (paper: δ_i, γ_i, ρ_v,i); max_force / max_torque resolved (N, N·m;
    never above the actuators')."""

    delta: float
    gamma: float
    velocity_funnel: VelocityFunnel
    saturation_margin: float
    max_force: float
    max_torque: float
    measurement_timeout: float


@dataclass(frozen=True)
class SignalModel:
    """A model chosen by name and its parameters: a disturbance or noise model, a link's jitter
    distribution or loss model."""

    model: str
    params: Mapping[str, Any]


@documented(MEASUREMENT_LINK_FIELDS)
@dataclass(frozen=True)
class MeasurementLink:
    """One measurement stream to an agent (docs/links.md); rate None: every control step."""

    rate: float | None
    delay: float
    jitter: SignalModel
    loss: SignalModel

    @property
    def ideal(self) -> bool:
        """Every sample at every step, at once, none lost: the link of a file that gives none."""
        return self.rate is None and self.delay == 0.0 and self.jitter.model == "none" and self.loss.model == "none"


@documented(WRENCH_LINK_FIELDS)
@dataclass(frozen=True)
class WrenchLink:
    """An agent's wrench on its way to the plant (docs/links.md)."""

    delay: float
    loss: SignalModel

    @property
    def ideal(self) -> bool:
        return self.delay == 0.0 and self.loss.model == "none"


@documented(block(AGENT_FIELDS, "links"))
@dataclass(frozen=True)
class AgentLinks:
    """How measurements reach one agent and its wrench the plant."""

    poses: MeasurementLink
    velocity: MeasurementLink
    wrench: WrenchLink


@documented(block(EDGE_FIELDS, "links"))
@dataclass(frozen=True)
class EdgeLinks:
    """An edge's own links of its ends' measurements (None: the observer's ``links.poses``)."""

    tail: MeasurementLink | None
    head: MeasurementLink | None


@documented(block(AGENT_FIELDS, "dynamics"))
@dataclass(frozen=True)
class Dynamics:
    """True plant of one agent (simulator only): inertia a 3×3 array (body frame, kg·m²), disturbance
    and velocity_noise SignalModels."""

    mass: float
    inertia: np.ndarray
    max_force: float
    max_torque: float
    disturbance: SignalModel
    velocity_noise: SignalModel


@documented(AGENT_FIELDS, derived=(("index", "position in the file's list of agents"),))
@dataclass(frozen=True)
class AgentSpec:
    """One agent: geometry, initial state (world position and R_world_body as numpy arrays, body twist),
    controller (ControllerGains), plant (Dynamics)."""

    index: int
    id: str
    radius: float
    sensing_radius: float
    position: np.ndarray
    R_world_body: np.ndarray
    linear_velocity: tuple[float, ...]
    angular_velocity: tuple[float, ...]
    controller: ControllerGains
    dynamics: Dynamics
    position_noise_std: float
    rotation_noise_std: float
    links: AgentLinks

    @property
    def twist(self) -> np.ndarray:
        """Initial body-frame twist [v_x, v_y, v_z, ω_x, ω_y, ω_z] (m/s, rad/s)."""
        return np.array(self.linear_velocity + self.angular_velocity)


@documented(EDGE_FIELDS, derived=(("index", "position among the kept edges"),))
@dataclass(frozen=True)
class EdgeSpec:
    """Edge k = (tail k1, head k2) with its desired offsets (R_des a numpy array), bounds (d_col, d_con
    resolved) and funnels."""

    index: int
    tail: str
    head: str
    d_des: float
    R_des: np.ndarray
    d_col: float
    d_con: float
    rho_e_inf: float
    decay_e: float
    rho_psi_0: float
    rho_psi_inf: float
    decay_psi: float
    links: EdgeLinks

    @property
    def c_col(self) -> float:
        """C_col = d_des² − d_col² (m²)."""
        return self.d_des**2 - self.d_col**2

    @property
    def c_con(self) -> float:
        """C_con = d_con² − d_des² (m²)."""
        return self.d_con**2 - self.d_des**2

    @property
    def name(self) -> str:
        return f"{self.tail}-{self.head}"

    def rho_e(self, t: float) -> float:
        """Normalised distance performance function ρ_e(t)."""
        from formation_core import funnels  # compiled kernels: not on the path of loading a file

        return funnels.rho(t, 1.0, funnels.rho_e_floor(self.c_col, self.c_con, self.rho_e_inf), self.decay_e)

    def rho_psi(self, t: float) -> float:
        """Orientation performance function ρ_ψ(t)."""
        from formation_core import funnels

        return funnels.rho(t, self.rho_psi_0, self.rho_psi_inf, self.decay_psi)


@documented(SIMULATION_FIELDS)
@dataclass(frozen=True)
class SimulationSpec:
    """Run settings (gravity a numpy 3-vector)."""

    mode: str
    duration: float
    physics_rate: float
    control_rate: float
    controller: str
    record_rate: float
    seed: int
    gravity: np.ndarray
    spanning_tree: bool
    rate_check: str
    contact: str
    step_timeout: float
    command_timeout: float

    @property
    def substeps(self) -> int:
        """Integrator steps per control period."""
        return round(self.physics_rate / self.control_rate)


@dataclass(frozen=True)
class FormationSpec:
    """A validated formation file."""

    name: str
    description: str
    source: str
    simulation: SimulationSpec
    agents: tuple[AgentSpec, ...]
    edges: tuple[EdgeSpec, ...]
    dropped_edges: tuple[tuple[str, str], ...]

    def agent(self, agent_id: str | int) -> AgentSpec:
        key = str(agent_id)
        for a in self.agents:
            if a.id == key:
                return a
        raise FormationSpecError("agents", f"no agent with id {key!r} (have {', '.join(self.agent_ids)})", key)

    @property
    def agent_ids(self) -> tuple[str, ...]:
        return tuple(a.id for a in self.agents)

    def pose_link(self, observer: str, target: str) -> MeasurementLink:
        """The link of ``observer``'s measurement of its neighbour ``target``: the edge's, else the observer's."""
        for e in self.edges:
            if (e.tail, e.head) == (observer, target) and e.links.tail is not None:
                return e.links.tail
            if (e.head, e.tail) == (observer, target) and e.links.head is not None:
                return e.links.head
        return self.agent(observer).links.poses

    @property
    def has_links(self) -> bool:
        """Whether any link is not ideal (no link model: every run as without one, bit for bit)."""
        return links_modelled(self.agents, self.edges)

    def with_agent_gains(self, gains: Mapping[str, Mapping[str, float]]) -> FormationSpec:
        """A copy whose agents use other live gains: ``{agent id: {"delta"|"gamma": value}}`` (values
        checked by the caller, as an agent checks its parameters)."""
        agents = []
        for a in self.agents:
            g, c = gains.get(a.id, {}), a.controller
            controller = replace(c, delta=g.get("delta", c.delta), gamma=g.get("gamma", c.gamma))
            agents.append(replace(a, controller=controller))
        return replace(self, agents=tuple(agents))

    def with_simulation(self, **changes: Any) -> FormationSpec:
        """A copy with simulation settings replaced (re-checked: rates stay multiples)."""
        sim = {**self.simulation.__dict__, **changes}
        check_rates(sim["physics_rate"], sim["control_rate"])
        return FormationSpec(
            self.name, self.description, self.source, SimulationSpec(**sim), self.agents, self.edges, self.dropped_edges
        )


@dataclass(frozen=True)
class IncidentEdge:
    """An edge as seen by one of its agents: role ``tail`` or ``head`` and the neighbour."""

    edge: EdgeSpec
    role: str
    neighbour: str


@dataclass(frozen=True)
class AgentView:
    """All an agent process may know: its gains and funnel, its sensing radius (m), its incident edges."""

    agent_id: str
    controller: ControllerGains
    edges: tuple[IncidentEdge, ...]
    sensing_radius: float

    @property
    def neighbours(self) -> tuple[str, ...]:
        return tuple(e.neighbour for e in self.edges)


@dataclass(frozen=True)
class SimulatorView:
    """What the simulator knows: the whole true plant and the sensing geometry."""

    name: str
    simulation: SimulationSpec
    agents: tuple[AgentSpec, ...]
    edges: tuple[EdgeSpec, ...]

    @property
    def has_links(self) -> bool:
        """Whether any link is not ideal (:attr:`FormationSpec.has_links`)."""
        return links_modelled(self.agents, self.edges)


def links_modelled(agents: Sequence[AgentSpec], edges: Sequence[EdgeSpec]) -> bool:
    """Whether any of these agents' or edges' links is not ideal."""
    own = (link for a in agents for link in (a.links.poses, a.links.velocity, a.links.wrench))
    ends = (link for e in edges for link in (e.links.tail, e.links.head) if link is not None)
    return not all(link.ideal for link in (*own, *ends))


def agent_view(spec: FormationSpec, agent_id: str | int) -> AgentView:
    """The agent's view of a formation: nothing of the plant or of other agents' gains."""
    me = spec.agent(agent_id)
    incident = []
    for e in spec.edges:
        if e.tail == me.id:
            incident.append(IncidentEdge(e, "tail", e.head))
        elif e.head == me.id:
            incident.append(IncidentEdge(e, "head", e.tail))
    return AgentView(me.id, me.controller, tuple(incident), me.sensing_radius)


def simulator_view(spec: FormationSpec) -> SimulatorView:
    return SimulatorView(spec.name, spec.simulation, spec.agents, spec.edges)


def check_rates(physics_rate: float, control_rate: float) -> None:
    """Refuse a physics rate [Hz] that is not an integer multiple of the control rate [Hz] (FormationSpecError)."""
    ratio = physics_rate / control_rate
    if ratio < 1 - 1e-9 or abs(ratio - round(ratio)) > 1e-9:
        raise FormationSpecError(
            "simulation.physics_rate",
            f"{physics_rate:g} Hz is not an integer multiple of control_rate {control_rate:g} Hz",
            physics_rate,
        )
