"""Formation files: load, validate, and split into the agent's and the simulator's views.

``load_formation(path)`` returns an immutable :class:`FormationSpec` or raises
:class:`FormationSpecError` naming the field, e.g.
``edges[2].distance: 4.5 is not inside (d_col=2.0, d_con=4.0)``.

An agent process uses :func:`agent_view` only: its own gains and velocity funnel and the
specification of its incident edges (what the paper lets an agent know). The simulator uses
:func:`simulator_view`: the true plant, disturbances and noise.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formation_msgs_py.errors import CollectedFormationSpecError, FormationSpecError
from formation_msgs_py.loader import locate, read_document, split_path
from formation_msgs_py.rotations import (
    is_rotation,
    matrix_from_axis_angle,
    matrix_from_quaternion,
    matrix_from_rpy,
    project_to_so3,
)
from formation_msgs_py.schema import (
    AGENT_FIELDS,
    EDGE_FIELDS,
    SIMULATION_FIELDS,
    TOP_FIELDS,
    block,
    check_partial,
    documented,
    parse_mapping,
    record_values,
    short,
    unknown_key,
)

#: ``project: true`` accepts a matrix with ‖RᵀR − I‖_F up to this and det > 0: the paper's printed
#: R_2(0) is 0.37 off (docs/controller.md, "Errors in the paper"); a reflection (det −1) or a zero
#: matrix has no nearest rotation worth taking.
PROJECT_TOLERANCE = 0.5
_SIGNALS = ("disturbance", "velocity_noise")

# --- result objects ---------------------------------------------------------------------------


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
    """A disturbance or noise model: ``model`` and its parameters."""

    model: str
    params: Mapping[str, Any]


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
        from formation_msgs_py import funnels  # compiled kernels: not on the path of loading a file

        return funnels.rho(t, 1.0, funnels.rho_e_floor(self.c_col, self.c_con, self.rho_e_inf), self.decay_e)

    def rho_psi(self, t: float) -> float:
        """Orientation performance function ρ_ψ(t)."""
        from formation_msgs_py import funnels

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

    def with_simulation(self, **changes: Any) -> FormationSpec:
        """A copy with simulation settings replaced (re-checked: rates stay multiples)."""
        sim = {**self.simulation.__dict__, **changes}
        _check_rates(sim["physics_rate"], sim["control_rate"])
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


# --- loading ----------------------------------------------------------------------------------


def load_formation(path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> FormationSpec:
    """Read, validate and return a formation file; ``overrides`` replace ``simulation`` keys.

    Raises FormationSpecError (CollectedFormationSpecError for several) with FILE:LINE:COL on each.
    """
    path = Path(path)
    document = read_document(path)
    data = document.data
    if overrides and isinstance(data, dict):
        data = copy.deepcopy(data)
        data.setdefault("simulation", {})
        if isinstance(data["simulation"], dict):
            data["simulation"].update(overrides)
    try:
        return formation_from_dict(data, source=str(path), default_name=path.stem)
    except FormationSpecError as exc:
        raise locate(exc, document) from None


def _deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in top.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) and "model" not in v:
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def _rotation_from(parsed: Mapping[str, Any], path: str) -> np.ndarray:
    if "matrix" in parsed:
        R = np.array(parsed["matrix"], dtype=np.float64)
        if not is_rotation(R):
            err = float(np.linalg.norm(R.T @ R - np.eye(3)))
            det = float(np.linalg.det(R))
            close = err <= PROJECT_TOLERANCE and det > 0
            if parsed["project"] and close:
                return project_to_so3(R)
            if parsed["project"]:
                why = f"det = {det:.4f} <= 0" if det <= 0 else f"‖RᵀR − I‖_F = {err:.3g} > {PROJECT_TOLERANCE:g}"
                raise FormationSpecError(
                    f"{path}.matrix",
                    f"is too far from a rotation to project ({why}): give a rotation",
                    parsed["matrix"],
                )
            hint = "; add 'project: true' to use its nearest rotation" if close else ""
            raise FormationSpecError(
                f"{path}.matrix",
                f"is not a rotation (‖RᵀR − I‖_F = {err:.3g}, det = {det:.4f}){hint}",
                parsed["matrix"],
            )
        # Rotations given to 1e-6 are snapped so that the plant starts exactly in SO(3).
        return project_to_so3(R)
    if "quaternion" in parsed:
        return np.array(matrix_from_quaternion(*parsed["quaternion"]))
    if "rpy" in parsed:
        return matrix_from_rpy(parsed["rpy"])
    axis, angle = parsed["axis_angle"]
    return matrix_from_axis_angle(axis, angle)


def _check_rates(physics_rate: float, control_rate: float) -> None:
    ratio = physics_rate / control_rate
    if ratio < 1 - 1e-9 or abs(ratio - round(ratio)) > 1e-9:
        raise FormationSpecError(
            "simulation.physics_rate",
            f"{physics_rate:g} Hz is not an integer multiple of control_rate {control_rate:g} Hz",
            physics_rate,
        )


def formation_from_dict(document: Any, *, source: str = "<dict>", default_name: str = "formation") -> FormationSpec:
    """Validate a parsed YAML document (see :func:`load_formation`).

    Every error is collected (CollectedFormationSpecError when there are several); the semantic checks
    of an agent or edge run only once its fields are valid, the tree checks once every edge is.
    """
    if not isinstance(document, Mapping):
        raise FormationSpecError("", f"a formation file is a mapping at the top level, got {type(document).__name__}")
    errors = _Collector()
    top = _parse_top(document, errors)
    defaults = _parse_defaults(document, errors)
    raw_agents, raw_edges = _item_lists(document, errors)
    agents, ids = _parse_agents(raw_agents, defaults["agent"], errors)
    agents_ok = not errors.items
    edges_parsed = _parse_edges(raw_edges, defaults["edge"], ids if agents_ok else None, errors)
    errors.raise_if_any()
    assert top is not None  # parsed: no error was found
    sim = top["simulation"]

    kept, dropped = _tree(list(ids), [(e["tail"], e["head"]) for _, e, _ in edges_parsed], sim["spanning_tree"])
    edges = _make_edges([item for item in edges_parsed if item[0] in kept], raw_edges, agents, errors)
    errors.raise_if_any()

    simulation = SimulationSpec(**{**sim, "gravity": np.array(sim["gravity"])})
    return FormationSpec(
        name=top["name"] or default_name,
        description=top["description"],
        source=source,
        simulation=simulation,
        agents=tuple(agents),
        edges=tuple(edges),
        dropped_edges=tuple((edges_parsed[k][1]["tail"], edges_parsed[k][1]["head"]) for k in dropped),
    )


#: (index in the file, parsed fields, field path) of an edge whose own checks passed
_ParsedEdge = tuple[int, dict[str, Any], str]


def _parse_top(document: Mapping[Any, Any], errors: _Collector) -> dict[str, Any] | None:
    """The unknown top-level keys, then name, description and simulation (rates checked); None if invalid."""
    known = [f.name for f in TOP_FIELDS]
    for key in document:
        if key not in known:
            errors.add(unknown_key(str(key), key, known))
    plain = ("name", "description", "simulation")
    top_plain = {k: v for k, v in document.items() if k in plain}
    top_fields = tuple(f for f in TOP_FIELDS if f.name in plain)
    top: dict[str, Any] | None = errors.run(lambda: parse_mapping(top_plain, top_fields, ""))
    if top is not None:
        sim = top["simulation"]
        errors.run(lambda: _check_rates(sim["physics_rate"], sim["control_rate"]))
    return top


def _parse_defaults(document: Mapping[Any, Any], errors: _Collector) -> dict[str, Mapping[str, Any]]:
    """The ``defaults`` block: its ``agent`` and ``edge`` mappings (empty where absent or invalid)."""
    defaults = document.get("defaults") or {}
    if not isinstance(defaults, Mapping):
        errors.add(
            FormationSpecError("defaults", f"expected a mapping with keys agent and edge, got {short(defaults)}")
        )
        defaults = {}
    for key in defaults:
        if key not in ("agent", "edge"):
            errors.add(unknown_key(f"defaults.{key}", key, ("agent", "edge")))
    blocks: dict[str, Mapping[str, Any]] = {}
    for key, fields in (("agent", AGENT_FIELDS), ("edge", EDGE_FIELDS)):
        block = defaults.get(key) or {}
        if not isinstance(block, Mapping):
            errors.add(FormationSpecError(f"defaults.{key}", f"expected a mapping, got {short(block)}", block))
            block = {}
        errors.extend(check_partial(block, fields, f"defaults.{key}"))
        blocks[key] = block
    return blocks


def _item_lists(document: Mapping[Any, Any], errors: _Collector) -> tuple[list[Any], list[Any]]:
    """The raw ``agents`` (at least 2) and ``edges`` (at least 1) lists; empty where invalid."""
    raw_agents = document.get("agents")
    if not isinstance(raw_agents, list) or len(raw_agents) < 2:
        errors.add(FormationSpecError("agents", f"expected a list of at least 2 agents, got {short(raw_agents)}"))
        raw_agents = []
    raw_edges = document.get("edges")
    if not isinstance(raw_edges, list) or not raw_edges:
        errors.add(FormationSpecError("edges", f"expected a non-empty list of edges, got {short(raw_edges)}"))
        raw_edges = []
    return raw_agents, raw_edges


def _parse_agents(
    raw_agents: list[Any], defaults: Mapping[str, Any], errors: _Collector
) -> tuple[list[AgentSpec], dict[str, int]]:
    """The valid agents and {id: index in the file} of every agent whose fields parsed (ids unique)."""
    agents: list[AgentSpec] = []
    ids: dict[str, int] = {}
    for i, raw in enumerate(raw_agents):
        path = f"agents[{i}]"
        if not isinstance(raw, Mapping):
            errors.add(FormationSpecError(path, f"expected a mapping, got {short(raw)}", raw))
            continue
        with errors.item(path, raw, "defaults.agent"):
            a = parse_mapping(_deep_merge(defaults, raw), AGENT_FIELDS, path)
            if a["id"] in ids:
                raise FormationSpecError(f"{path}.id", f"{a['id']!r} is used by agents[{ids[a['id']]}] too", a["id"])
            ids[a["id"]] = i
            agents.append(_make_agent(i, a, path))
    return agents, ids


def _parse_edges(
    raw_edges: list[Any], defaults: Mapping[str, Any], ids: Mapping[str, int] | None, errors: _Collector
) -> list[_ParsedEdge]:
    """The edges whose fields parsed: ends that are agents (checked when ``ids`` is given: every agent
    was valid), distinct, and no pair twice."""
    parsed: list[_ParsedEdge] = []
    seen: dict[frozenset[str], int] = {}
    for k, raw in enumerate(raw_edges):
        path = f"edges[{k}]"
        if not isinstance(raw, Mapping):
            errors.add(FormationSpecError(path, f"expected a mapping, got {short(raw)}", raw))
            continue
        with errors.item(path, raw, "defaults.edge"):
            e = parse_mapping(_deep_merge(defaults, raw), EDGE_FIELDS, path)
            if ids is not None:
                for end in ("tail", "head"):
                    if e[end] not in ids:
                        raise FormationSpecError(
                            f"{path}.{end}", f"unknown agent {e[end]!r} (agents: {', '.join(ids)})", e[end]
                        )
            if e["tail"] == e["head"]:
                raise FormationSpecError(path, f"tail and head are the same agent {e['tail']!r}", e["tail"])
            pair = frozenset((e["tail"], e["head"]))
            if pair in seen:
                raise FormationSpecError(path, f"duplicates edges[{seen[pair]}] ({e['tail']}, {e['head']})", raw)
            seen[pair] = k
            parsed.append((k, e, path))
    return parsed


def _make_edges(
    kept: list[_ParsedEdge], raw_edges: list[Any], agents: list[AgentSpec], errors: _Collector
) -> list[EdgeSpec]:
    """The edges of the sensing tree, each checked against its two agents (indices among the kept)."""
    by_id = {a.id: a for a in agents}
    edges: list[EdgeSpec] = []
    for k, e, path in kept:
        with errors.item(path, raw_edges[k], "defaults.edge"):
            edges.append(_make_edge(len(edges), e, path, by_id[e["tail"]], by_id[e["head"]]))
    return edges


class _Collector:
    """Errors of one formation file in the order found, each once; an item's errors that come from
    ``defaults`` are reported at the defaults."""

    def __init__(self) -> None:
        self.errors: list[FormationSpecError] = []
        self.items = 0
        self._seen: set[tuple[str, str]] = set()

    def add(self, err: FormationSpecError) -> None:
        for e in err.errors if isinstance(err, CollectedFormationSpecError) else [err]:
            key = (e.path, e.message)
            if key not in self._seen:
                self._seen.add(key)
                self.errors.append(e)
            elif e.elements:  # the same default value breaks another agent or edge's check: name it too
                first = next(x for x in self.errors if (x.path, x.message) == key)
                if first.elements:  # (not a value error of the defaults block itself: that names no item)
                    first.elements += [x for x in e.elements if x not in first.elements]

    def extend(self, errs: list[FormationSpecError]) -> None:
        for e in errs:
            self.add(e)

    def run(self, fn: Any) -> Any:
        try:
            return fn()
        except FormationSpecError as exc:
            self.add(exc)
            return None

    @contextlib.contextmanager
    def item(self, path: str, raw: Mapping[str, Any], defaults_path: str) -> Any:
        """Collect the errors of one agent or edge; re-path those whose value came from the defaults."""
        try:
            yield
        except FormationSpecError as exc:
            self.items += 1
            for e in exc.errors if isinstance(exc, CollectedFormationSpecError) else [exc]:
                if e.path.startswith(path + ".") and not _given(raw, split_path(e.path[len(path) + 1 :])):
                    if not e.message == "is required":
                        e.path = defaults_path + e.path[len(path) :]
                        e.elements.append([_label(path, raw), path, ""])  # which agent or edge breaks it
                self.add(e)

    def raise_if_any(self) -> None:
        if self.errors:
            raise self.errors[0] if len(self.errors) == 1 else CollectedFormationSpecError(self.errors)


def _label(path: str, raw: Mapping[str, Any]) -> str:
    """``edges[0] (1, 2)``, ``agents[3] (id 4)``: an item's path and what names it in the file."""
    if "tail" in raw and "head" in raw:
        return f"{path} ({raw['tail']}, {raw['head']})"
    return f"{path} (id {raw['id']})" if "id" in raw else path


