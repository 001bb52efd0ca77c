"""A recorded run decoded from a bag: ground truth, measurements and wrenches keyed by stamp.

Used by the analysis and the controller re-run (no ROS). Stamps are integer nanoseconds (exact
step matching); log times are the recorder's receive times (ns).

The formation file comes from ``--formation FILE`` or, when the recorder was given one, from
the bag itself (``custom_data.formation_yaml`` in metadata.yaml and in every segment). What was
run (mode, control rate, duration) may differ from the file's (command-line overrides): the bag
says it where its writer knew it (:func:`stated_settings`).
"""

from __future__ import annotations

import argparse
import bisect
from array import array
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

from formation_bag import messages as m
from formation_bag.contract import KEY_FORMATION_FILE, KEY_FORMATION_YAML
from formation_bag.progress import Progress
from formation_bag.reader import Bag
from formation_core.errors import BagFormatError, BagTopicError, FormationSpecError, OverrideError
from formation_core.formation import FormationSpec
from formation_core.loader import parse_document, read_document
from formation_core.options import positive
from formation_core.schema import SIMULATION_FIELDS
from formation_core.spec import formation_from_dict


class Series:
    """Messages of one topic in stamp order: stamps (ns), log times (ns), values.

    Stored compactly (a bag holds ~10⁶ messages: Python lists of decoded values took ~1.5 GB):
    each message's ``width`` doubles as sent (docs/topics.md order) in one flat array; ``values[k]``
    decodes message k on demand with ``decode`` (the nodes' own decoders, so the numbers are the
    ones the agents saw).
    """

    def __init__(self, width: int = 0, decode: Callable[[Sequence[float]], Any] | None = None) -> None:
        self.width = width
        self.decode = decode
        self.stamps = array("q")
        self.log_times = array("q")
        self.flat = array("d")
        self.values = _Values(self)

    def add(self, stamp: int, log_time: int, doubles: Sequence[float]) -> None:
        """One message: its stamp and log time (ns) and its ``width`` doubles."""
        if len(doubles) != self.width:
            raise BagFormatError(f"a message of {len(doubles)} values where {self.width} were expected")
        self.stamps.append(stamp)
        self.log_times.append(log_time)
        self.flat.extend(doubles)

    def value(self, k: int) -> Any:
        """The decoded value of message k."""
        if self.decode is None:
            return None
        w = self.width
        return self.decode(self.flat[k * w : (k + 1) * w])

    def sort(self) -> None:
        if any(a > b for a, b in zip(self.stamps, self.stamps[1:])):
            order = sorted(range(len(self.stamps)), key=lambda k: (self.stamps[k], self.log_times[k]))
            w, flat = self.width, self.flat
            self.stamps = array("q", (self.stamps[k] for k in order))
            self.log_times = array("q", (self.log_times[k] for k in order))
            self.flat = array("d", (x for k in order for x in flat[k * w : (k + 1) * w]))

    def latest_at(self, stamp: int) -> int | None:
        """Index of the last message with stamp ≤ ``stamp`` (None if there is none)."""
        k = bisect.bisect_right(self.stamps, stamp) - 1
        return k if k >= 0 else None

    def exactly_at(self, stamp: int) -> int | None:
        """Index of the last message stamped exactly ``stamp`` (None if there is none)."""
        k = self.latest_at(stamp)
        return k if k is not None and self.stamps[k] == stamp else None

    def __len__(self) -> int:
        return len(self.stamps)


class _Values(Sequence[Any]):
    """The decoded values of a :class:`Series`, one at a time (nothing is held)."""

    def __init__(self, series: Series) -> None:
        self._s = series

    def __len__(self) -> int:
        return len(self._s)

    @overload
    def __getitem__(self, k: int) -> Any: ...
    @overload
    def __getitem__(self, k: slice) -> list[Any]: ...
    def __getitem__(self, k: int | slice) -> Any:
        if isinstance(k, slice):
            return [self._s.value(i) for i in range(*k.indices(len(self)))]
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        return self._s.value(k)


#: custom_data keys that say what was run: the simulator's own bag has them, formation-record
#: ``--meta KEY=VALUE`` adds them; the analysis takes them over the formation file's settings
RUN_SETTING_KEYS = ("mode", "control_rate", "duration")
MODES: tuple[str, ...] = next(f.choices for f in SIMULATION_FIELDS if f.name == "mode")


