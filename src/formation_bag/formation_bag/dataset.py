"""A recorded run decoded from a bag: ground truth, measurements and wrenches keyed by stamp.

Used by the analysis and the controller re-run (no ROS). Stamps are integer nanoseconds (exact
step matching); log times are the recorder's receive times (ns).

The formation file comes from ``--formation FILE`` or, when the recorder was given one, from
the bag itself (``custom_data.formation_yaml`` in metadata.yaml and in every segment).
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from formation_bag import messages as m
from formation_bag.reader import Bag
from formation_msgs_py.bag import KEY_FORMATION_FILE, KEY_FORMATION_YAML
from formation_msgs_py.errors import BagFormatError, BagTopicError, FormationSpecError, OverrideError
from formation_msgs_py.loader import parse_document, read_document
from formation_msgs_py.spec import FormationSpec, formation_from_dict


@dataclass
class Series:
    """Messages of one topic in stamp order: stamps (ns), log times (ns), decoded values."""

    stamps: list[int] = field(default_factory=list)
    log_times: list[int] = field(default_factory=list)
    values: list[Any] = field(default_factory=list)

    def add(self, stamp: int, log_time: int, value: Any) -> None:
        self.stamps.append(stamp)
        self.log_times.append(log_time)
        self.values.append(value)

    def sort(self) -> None:
        if any(a > b for a, b in zip(self.stamps, self.stamps[1:])):
            order = sorted(range(len(self.stamps)), key=lambda k: (self.stamps[k], self.log_times[k]))
            self.stamps = [self.stamps[k] for k in order]
            self.log_times = [self.log_times[k] for k in order]
            self.values = [self.values[k] for k in order]

    def latest_at(self, stamp: int) -> int | None:
        """Index of the last message with stamp ≤ ``stamp`` (None if there is none)."""
        k = bisect.bisect_right(self.stamps, stamp) - 1
        return k if k >= 0 else None

    def __len__(self) -> int:
        return len(self.stamps)


@dataclass
class RunData:
    path: Path
    spec: FormationSpec
    document: dict[str, Any]
    custom_data: dict[str, str]
    ground_truth: Series
    velocity: dict[str, Series]
    wrench: dict[str, Series]
    relative_pose: dict[tuple[str, str], Series]
    clock: Series
    lost: list[str]
    recovered: bool
    first_log: int
    last_log: int
    topic_counts: dict[str, int]


def formation_document(bag: Bag, formation: str | Path | None) -> tuple[dict[str, Any], str]:
    """The formation file's YAML document and its name (``--formation`` wins over the bag's copy)."""
    if formation is not None:
        document = read_document(formation)  # the one reader of formation files (FILE:LINE:COL errors)
        name = str(formation)
    else:
        text = bag.custom_data.get(KEY_FORMATION_YAML)
        if not text:
            raise BagFormatError(
                f"bag {bag.path} carries no formation file (custom_data.{KEY_FORMATION_YAML}); pass --formation FILE"
            )
        name = bag.custom_data.get(KEY_FORMATION_FILE, "formation.yaml")
        document = parse_document(text.encode("utf-8"), name)
    doc = document.data
    if not isinstance(doc, dict):
        raise FormationSpecError("", f"{name}: a formation file is a mapping at the top level")
    return doc, name


def spec_from_document(doc: Mapping[str, Any], name: str) -> FormationSpec:
    return formation_from_dict(doc, source=name, default_name=Path(name).stem)


def apply_overrides(doc: Mapping[str, Any], overrides: Mapping[str, Any], where: str = "override") -> dict[str, Any]:
    """A formation document with gains/funnels replaced by an override file.

    Override file (YAML)::

        agents:            # by agent id: any agent keys (controller: gains, velocity_funnel, …)
          "3": {controller: {gamma: 10.0}}
        edges:             # by "tail-head": any edge keys (distance_funnel, orientation_funnel, …)
          "1-2": {distance_funnel: {decay: 1.0}}
        defaults: {agent: {...}, edge: {...}}   # merged into the file's defaults
    """
    if not isinstance(overrides, Mapping):
        raise OverrideError(where, "expected a mapping with keys agents, edges, defaults")
    unknown = set(overrides) - {"agents", "edges", "defaults"}
    if unknown:
        raise OverrideError(f"{where}.{sorted(unknown)[0]}", "unknown key (expected agents, edges, defaults)")
    out = _deep_copy(doc)
    if "defaults" in overrides:
        if not isinstance(overrides["defaults"], Mapping):
            raise OverrideError(f"{where}.defaults", "expected a mapping")
        out["defaults"] = _merge(out.get("defaults") or {}, overrides["defaults"])
    agents = out.get("agents") or []
    for aid, change in (overrides.get("agents") or {}).items():
        idx = next((k for k, a in enumerate(agents) if str(a.get("id")) == str(aid)), None)
        if idx is None:
            ids = ", ".join(str(a.get("id")) for a in agents)
            raise OverrideError(f"{where}.agents.{aid}", f"no agent with id {aid!r} (have {ids})")
        if not isinstance(change, Mapping):
            raise OverrideError(f"{where}.agents.{aid}", "expected a mapping")
        agents[idx] = _merge(agents[idx], change)
    edges = out.get("edges") or []
    for name, change in (overrides.get("edges") or {}).items():
        tail, _, head = str(name).partition("-")
        idx = next((k for k, e in enumerate(edges) if {str(e.get("tail")), str(e.get("head"))} == {tail, head}), None)
        if idx is None:
            raise OverrideError(f"{where}.edges.{name}", "no such edge (write it as TAIL-HEAD, e.g. 1-2)")
        if not isinstance(change, Mapping):
            raise OverrideError(f"{where}.edges.{name}", "expected a mapping")
        edges[idx] = _merge(edges[idx], change)
    return out


def _deep_copy(x: Any) -> Any:
    if isinstance(x, Mapping):
        return {k: _deep_copy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_deep_copy(v) for v in x]
    return x


def _merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in top.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = _deep_copy(v)
    return out


def load_run(
    path: str | Path,
    *,
    formation: str | Path | None = None,
    namespace: str = "",
    need_ground_truth: bool = True,
) -> RunData:
    """Read and decode every docs/topics.md topic of a bag (tolerates a killed recorder's bag)."""
    path = Path(path)
    with Bag(path) as bag:
        doc, name = formation_document(bag, formation)
        spec = spec_from_document(doc, name)
        # the topics of docs/topics.md this analysis reads (not diagnostics), by what they carry
        kinds = {t: k for t in bag.topics if (k := m.classify(t, namespace)) is not None and k.kind != "diagnostics"}
        wanted = list(kinds)
        gt = Series()
        clock = Series()
        vel: dict[str, Series] = {a.id: Series() for a in spec.agents}
        wr: dict[str, Series] = {a.id: Series() for a in spec.agents}
        rel: dict[tuple[str, str], Series] = {}
        counts: dict[str, int] = {t: 0 for t in bag.topics}
        first = last = None
        decode = m.fast_decode
        for msg in bag.messages(wanted):
            counts[msg.topic] += 1
            first = msg.log_time if first is None else min(first, msg.log_time)
            last = msg.log_time if last is None else max(last, msg.log_time)
            k = kinds[msg.topic]
            stamp, value = decode(k.kind, msg.data, msg.msgtype)
            if k.kind == "clock":
                clock.add(stamp, msg.log_time, None)
            elif k.kind == "ground_truth":
                gt.add(stamp, msg.log_time, value)
            elif k.agent is None:
                continue  # every other kind names its agent (messages.classify)
            elif k.kind == "velocity" and k.agent in vel:
                vel[k.agent].add(stamp, msg.log_time, value)
            elif k.kind == "wrench" and k.agent in wr:
                wr[k.agent].add(stamp, msg.log_time, value)
            elif k.kind == "relative_pose" and k.target is not None:
                rel.setdefault((k.agent, k.target), Series()).add(stamp, msg.log_time, value)
        lost, recovered = list(bag.lost), bag.recovered
        custom = dict(bag.custom_data)
    for s in (gt, clock, *vel.values(), *wr.values(), *rel.values()):
        s.sort()
    if need_ground_truth and not len(gt):
        raise BagTopicError(
            f"bag {path} has no {m.absolute('formation/ground_truth', namespace)} messages: cannot check the funnels"
        )
    n = len(spec.agents)
    for i, s in enumerate(gt.values):
        if len(s[0]) != n:
            raise BagFormatError(
                f"bag {path}: ground truth at stamp {gt.stamps[i]} ns has {len(s[0])} poses, "
                f"the formation file {name} has {n} agents"
            )
    return RunData(path, spec, doc, custom, gt, vel, wr, rel, clock, lost, recovered, first or 0, last or 0, counts)