def _given(raw: Any, key: tuple[Any, ...]) -> bool:
    """Whether the item itself (not the defaults) holds the value at ``key``."""
    node = raw
    for part in key:
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        else:
            return False
    return True


def _tree(nodes: list[str], pairs: list[tuple[str, str]], reduce: bool) -> tuple[set[int], list[int]]:
    """Indices of the edges kept (all, for a tree) and dropped (spanning-tree reduction)."""
    parent = {n: n for n in nodes}

    def find(x: str) -> str:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    kept: set[int] = set()
    dropped: list[int] = []
    for k, (a, b) in enumerate(pairs):
        ra, rb = find(a), find(b)
        if ra == rb:
            if not reduce:
                raise FormationSpecError(
                    f"edges[{k}]",
                    f"({a}, {b}) closes a cycle: the sensing graph must be a tree "
                    "(set simulation.spanning_tree: true to drop such edges)",
                    (a, b),
                )
            dropped.append(k)
            continue
        parent[ra] = rb
        kept.add(k)
    components: dict[str, list[str]] = {}
    for n in nodes:
        components.setdefault(find(n), []).append(n)
    if len(components) > 1:
        parts = sorted((sorted(c) for c in components.values()), key=len)
        raise FormationSpecError(
            "edges",
            "the sensing graph is disconnected: components " + "; ".join("{" + ", ".join(c) + "}" for c in parts),
            parts,
        )
    return kept, dropped


