"""Formation files: read, validate and build the typed formation (:mod:`formation_core.formation`).

``load_formation(path)`` returns an immutable :class:`~formation_core.formation.FormationSpec` or raises
:class:`FormationSpecError` naming the field, e.g.
``edges[2].distance: 4.5 is not inside (d_col=2.0, d_con=4.0)``: every error of the file at once.

Over 500 lines: parsing and the semantic checks share the file's item structure, the
defaults' merge and one error collector, so that every error of a file is reported in file order in
one pass; split, each half would need the other's internals.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from formation_core.errors import FormationSpecError, each_error, one_error
from formation_core.formation import (
    AgentLinks,
    AgentSpec,
    ControllerGains,
    Dynamics,
    EdgeLinks,
    EdgeSpec,
    FormationSpec,
    MeasurementLink,
    SignalModel,
    SimulationSpec,
    VelocityFunnel,
    WrenchLink,
    check_rates,
)
from formation_core.loader import locate, read_document, split_path
from formation_core.rotations import (
    is_rotation,
    matrix_from_axis_angle,
    matrix_from_quaternion,
    matrix_from_rpy,
    project_to_so3,
)
from formation_core.schema import (
    AGENT_FIELDS,
    EDGE_FIELDS,
    TOP_FIELDS,
    Field,
    Parsed,
    UnusableValueError,
    check_partial,
    parse_partial,
    record_values,
    short,
    unknown_key,
)

#: ``project: true`` accepts a matrix with ‖RᵀR − I‖_F up to this and det > 0: the paper's printed
#: R_2(0) is 0.37 off (docs/controller.md, "Errors in the paper"); a reflection (det −1) or a zero
#: matrix has no nearest rotation worth taking.
PROJECT_TOLERANCE = 0.5
_SIGNALS = ("disturbance", "velocity_noise")
_T = TypeVar("_T")

# --- loading ----------------------------------------------------------------------------------


def load_formation(path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> FormationSpec:
    """Read, validate and return a formation file; ``overrides`` replace ``simulation`` keys.

    Raises FormationSpecError (CollectedFormationSpecError for several) with FILE:LINE:COL on each:
    every error of the file at once (duplicate keys, fields, semantic checks), in file order.
    """
    path = Path(path)
    document = read_document(path, collect_duplicates=True)
    data = document.data
    if overrides and isinstance(data, dict):
        data = copy.deepcopy(data)
        data.setdefault("simulation", {})
        if isinstance(data["simulation"], dict):
            data["simulation"].update(overrides)
    try:
        spec = formation_from_dict(data, source=str(path), default_name=path.stem)
    except FormationSpecError as exc:
        raise locate([*document.errors, exc], document) from None
    if document.errors:
        raise locate(document.errors, document)
    return spec


def _deep_merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in top.items():
        # a mapping that names its variant (a signal, a jitter distribution, a loss model) replaces
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) and not {"model", "distribution"} & set(v):
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


def formation_from_dict(document: Any, *, source: str = "<dict>", default_name: str = "formation") -> FormationSpec:
    """Validate a parsed YAML document (see :func:`load_formation`).

    Every error is collected (CollectedFormationSpecError when there are several). A check that needs
    a value the document gets wrong (missing, of the wrong type, a matrix that is not a rotation, an
    agent an edge cannot find) is skipped; every other check runs. The tree is checked once every
    agent and edge is known.
    """
    if not isinstance(document, Mapping):
        raise FormationSpecError("", f"a formation file is a mapping at the top level, got {type(document).__name__}")
    errors = _Collector()
    top = _parse_top(document, errors)
    defaults = _parse_defaults(document, errors)
    raw_agents, raw_edges, lists_ok = _item_lists(document, errors)
    agents = _parse_items(raw_agents, "agents", AGENT_FIELDS, defaults["agent"], errors)
    edges = _parse_items(raw_edges, "edges", EDGE_FIELDS, defaults["edge"], errors)
    link_checks = (partial(_check_agent_links, top),)
    for a in agents:
        _check_item(a, (*_AGENT_CHECKS, *link_checks), errors)
    by_id, ids_complete = _agent_ids(agents, errors)
    ids_complete = ids_complete and lists_ok and len(agents) == len(raw_agents)
    kept, dropped = _sensing_tree(edges, by_id, ids_complete, len(edges) == len(raw_edges), top, errors)
    ends = {k: _ends(edges[k], by_id) for k in kept}
    for k in kept:
        _check_item(edges[k], (*_EDGE_CHECKS, partial(_check_edge_links, top)), errors, *ends[k])
    errors.raise_if_any()

    sim = top["simulation"]
    return FormationSpec(
        name=top["name"] or default_name,
        description=top["description"],
        source=source,
        simulation=SimulationSpec(**{**sim, "gravity": np.array(sim["gravity"])}),
        agents=tuple(_make_agent(a.index, a.values) for a in agents),
        edges=tuple(_make_edge(i, edges[k].values, *ends[k]) for i, k in enumerate(kept)),
        dropped_edges=tuple(dropped),
    )


@dataclass
class _Item:
    """An agent or edge of the file: its index, field path, own mapping (without the defaults) and the
    values that parsed (its checks add the rotation they derive: ``R_world_body``, ``R_des``)."""

    index: int
    path: str
    raw: Mapping[str, Any]
    values: Parsed

    @property
    def defaults_path(self) -> str:
        """Where the values it inherits are given."""
        return "defaults.agent" if self.path.startswith("agents") else "defaults.edge"


def _usable(read: Callable[[], Any]) -> Any:
    """``read()``, or None when it reads a value the file gets wrong."""
    try:
        return read()
    except UnusableValueError:
        return None


def _parse_top(document: Mapping[Any, Any], errors: _Collector) -> Parsed:
    """The unknown top-level keys, then name, description and simulation (rates checked)."""
    known = [f.name for f in TOP_FIELDS]
    for key in document:
        if key not in known:
            errors.add(unknown_key(str(key), key, known))
    plain = ("name", "description", "simulation")
    top_plain = {k: v for k, v in document.items() if k in plain}
    top, errs = parse_partial(top_plain, tuple(f for f in TOP_FIELDS if f.name in plain), "")
    errors.extend(errs)
    errors.run(lambda: check_rates(top["simulation"]["physics_rate"], top["simulation"]["control_rate"]))
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


def _item_lists(document: Mapping[Any, Any], errors: _Collector) -> tuple[list[Any], list[Any], bool]:
    """The raw ``agents`` and ``edges`` lists (empty where not a list) and whether both are valid:
    at least 2 agents, at least 1 edge."""
    raw_agents = document.get("agents")
    raw_edges = document.get("edges")
    agents_ok = isinstance(raw_agents, list) and len(raw_agents) >= 2
    edges_ok = isinstance(raw_edges, list) and len(raw_edges) >= 1
    if not agents_ok:
        errors.add(FormationSpecError("agents", f"expected a list of at least 2 agents, got {short(raw_agents)}"))
    if not edges_ok:
        errors.add(FormationSpecError("edges", f"expected a non-empty list of edges, got {short(raw_edges)}"))
    return (
        raw_agents if isinstance(raw_agents, list) else [],
        raw_edges if isinstance(raw_edges, list) else [],
        agents_ok and edges_ok,
    )


def _parse_items(
    raw_items: list[Any], name: str, fields: tuple[Field, ...], defaults: Mapping[str, Any], errors: _Collector
) -> list[_Item]:
    """The agents or edges that are mappings, each with the values that parsed (the rest reported)."""
    items: list[_Item] = []
    for i, raw in enumerate(raw_items):
        path = f"{name}[{i}]"
        if not isinstance(raw, Mapping):
            errors.add(FormationSpecError(path, f"expected a mapping, got {short(raw)}", raw))
            continue
        values, errs = parse_partial(_deep_merge(defaults, raw), fields, path)
        items.append(_Item(i, path, raw, values))
        errors.add_item(items[-1], errs)
    return items


def _agent_ids(agents: list[_Item], errors: _Collector) -> tuple[dict[str, _Item | None], bool]:
    """{id: agent} (None for an id two agents use) and whether every agent has an id of its own."""
    by_id: dict[str, _Item | None] = {}
    complete = True
    for a in agents:
        agent_id = a.values.get("id")
        if agent_id is None:
            complete = False
        elif agent_id in by_id:
            first = next(b.index for b in agents if b.values.get("id") == agent_id)
            err = FormationSpecError(f"{a.path}.id", f"{agent_id!r} is used by agents[{first}] too", agent_id)
            errors.add_item(a, [err])
            by_id[agent_id] = None
            complete = False
        else:
            by_id[agent_id] = a
    return by_id, complete


def _check_item(item: _Item, checks: Sequence[Callable[..., None]], errors: _Collector, *agents: Parsed) -> None:
    """Run every check of an agent (or of an edge, given its tail and head agents' values)."""
    for check in checks:
        errors.run(partial(check, item.values, *agents, item.path), item)


def _sensing_tree(
    edges: list[_Item],
    by_id: Mapping[str, _Item | None],
    ids_complete: bool,
    all_edges: bool,
    top: Parsed,
    errors: _Collector,
) -> tuple[list[int], list[tuple[str, str]]]:
    """Indices of the edges to check and build, and the (tail, head) of those the spanning-tree
    reduction drops. The tree is known when every agent has an id of its own (``ids_complete``),
    every edge is a mapping (``all_edges``) and simulation.spanning_tree is usable; until then
    every edge is checked and none dropped."""
    pairs = _link_edges(edges, by_id, ids_complete, errors)
    reduce = _usable(lambda: top["simulation"]["spanning_tree"])
    if ids_complete and all_edges and reduce is not None:
        return _reduce_to_tree(list(by_id), pairs, reduce, errors)
    return list(range(len(edges))), []


def _link_edges(
    edges: list[_Item], by_id: Mapping[str, _Item | None], ids_complete: bool, errors: _Collector
) -> list[tuple[str, str] | None]:
    """Per edge, (tail, head) when both are agents of the file, distinct, and no earlier edge joins
    them; else None. An end that names no agent is an error when every agent's id is known."""
    seen: dict[frozenset[str], int] = {}
    pairs: list[tuple[str, str] | None] = []
    for e in edges:
        if ids_complete:
            for end in ("tail", "head"):
                errors.run(partial(_check_end, e, end, by_id), e)
        pairs.append(errors.run(partial(_link, e, by_id, seen), e))
    return pairs


def _check_end(e: _Item, end: str, by_id: Mapping[str, _Item | None]) -> None:
    if e.values[end] not in by_id:
        raise FormationSpecError(
            f"{e.path}.{end}", f"unknown agent {e.values[end]!r} (agents: {', '.join(by_id)})", e.values[end]
        )


def _link(e: _Item, by_id: Mapping[str, _Item | None], seen: dict[frozenset[str], int]) -> tuple[str, str] | None:
    tail, head = e.values["tail"], e.values["head"]
    if tail == head:
        raise FormationSpecError(e.path, f"tail and head are the same agent {tail!r}", tail)
    pair = frozenset((tail, head))
    if pair in seen:
        raise FormationSpecError(e.path, f"duplicates edges[{seen[pair]}] ({tail}, {head})", e.raw)
    seen[pair] = e.index
    return (tail, head) if by_id.get(tail) is not None and by_id.get(head) is not None else None


def _ends(e: _Item, by_id: Mapping[str, _Item | None]) -> tuple[Parsed, Parsed]:
    """The values of the edge's tail and head agents (empty where the agent is unknown: every check
    that needs it is skipped)."""
    found = [by_id.get(e.values.get(end, "")) for end in ("tail", "head")]
    tail, head = (a.values if a is not None else Parsed() for a in found)
    return tail, head


class _Collector:
    """Errors of one formation file in the order found, each once; an item's errors that come from
    ``defaults`` are reported at the defaults."""

    def __init__(self) -> None:
        self.errors: list[FormationSpecError] = []
        self._seen: set[tuple[str, str]] = set()

    def add(self, err: FormationSpecError) -> None:
        for e in each_error(err):
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

    def run(self, check: Callable[[], _T], item: _Item | None = None) -> _T | None:
        """``check()``; None when it finds an error (collected, as one of ``item``'s if given) or needs a
        value the file gets wrong (skipped: that value's own error is reported)."""
        try:
            return check()
        except UnusableValueError:
            return None
        except FormationSpecError as exc:
            if item is None:
                self.add(exc)
            else:
                self.add_item(item, each_error(exc))
            return None

    def add_item(self, item: _Item, errs: list[FormationSpecError]) -> None:
        """Collect the errors of one agent or edge; re-path those whose value came from the defaults."""
        for e in errs:
            if e.path.startswith(item.path + ".") and not _given(item.raw, split_path(e.path[len(item.path) + 1 :])):
                if not e.message == "is required":
                    e.path = item.defaults_path + e.path[len(item.path) :]
                    e.elements.append([_label(item.path, item.raw), item.path, ""])  # which agent or edge breaks it
            self.add(e)

    def raise_if_any(self) -> None:
        if self.errors:
            raise one_error(self.errors)


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


def _reduce_to_tree(
    nodes: list[str], pairs: list[tuple[str, str] | None], reduce: bool, errors: _Collector
) -> tuple[list[int], list[tuple[str, str]]]:
    """Indices of the edges kept and the (tail, head) of those dropped (spanning-tree reduction);
    without ``reduce`` an edge that closes a cycle is an error (neither kept nor dropped). An edge
    that is not linked (``None``: its error is reported) is kept for its own checks; connectivity is
    checked when every edge is linked."""
    parent = {n: n for n in nodes}

    def find(x: str) -> str:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    kept: list[int] = []
    dropped: list[tuple[str, str]] = []
    for k, pair in enumerate(pairs):
        if pair is None:
            kept.append(k)
            continue
        a, b = pair
        ra, rb = find(a), find(b)
        if ra == rb:
            if reduce:
                dropped.append(pair)
            else:
                errors.add(
                    FormationSpecError(
                        f"edges[{k}]",
                        f"({a}, {b}) closes a cycle: the sensing graph must be a tree "
                        "(set simulation.spanning_tree: true to drop such edges)",
                        (a, b),
                    )
                )
            continue
        parent[ra] = rb
        kept.append(k)
    if None not in pairs:
        _check_connected(nodes, find, errors)
    return kept, dropped


def _check_connected(nodes: list[str], find: Callable[[str], str], errors: _Collector) -> None:
    components: dict[str, list[str]] = {}
    for n in nodes:
        components.setdefault(find(n), []).append(n)
    if len(components) > 1:
        parts = sorted((sorted(c) for c in components.values()), key=len)
        errors.add(
            FormationSpecError(
                "edges",
                "the sensing graph is disconnected: components " + "; ".join("{" + ", ".join(c) + "}" for c in parts),
                parts,
            )
        )


# --- checks of one agent or edge --------------------------------------------------------------
# Each reads the values it needs from the item's Parsed values (and its agents'); one that reads a
# value the file gets wrong raises UnusableValueError and is skipped (that value's error is reported).


def _check_agent_orientation(a: Parsed, path: str) -> None:
    a["R_world_body"] = _rotation_from(a["orientation"], f"{path}.orientation")


def _check_velocity_funnel(a: Parsed, path: str) -> None:
    vf = a["controller"]["velocity_funnel"]
    if vf["rho_0"] == "auto":
        return
    for ch, (r0, rinf) in enumerate(zip(vf["rho_0"], vf["rho_inf"])):
        if rinf >= r0:
            raise FormationSpecError(
                f"{path}.controller.velocity_funnel.rho_inf",
                f"channel {ch}: rho_inf {rinf:g} must be below rho_0 {r0:g}",
                rinf,
            )


def _check_saturation_margin(a: Parsed, path: str) -> None:
    c = a["controller"]
    if not c["saturation_margin"] < 0.5:
        raise FormationSpecError(
            f"{path}.controller.saturation_margin",
            f"{c['saturation_margin']!r} must be below 0.5",
            c["saturation_margin"],
        )


def _check_actuator_limit(key: str, a: Parsed, path: str) -> None:
    """The controller's ``max_force`` or ``max_torque``, where given, within the actuators'."""
    c, d = a["controller"], a["dynamics"]
    if c[key] is not None and c[key] > d[key]:
        raise FormationSpecError(
            f"{path}.controller.{key}",
            f"{c[key]:g} exceeds the actuators' dynamics.{key} {d[key]:g}: the simulator would refuse it",
            c[key],
        )


def _check_inertia(a: Parsed, path: str) -> None:
    J = np.array(a["dynamics"]["inertia"], dtype=np.float64)
    if not np.allclose(J, J.T, atol=1e-12):
        raise FormationSpecError(f"{path}.dynamics.inertia", f"{J.tolist()} is not symmetric", a["dynamics"]["inertia"])
    eig = np.linalg.eigvalsh(J)
    if eig.min() <= 0:
        raise FormationSpecError(
            f"{path}.dynamics.inertia",
            f"{J.tolist()} is not positive definite (eigenvalues {eig.round(6).tolist()})",
            a["dynamics"]["inertia"],
        )


def _jitter_max(jitter: Mapping[str, Any]) -> float:
    """The largest extra delay of a jitter distribution [s]."""
    return 0.0 if jitter["distribution"] == "none" else float(jitter["max"])


def _link_errors(link: Mapping[str, Any] | None, sim: Parsed, path: str) -> list[FormationSpecError]:
    """A measurement or wrench link against the run: no sensor faster than the control rate, every
    sample able to arrive within the run, and the sampled controller (a link delivers at control steps).
    A check that needs a value the file gets wrong is skipped (that value's error is reported)."""
    if link is None:
        return []
    errs = []

    def rate_check() -> None:
        rate = link.get("rate")
        if rate is not None and rate > sim["control_rate"]:
            raise FormationSpecError(
                f"{path}.rate",
                f"{rate:g} Hz is faster than simulation.control_rate {sim['control_rate']:g} Hz "
                "(a sensor is sampled at control steps)",
                rate,
            )

    def delay_check() -> None:
        extra = _jitter_max(link["jitter"]) if "jitter" in link else 0.0  # a wrench link has none
        if link["delay"] + extra >= sim["duration"]:
            raise FormationSpecError(
                f"{path}.delay",
                f"{link['delay']:g} s, with the jitter's largest extra delay {extra:g} s, is not below "
                f"simulation.duration {sim['duration']:g} s: no sample would arrive",
                link["delay"],
            )

    def mode_check() -> None:
        ideal = link.get("rate") is None and link["delay"] == 0.0 and link["loss"]["model"] == "none"
        ideal = ideal and ("jitter" not in link or link["jitter"]["distribution"] == "none")
        if not ideal and sim["controller"] == "continuous":
            raise FormationSpecError(
                path,
                "a link model delivers its samples at control steps: it needs simulation.controller: sampled "
                "(continuous evaluates the law between them)",
            )

    for check in (rate_check, delay_check, mode_check):
        try:
            check()
        except UnusableValueError:
            continue
        except FormationSpecError as exc:
            errs.append(exc)
    return errs


def _check_links(sim: Parsed, links: Parsed, keys: tuple[str, ...], path: str) -> None:
    """:func:`_link_errors` of each link in ``links`` (one whose values the file gets wrong is skipped:
    those errors are reported already)."""
    errs: list[FormationSpecError] = []
    for key in keys:
        try:
            errs += _link_errors(links[key], sim, f"{path}.links.{key}")
        except UnusableValueError:
            continue
    if errs:
        raise one_error(errs)


def _check_agent_links(top: Parsed, a: Parsed, path: str) -> None:
    _check_links(top["simulation"], a["links"], ("poses", "velocity", "wrench"), path)


def _check_edge_links(top: Parsed, e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    _check_links(top["simulation"], e["links"], ("tail", "head"), path)


_AGENT_CHECKS: tuple[Callable[[Parsed, str], None], ...] = (
    _check_agent_orientation,
    _check_velocity_funnel,
    _check_saturation_margin,
    partial(_check_actuator_limit, "max_force"),
    partial(_check_actuator_limit, "max_torque"),
    _check_inertia,
)


def _d_col(e: Parsed, tail: Parsed, head: Parsed) -> float:
    """The collision distance: as given, or r_tail + r_head (m)."""
    return float(e["d_col"] if e["d_col"] is not None else tail["radius"] + head["radius"])


def _d_con(e: Parsed, tail: Parsed, head: Parsed) -> float:
    """The connectivity distance: as given, or min(s_tail, s_head) (m)."""
    return float(e["d_con"] if e["d_con"] is not None else min(tail["sensing_radius"], head["sensing_radius"]))


def _check_edge_orientation(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    e["R_des"] = _rotation_from(e["orientation"], f"{path}.orientation")


def _check_distance(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    d_col, d_con, d_des = _d_col(e, tail, head), _d_con(e, tail, head), e["distance"]
    if not d_col < d_des < d_con:
        raise FormationSpecError(f"{path}.distance", f"{d_des} is not inside (d_col={d_col}, d_con={d_con})", d_des)


def _check_d_con(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    d_con = _d_con(e, tail, head)
    s_min = min(tail["sensing_radius"], head["sensing_radius"])
    if d_con > s_min + 1e-12:
        raise FormationSpecError(
            f"{path}.d_con",
            f"{d_con:g} exceeds the sensing radius {s_min:g} of its agents: the edge would be lost inside its funnel",
            d_con,
        )


def _check_initial_distance(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    d_col, d_con = _d_col(e, tail, head), _d_con(e, tail, head)
    d0 = float(np.linalg.norm(np.subtract(head["position"], tail["position"])))
    if not d_col < d0 < d_con:
        raise FormationSpecError(
            path,
            f"initial distance {d0:.4g} between {tail['id']} and {head['id']} is not inside "
            f"(d_col={d_col:g}, d_con={d_con:g})",
            d0,
        )


def _check_rho_psi_0(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    of = e["orientation_funnel"]
    if of["rho_0"] >= 2.0:
        raise FormationSpecError(f"{path}.orientation_funnel.rho_0", f"{of['rho_0']:g} must be below 2", of["rho_0"])


def _check_psi_0(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    from formation_core import funnels

    R_des = e["R_des"]  # set by _check_edge_orientation, which runs first
    _, psi0 = funnels.edge_errors_from_arrays(
        tail["position"], head["position"], tail["R_world_body"], head["R_world_body"], e["distance"], R_des
    )
    of = e["orientation_funnel"]
    if psi0 >= of["rho_0"]:
        raise FormationSpecError(
            f"{path}.orientation_funnel.rho_0",
            f"{of['rho_0']:g} must exceed the initial orientation error psi(0)={psi0:.4f}",
            of["rho_0"],
        )


def _check_rho_psi_inf(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    of = e["orientation_funnel"]
    if of["rho_inf"] >= of["rho_0"]:
        raise FormationSpecError(
            f"{path}.orientation_funnel.rho_inf",
            f"{of['rho_inf']:g} must be below rho_0={of['rho_0']:g}",
            of["rho_inf"],
        )


def _check_rho_e_inf(e: Parsed, tail: Parsed, head: Parsed, path: str) -> None:
    d_col, d_con, d_des = _d_col(e, tail, head), _d_con(e, tail, head), e["distance"]
    s_min = min(tail["sensing_radius"], head["sensing_radius"])
    if not (d_col < d_des < d_con and d_con <= s_min + 1e-12):  # reported: C_col and C_con bound nothing then
        return
    c_max = max(d_des**2 - d_col**2, d_con**2 - d_des**2)
    df = e["distance_funnel"]
    if df["rho_inf"] >= c_max:
        raise FormationSpecError(
            f"{path}.distance_funnel.rho_inf",
            f"{df['rho_inf']:g} must be below max(C_col, C_con)={c_max:g}",
            df["rho_inf"],
        )


_EDGE_CHECKS: tuple[Callable[[Parsed, Parsed, Parsed, str], None], ...] = (
    _check_edge_orientation,
    _check_distance,
    _check_d_con,
    _check_initial_distance,
    _check_rho_psi_0,
    _check_psi_0,
    _check_rho_psi_inf,
    _check_rho_e_inf,
)


# --- built objects (from values every check passed) -------------------------------------------


def _make_agent(index: int, a: Mapping[str, Any]) -> AgentSpec:
    c = a["controller"]
    vf = c["velocity_funnel"]
    rho_0 = None if vf["rho_0"] == "auto" else tuple(vf["rho_0"])
    d = a["dynamics"]
    limits = {key: d[key] if c[key] is None else c[key] for key in ("max_force", "max_torque")}
    gains = ControllerGains(
        **{
            **c,
            "velocity_funnel": VelocityFunnel(**{**vf, "rho_0": rho_0}),
            "max_force": limits["max_force"],
            "max_torque": limits["max_torque"],
        }
    )
    signals = {k: _signal(d[k]) for k in _SIGNALS}
    dyn = Dynamics(**{**d, "inertia": np.array(d["inertia"], dtype=np.float64), **signals})
    links = a["links"]
    return AgentSpec(
        index=index,
        **{
            **record_values(AGENT_FIELDS, a),
            "position": np.array(a["position"]),
            "R_world_body": a["R_world_body"],
            "controller": gains,
            "dynamics": dyn,
            "links": AgentLinks(
                _stream(links["poses"]),
                _stream(links["velocity"]),
                WrenchLink(links["wrench"]["delay"], _signal(links["wrench"]["loss"])),
            ),
        },
    )


def _signal(parsed: Mapping[str, Any], key: str = "model") -> SignalModel:
    return SignalModel(parsed[key], {p: v for p, v in parsed.items() if p != key})


def _stream(parsed: Mapping[str, Any]) -> MeasurementLink:
    return MeasurementLink(
        parsed["rate"], parsed["delay"], _signal(parsed["jitter"], "distribution"), _signal(parsed["loss"])
    )


def _measurement_link(parsed: Mapping[str, Any] | None) -> MeasurementLink | None:
    return None if parsed is None else _stream(parsed)


def _make_edge(index: int, e: Parsed, tail: Parsed, head: Parsed) -> EdgeSpec:
    return EdgeSpec(
        index=index,
        **{
            **record_values(EDGE_FIELDS, e),
            "R_des": e["R_des"],
            "d_col": _d_col(e, tail, head),
            "d_con": _d_con(e, tail, head),
            "links": EdgeLinks(_measurement_link(e["links"]["tail"]), _measurement_link(e["links"]["head"])),
        },
    )