@dataclass(frozen=True)
class StatedSettings:
    """What a bag says was run (None: it does not say): mode, control rate [Hz], duration [s]."""

    mode: str | None = None
    control_rate: float | None = None
    duration: float | None = None


def stated_settings(custom: Mapping[str, str], where: str) -> StatedSettings:
    """The run settings of ``custom`` (custom_data, or formation-record's ``--meta``).

    Raises :class:`BagFormatError` naming ``where`` + the key and the value when one is not a
    mode of the formation file or a finite number > 0.
    """
    mode = custom.get("mode")
    if mode is not None and mode not in MODES:
        raise BagFormatError(f"{where}mode {mode!r} is not one of {', '.join(MODES)}")
    numbers: dict[str, float | None] = {}
    for key in ("control_rate", "duration"):
        text = custom.get(key)
        try:
            numbers[key] = None if text is None else positive(text)
        except argparse.ArgumentTypeError as exc:
            raise BagFormatError(f"{where}{key} {exc}") from None
    return StatedSettings(mode, numbers["control_rate"], numbers["duration"])


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
    stated: StatedSettings  # what the bag says was run (custom_data)


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
    prog: str = "formation-bag",
) -> RunData:
    """Read and decode every docs/topics.md topic of a bag in one pass (tolerates a killed recorder's
    bag); a progress line on stderr every few seconds when it takes that long."""
    path = Path(path)
    with Bag(path) as bag:
        stated = stated_settings(bag.custom_data, f"bag {path}: custom_data.")
        doc, name = formation_document(bag, formation)
        spec = spec_from_document(doc, name)
        infos = bag.topics
        kinds = {t: m.classify(t, namespace) for t in infos}
        wanted = [t for t, k in kinds.items() if k is not None and k.kind != "diagnostics"]
        n_agents = len(spec.agents)
        gt = Series(7 * n_agents, m.FROM_VALUES["ground_truth"])
        clock = Series()
        vel = {a.id: Series(6, m.FROM_VALUES["velocity"]) for a in spec.agents}
        wr = {a.id: Series(6, m.FROM_VALUES["wrench"]) for a in spec.agents}
        rel: dict[tuple[str, str], Series] = {}
        # every series a topic's messages go to (None: a topic of no agent of the formation)
        target: dict[str, Series | None] = {}
        for t in wanted:
            k = kinds[t]
            assert k is not None
            if k.kind == "clock":
                target[t] = clock
            elif k.kind == "ground_truth":
                target[t] = gt
            elif k.kind == "velocity":
                target[t] = vel.get(k.agent or "")
            elif k.kind == "wrench":
                target[t] = wr.get(k.agent or "")
            else:
                target[t] = rel.setdefault((k.agent or "", k.target or ""), Series(7, m.FROM_VALUES["relative_pose"]))
        first = last = None
        values_of = m.fast_values
        progress = Progress(prog, f"reading {path.name}", sum(infos[t].count for t in wanted))
        n = 0
        for msg in bag.messages(wanted):
            n += 1
            progress.update(n)
            lg = msg.log_time
            if first is None or lg < first:
                first = lg
            if last is None or lg > last:
                last = lg
            series = target[msg.topic]
            if series is None:
                continue
            stamp, values = values_of(kinds[msg.topic].kind, msg.data, msg.msgtype)  # type: ignore[union-attr]
            if len(values) != series.width:
                raise BagFormatError(
                    f"bag {path}: {msg.topic} at stamp {stamp} ns holds {len(values)} values, expected "
                    f"{series.width}" + (f" (7 per agent: {name} has {n_agents} agents)" if series is gt else "")
                )
            series.add(stamp, lg, values)
        progress.finish(n)
        lost, recovered = list(bag.lost), bag.recovered
        custom = dict(bag.custom_data)
        # every topic's count, also of those not decoded (/diagnostics, markers, funnels): from the index
        counts = {t: info.count for t, info in infos.items()}
    for s in (gt, clock, *vel.values(), *wr.values(), *rel.values()):
        s.sort()
    if need_ground_truth and not len(gt):
        raise BagTopicError(
            f"bag {path} has no {m.absolute('formation/ground_truth', namespace)} messages: cannot check the funnels"
        )
    return RunData(
        path, spec, doc, custom, gt, vel, wr, rel, clock, lost, recovered, first or 0, last or 0, counts, stated
    )