def _make_agent(index: int, a: Mapping[str, Any], path: str) -> AgentSpec:
    c = a["controller"]
    vf = c["velocity_funnel"]
    rho_0 = None if vf["rho_0"] == "auto" else tuple(vf["rho_0"])
    if rho_0 is not None:
        for ch, (r0, rinf) in enumerate(zip(rho_0, vf["rho_inf"])):
            if rinf >= r0:
                raise FormationSpecError(
                    f"{path}.controller.velocity_funnel.rho_inf",
                    f"channel {ch}: rho_inf {rinf:g} must be below rho_0 {r0:g}",
                    rinf,
                )
    if not c["saturation_margin"] < 0.5:
        raise FormationSpecError(
            f"{path}.controller.saturation_margin",
            f"{c['saturation_margin']!r} must be below 0.5",
            c["saturation_margin"],
        )
    d = a["dynamics"]
    limits = {}
    for key in ("max_force", "max_torque"):
        if c[key] is None:
            limits[key] = d[key]
        elif c[key] > d[key]:
            raise FormationSpecError(
                f"{path}.controller.{key}",
                f"{c[key]:g} exceeds the actuators' dynamics.{key} {d[key]:g}: the simulator would refuse it",
                c[key],
            )
        else:
            limits[key] = c[key]
    gains = ControllerGains(
        **{
            **c,
            "velocity_funnel": VelocityFunnel(**{**vf, "rho_0": rho_0}),
            "max_force": limits["max_force"],
            "max_torque": limits["max_torque"],
        }
    )
    J = np.array(d["inertia"], dtype=np.float64)
    if not np.allclose(J, J.T, atol=1e-12):
        raise FormationSpecError(f"{path}.dynamics.inertia", f"{J.tolist()} is not symmetric", d["inertia"])
    eig = np.linalg.eigvalsh(J)
    if eig.min() <= 0:
        raise FormationSpecError(
            f"{path}.dynamics.inertia",
            f"{J.tolist()} is not positive definite (eigenvalues {eig.round(6).tolist()})",
            d["inertia"],
        )
    signals = {k: SignalModel(d[k]["model"], {p: v for p, v in d[k].items() if p != "model"}) for k in _SIGNALS}
    dyn = Dynamics(**{**d, "inertia": J, **signals})
    return AgentSpec(
        index=index,
        **{
            **record_values(AGENT_FIELDS, a),
            "position": np.array(a["position"]),
            "R_world_body": _rotation_from(a["orientation"], f"{path}.orientation"),
            "controller": gains,
            "dynamics": dyn,
        },
    )


def _make_edge(index: int, e: Mapping[str, Any], path: str, tail: AgentSpec, head: AgentSpec) -> EdgeSpec:
    d_col = e["d_col"] if e["d_col"] is not None else tail.radius + head.radius
    d_con = e["d_con"] if e["d_con"] is not None else min(tail.sensing_radius, head.sensing_radius)
    d_des = e["distance"]
    if not d_col < d_des < d_con:
        raise FormationSpecError(f"{path}.distance", f"{d_des} is not inside (d_col={d_col}, d_con={d_con})", d_des)
    s_min = min(tail.sensing_radius, head.sensing_radius)
    if d_con > s_min + 1e-12:
        raise FormationSpecError(
            f"{path}.d_con",
            f"{d_con:g} exceeds the sensing radius {s_min:g} of its agents: the edge would be lost inside its funnel",
            d_con,
        )
    d0 = float(np.linalg.norm(head.position - tail.position))
    if not d_col < d0 < d_con:
        raise FormationSpecError(
            path,
            f"initial distance {d0:.4g} between {tail.id} and {head.id} is not inside "
            f"(d_col={d_col:g}, d_con={d_con:g})",
            d0,
        )
    R_des = _rotation_from(e["orientation"], f"{path}.orientation")
    psi0 = 0.5 * float(np.trace(np.eye(3) - R_des.T @ head.R_world_body.T @ tail.R_world_body))
    of = e["orientation_funnel"]
    if of["rho_0"] >= 2.0:
        raise FormationSpecError(f"{path}.orientation_funnel.rho_0", f"{of['rho_0']:g} must be below 2", of["rho_0"])
    if psi0 >= of["rho_0"]:
        raise FormationSpecError(
            f"{path}.orientation_funnel.rho_0",
            f"{of['rho_0']:g} must exceed the initial orientation error psi(0)={psi0:.4f}",
            of["rho_0"],
        )
    if of["rho_inf"] >= of["rho_0"]:
        raise FormationSpecError(
            f"{path}.orientation_funnel.rho_inf",
            f"{of['rho_inf']:g} must be below rho_0={of['rho_0']:g}",
            of["rho_inf"],
        )
    c_max = max(d_des**2 - d_col**2, d_con**2 - d_des**2)
    df = e["distance_funnel"]
    if df["rho_inf"] >= c_max:
        raise FormationSpecError(
            f"{path}.distance_funnel.rho_inf",
            f"{df['rho_inf']:g} must be below max(C_col, C_con)={c_max:g}",
            df["rho_inf"],
        )
    return EdgeSpec(index=index, **{**record_values(EDGE_FIELDS, e), "R_des": R_des, "d_col": d_col, "d_con": d_con})
