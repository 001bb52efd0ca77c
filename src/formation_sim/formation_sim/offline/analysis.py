"""Offline analysis of a recorded run (no ROS): ``formation-analyze BAG --out DIR``.

From ``/formation/ground_truth`` it recomputes every e_k and ψ_k and checks every funnel with
the same :class:`formation_sim.core.recorder.RunRecorder` the headless runner and the simulator use,
so the outputs have the format of docs/outputs.md (summary.json, trajectory.npz, the figures and
the Foxglove layout). Per ground-truth sample (stamp t_k) it uses:

- u: the wrench each agent published with stamp t_k; if the bag misses it (a recorder that matched
  an agent late), the re-run's wrench for t_k (equal to the agent's on every recorded step), else
  the latest earlier one (zero-order hold);
  realtime runs: the latest wrench received before the next sample, zero if older than
  ``command_timeout`` (the simulator's rule, with the recorder's receive order);
- ṽ (trajectory ``v``): the recorded noisy twist (the bag has no true velocity);
- the velocity-funnel margins and controller levels: from re-running each agent's controller on
  its recorded measurements (:mod:`formation_sim.offline.rerun`; exactly what the agent computed), with
  the same fault order as the headless runner (missing measurement, funnels, controller ERROR).

It also writes CSV exports (errors.csv, inputs.csv, positions.csv), and ``ages.json``/``ages.csv``:
for bags with receive log times, the age of every measurement and wrench per edge and agent, in
simulation time (latest /clock at receipt − header stamp) and in wall time (receipt − receipt of
the /clock that announced the stamp), and each agent's response time (wrench receipt − receipt of
its velocity with that stamp); a lockstep bag's log times are simulation time: no ages. The
summary's wall time and real-time factor are the run's (:func:`run_wall_time`).
A bag truncated by a killed recorder, or missing messages, is analysed as far as it goes: the
verdict is then INCOMPLETE with what is missing listed (``bag.missing``), never FAIL for lack of
data; a violation seen in the data present is still FAIL.

Over 500 lines: the settings of a run read back from its bag, the step-by-step replay of what the
simulator decided, the report of what the bag lacks and the exports all read the same decoded run
(:class:`formation_bag.dataset.RunData`) with the same notion of a step; apart, each would re-derive it.
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import sys
import time
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from formation_agent.controller import ERROR
from formation_bag import messages as m
from formation_bag.contract import KEY_LINKS, KEY_REPAIRED, KEY_RUN_STOPPED
from formation_bag.dataset import RunData, Series, load_run
from formation_core.errors import BagError, FormationError
from formation_core.faults import write_json
from formation_core.verdict import ExitCode, Incomplete, guarded
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.summary import BagReport, LinkReport, RunSummary
from formation_sim.offline.parsers import VELOCITY_MARGIN_MODES, analyze_parser
from formation_sim.offline.rerun import AgentRerun, rerun_all
from formation_sim.preflight import prepare_out_dir
from formation_sim.views.outputs import format_summary, report_animation, write_outputs


def _rate_from_stamps(stamps: Sequence[int]) -> float | None:
    if len(stamps) < 2:
        return None
    d = np.diff(np.asarray(stamps, dtype=np.int64))
    d = d[d > 0]
    if not d.size:
        return None
    return m.NS_PER_S / float(np.median(d))


@dataclass(frozen=True)
class RunSettings:
    """What the analysis needs to know of the run beyond its messages: what the bag says was run
    (custom_data), else what its messages show, else the formation file's."""

    mode: str
    control_rate: float  # Hz
    gt_rate: float  # Hz of the recorded ground truth
    duration: float  # s: the span [0, duration] every sample of which is expected in the bag
    gt_rate_measured: float | None  # from the stamps (None: fewer than two samples)
    #: s: what the run was asked for, as the bag says or else the formation file; None when the
    #: ground truth runs past it and the bag does not say (then ``duration`` is the recorded span)
    requested_duration: float | None = None
    #: where mode, control_rate and duration come from: ``bag`` (custom_data), ``recording``
    #: (the messages' stamps) or ``formation file``
    sources: dict[str, str] = field(default_factory=dict)
    #: where the bag and the formation file disagree, one sentence each
    notes: tuple[str, ...] = ()

    @property
    def realtime(self) -> bool:
        return "realtime" in self.mode


def run_settings(run: RunData) -> RunSettings:
    """Mode, control rate, ground-truth rate and duration of a recorded run.

    Each setting is the bag's where it says what was run (custom_data ``mode``, ``control_rate``,
    ``duration``: the simulator's own bag, ``formation-record --meta``), else the recording's
    (the control rate from the velocity stamps; the duration from the last ground-truth stamp when
    it runs past the formation file's), else the formation file's. The duration never ends before
    the recorded ground truth: a run that went on longer than the bag or the file says is checked
    (and its samples expected) to its end, and a bag that ends before it is missing data, never a
    shorter PASS. Disagreements with the formation file are listed in ``notes``.
    """
    spec, stated, file = run.spec, run.stated, run.spec.simulation
    gt = run.ground_truth
    sources: dict[str, str] = {}
    notes: list[str] = []
    gt_rate = _rate_from_stamps(gt.stamps)
    if stated.control_rate is not None:
        control_rate, sources["control_rate"] = stated.control_rate, "bag"
    else:
        measured = _rate_from_stamps(run.velocity[spec.agent_ids[0]].stamps) or gt_rate
        control_rate, sources["control_rate"] = (
            (measured, "recording") if measured else (file.control_rate, "formation file")
        )
    if abs(control_rate - file.control_rate) > 1e-3 * file.control_rate:  # measured from integer-ns stamps
        said = "the bag says" if sources["control_rate"] == "bag" else "from the recorded stamps"
        notes.append(f"control rate: {control_rate:g} Hz {said}; the formation file says {file.control_rate:g} Hz")
    mode, sources["mode"] = (stated.mode, "bag") if stated.mode is not None else (file.mode, "formation file")
    if mode != file.mode:
        notes.append(f"mode: {mode} as the bag says; the formation file says {file.mode}")
    if stated.duration is not None:
        asked, sources["duration"] = stated.duration, "bag"
    else:
        asked, sources["duration"] = file.duration, "formation file"
    duration: float = asked
    requested: float | None = asked
    rate = gt_rate or control_rate
    tol = 0.5 / rate  # half a sample: the stamps are those of steps k / rate
    end = m.seconds(gt.stamps[-1]) if len(gt) else None
    unsaid = "the bag does not say what was run (no custom_data.duration: formation-record --meta duration=S)"
    if end is not None and end > asked + tol:
        duration, sources["duration"] = end, "recording"
        if stated.duration is not None:
            notes.append(
                f"duration: the ground truth runs to {end:g} s, past the {asked:g} s the bag says was run: "
                f"analysed to {end:g} s"
            )
        else:
            notes.append(
                f"duration: {unsaid}; its ground truth runs to {end:g} s, past the formation file's {asked:g} s: "
                f"analysed to {end:g} s"
            )
        requested = None  # the bag does not say, or says something its data contradicts
    elif stated.duration is not None and abs(asked - file.duration) > tol:
        notes.append(f"duration: {asked:g} s as the bag says; the formation file says {file.duration:g} s")
    elif stated.duration is None and end is not None and end < asked - tol:
        notes.append(
            f"duration: {unsaid}; its ground truth ends at {end:g} s of the formation file's {asked:g} s: "
            "the rest is missing data"
        )
    return RunSettings(mode, control_rate, rate, duration, gt_rate, requested, sources, tuple(notes))


def log_times_are_wall(run: RunData) -> bool:
    """True if the bag's log times are receive times (realtime runs, ``formation-record --log-time
    receive``); False if they are simulation time (lockstep): then they say nothing of wall time."""
    counts = _recorder_counts(run.custom_data)
    if counts and counts.get("log_time") in ("receive", "sim"):
        return bool(counts["log_time"] == "receive")
    return "realtime" in (run.custom_data.get("mode") or run.spec.simulation.mode)


def run_wall_time(run: RunData) -> float | None:
    """The run's wall time [s]: noted by its writer in the bag (``wall_time``), else the span of
    receive log times, else None (a lockstep bag's log times are simulation time)."""
    try:
        return float(run.custom_data["wall_time"])
    except (KeyError, ValueError):
        pass
    if log_times_are_wall(run):
        return (run.last_log - run.first_log) / m.NS_PER_S
    return None


class _StepReplay:
    """Feeds a recorded run to a :class:`RunRecorder` sample by sample (see the module docstring)."""

    def __init__(self, run: RunData, settings: RunSettings, recorder: RunRecorder, reruns: dict[str, AgentRerun]):
        self.run, self.settings, self.recorder, self.reruns = run, settings, recorder, reruns
        self.ids = list(run.spec.agent_ids)
        self.rerun_stamps = {a: array("q", r.stamps.tolist()) for a, r in reruns.items()}
        self.substituted: dict[str, int] = {}
        gt_set = set(run.ground_truth.stamps)
        # control steps without a ground-truth sample (ground truth recorded below the control rate):
        # their velocity margins, faults and wrench peaks are still known from the re-run and the bag
        self.between = sorted({int(s) for r in reruns.values() for s in r.stamps} - gt_set)
        self._between_pos = 0
        self._held: dict[str, tuple[list[int], list[int]]] = {}
        if settings.realtime:
            for a in self.ids:
                w = run.wrench[a]
                order = sorted(range(len(w)), key=lambda k: (w.log_times[k], w.stamps[k]))
                self._held[a] = ([w.log_times[k] for k in order], order)

    def run_all(self) -> None:
        """Every ground-truth sample, and the control steps between them (lockstep)."""
        gt = self.run.ground_truth
        for kk, stamp in enumerate(gt.stamps):
            self.steps_between(stamp)
            self.sample(kk, stamp)
        self.steps_between(gt.stamps[-1] + 1 if len(gt) else None)  # not past the last sample: the run's end

    def rerun_step(self, a: str, stamp: int) -> tuple[int, bool] | None:
        """(index, exact) of agent a's re-run step for ``stamp``: the step itself, else the latest before."""
        stamps = self.rerun_stamps.get(a)
        if stamps is None:
            return None
        k = bisect.bisect_right(stamps, stamp) - 1
        return None if k < 0 else (k, stamps[k] == stamp)

    def count_fault(self, t: float, a: str, k: int) -> bool:
        """Count re-run step k's fault; True if its margins are known (no measurement missing in the bag)."""
        r = self.reruns[a]
        if r.level[k] == ERROR:
            self.recorder.fault(t, "controller", a, r.messages.get(k, ""))
        if r.faults[k] is not None:
            self.recorder.fault(t, "measurement", a, r.faults[k] or "")
            return False
        return True

    def steps_between(self, until: int | None) -> None:
        """The control steps before ``until`` (ns) that have no ground-truth sample (lockstep only)."""
        while self._between_pos < len(self.between) and (until is None or self.between[self._between_pos] < until):
            step = self.between[self._between_pos]
            self._between_pos += 1
            if self.settings.realtime:
                continue
            t_s = m.seconds(step)
            margin_v = np.full((len(self.ids), 6), math.inf)
            rec = self.recorder
            for i, a in enumerate(self.ids):
                found = self.rerun_step(a, step)
                if found is None or not found[1]:
                    continue
                k = found[0]
                w = self.recorded_wrench(a, step) or self.reruns[a].rerun[k].tolist()
                rec.peak_force[i] = max(rec.peak_force[i], math.sqrt(sum(x * x for x in w[:3])))
                rec.peak_torque[i] = max(rec.peak_torque[i], math.sqrt(sum(x * x for x in w[3:])))
                if self.count_fault(t_s, a, k):
                    margin_v[i] = self.reruns[a].margin_v[k]
            rec.update_velocity(t_s, margin_v)

    def recorded_wrench(self, a: str, stamp: int) -> list[float] | None:
        series = self.run.wrench[a]
        k = series.exactly_at(stamp)
        return None if k is None else series.value(k)

    def held_wrench(self, a: str, kk: int) -> list[float]:
        """Realtime: the latest wrench received before ground-truth sample kk+1, zero if older than
        ``command_timeout`` (the simulator's rule, approximated with the recorder's receive order)."""
        gt, run = self.run.ground_truth, self.run
        nxt = gt.log_times[kk + 1] if kk + 1 < len(gt) else run.last_log + 1
        log_times, order = self._held[a]
        j = bisect.bisect_left(log_times, nxt) - 1
        if j < 0:
            return [0.0] * 6
        w = run.wrench[a]
        timeout_ns = round(run.spec.simulation.command_timeout * m.NS_PER_S)
        return w.value(order[j]) if gt.stamps[kk] - w.stamps[order[j]] <= timeout_ns else [0.0] * 6

    def applied_wrench(self, a: str, stamp: int, found: tuple[int, bool] | None) -> list[float]:
        """Lockstep: the wrench agent a sent for ``stamp``; else the re-run's (not in the bag: the
        recorder matched the agent late; it equals the agent's on every recorded step); else the latest."""
        w = self.recorded_wrench(a, stamp)
        if w is None and found is not None and found[1] and self.reruns[a].faults[found[0]] is None:
            w = self.reruns[a].rerun[found[0]].tolist()
            self.substituted[a] = self.substituted.get(a, 0) + 1
        if w is None:
            series = self.run.wrench[a]
            k = series.latest_at(stamp)
            w = None if k is None else series.value(k)
        return w or [0.0] * 6

    def sample(self, kk: int, stamp: int) -> None:
        """Ground-truth sample kk (stamp ns) with the agents' wrenches, twists and velocity margins."""
        t = m.seconds(stamp)
        found = {a: self.rerun_step(a, stamp) for a in self.ids}
        if self.settings.realtime:
            u = np.array([self.held_wrench(a, kk) for a in self.ids])
        else:
            u = np.array([self.applied_wrench(a, stamp, found[a]) for a in self.ids])
        v = []
        for a in self.ids:
            series = self.run.velocity[a]
            k = series.latest_at(stamp)
            v.append((None if k is None else series.value(k)) or [0.0] * 6)
        margin_v = None
        if self.reruns:
            # a step whose measurements are missing from the bag has unknown margins (inf), not −1
            margin_v = np.full((len(self.ids), 6), math.inf)
            for i, a in enumerate(self.ids):
                f = found[a]
                if f is None:
                    continue
                k, exact = f
                if exact and self.count_fault(t, a, k):
                    margin_v[i] = self.reruns[a].margin_v[k]
                elif not exact and self.reruns[a].faults[k] is None:
                    margin_v[i] = self.reruns[a].margin_v[k]  # the latest step before this sample
        p_list, R_list = self.run.ground_truth.value(kk)
        self.recorder.add(t, np.array(p_list), np.array(R_list), np.array(v), u, margin_v)


def run_stopped(custom_data: dict[str, str]) -> Incomplete | None:
    """Why the recorded run stopped before its end, as its simulator wrote it into the bag
    (:data:`formation_bag.contract.KEY_RUN_STOPPED`), or None (it did not say)."""
    text = custom_data.get(KEY_RUN_STOPPED)
    if not text:
        return None
    try:
        said = json.loads(text)
        code = ExitCode(int(said["exit_status"]))
        reason = str(said["reason"])
    except (ValueError, KeyError, TypeError):
        return None  # unreadable: the data's own gaps say enough
    return Incomplete(code, reason)


def recorded_links(custom_data: dict[str, str]) -> LinkReport | None:
    """The link model's statistics the simulator wrote into the bag (:data:`formation_bag.contract.KEY_LINKS`:
    counted at every control step, which a bag's messages cannot show), or None."""
    text = custom_data.get(KEY_LINKS)
    if not text:
        return None
    try:
        links = json.loads(text)
    except ValueError:
        return None
    # written by link_summary (JSON of a LinkReport); a bag's custom data is only read back, never checked
    return cast(LinkReport, links) if isinstance(links, dict) else None


def analyze_run(
    run: RunData,
    *,
    velocity_margins: str = "rerun",
    reruns: dict[str, AgentRerun] | None = None,
    prog: str = "formation-analyze",
) -> tuple[RunRecorder, RunSummary, dict[str, AgentRerun]]:
    """Check every funnel on a decoded run; returns (recorder, summary, re-runs)."""
    if velocity_margins not in VELOCITY_MARGIN_MODES:
        raise ValueError(f"velocity_margins {velocity_margins!r} is not one of {VELOCITY_MARGIN_MODES}")
    started = time.perf_counter()
    settings = run_settings(run)
    record_every = max(1, round(settings.gt_rate / run.spec.simulation.record_rate))
    recorder = RunRecorder(run.spec, record_every=record_every, mode=settings.mode, control_rate=settings.control_rate)
    if velocity_margins == "rerun" and reruns is None:
        reruns = rerun_all(run, check_age=False, prog=prog)
    reruns = reruns or {}
    replay = _StepReplay(run, settings, recorder, reruns)
    replay.run_all()
    missing = missing_data(
        run,
        settings.control_rate,
        settings.gt_rate,
        settings.duration,
        _recorder_counts(run.custom_data),
        wrenches=not settings.realtime,
    )
    incomplete = Incomplete(ExitCode.INCOMPLETE, "data missing: " + "; ".join(missing)) if missing else None
    stopped = run_stopped(run.custom_data)
    if stopped is not None and incomplete is not None:  # the run says why its data ends: that first
        incomplete = Incomplete(stopped.code, f"the run stopped: {stopped.reason}; {incomplete.reason}")
    bag_info = bag_report(run, settings, missing, replay, velocity_margins)
    bag_info["analysis_time"] = time.perf_counter() - started
    recorder.links = recorded_links(run.custom_data)
    summary = recorder.summary(
        wall_time=run_wall_time(run),
        requested_duration=settings.requested_duration,
        incomplete=incomplete,
        extra={"source": "bag", "bag": bag_info},
    )
    return recorder, summary, reruns


def bag_report(
    run: RunData, settings: RunSettings, missing: list[str], replay: _StepReplay, velocity_margins: str
) -> BagReport:
    """The summary's ``bag`` entry: what the bag held and lacked, and how the re-runs compared."""
    gt = run.ground_truth
    gaps = stamp_gaps(gt.stamps, settings.gt_rate, settings.duration)
    return {
        "path": str(run.path),
        "recovered_without_metadata": run.recovered,
        "repaired": run.custom_data.get(KEY_REPAIRED),
        "lost": run.lost,
        "truncated": bool(missing),
        "ground_truth_samples": len(gt),
        "ground_truth_expected": round(settings.duration * settings.gt_rate) + 1,
        "settings": {
            "mode": settings.mode,
            "control_rate": settings.control_rate,
            "duration": settings.duration,
            "from": settings.sources,
            "formation_file": {
                "mode": run.spec.simulation.mode,
                "control_rate": run.spec.simulation.control_rate,
                "duration": run.spec.simulation.duration,
            },
            "notes": list(settings.notes),
        },
        "ground_truth_gaps": len(gaps),
        "ground_truth_missing": [[m.seconds(lo), m.seconds(hi)] for lo, hi in gaps],
        "missing": missing,
        "ground_truth_rate": settings.gt_rate_measured,
        "steps_between_ground_truth": 0 if settings.realtime else len(replay.between),
        "topics": run.topic_counts,
        "log_time": "receive" if log_times_are_wall(run) else "sim",
        "velocity_margins": velocity_margins,
        "wrenches_from_rerun": replay.substituted,
        "recorder_counts": _recorder_counts(run.custom_data),
        "rerun": {
            a: {"equal": r.first_difference(None) is None, "max_abs_diff": r.max_abs_diff, "compared": r.compared}
            for a, r in replay.reruns.items()
        },
    }


def stamp_gaps(stamps: Sequence[int], rate: float, duration: float) -> list[tuple[int, int]]:
    """Missing stretches [first missing, last missing] (ns) of a series due every 1/rate s over [0, duration]."""
    step = m.NS_PER_S / rate
    have = sorted({round(s / step) for s in stamps})
    last = round(duration * rate)
    gaps = []
    prev = -1
    for k in [*have, last + 1]:
        if k > prev + 1 and prev + 1 <= last:
            gaps.append((round((prev + 1) * step), round(min(k - 1, last) * step)))
        prev = max(prev, k)
    return gaps


def missing_data(
    run: RunData,
    control_rate: float,
    gt_rate: float,
    duration: float,
    counts: dict[str, Any] | None,
    *,
    wrenches: bool = True,
) -> list[str]:
    """What the bag lacks, one phrase per topic: lost segments, missing steps (with their times)
    of the ground truth, velocities and (lockstep: one per step) wrenches, and messages the
    recorder counted as missed."""
    out = [f"lost {x}" for x in run.lost]
    if run.custom_data.get(KEY_REPAIRED):  # formation-bag repair salvaged what a killed writer left
        out.append(f"writer stopped, bag repaired: {run.custom_data[KEY_REPAIRED]}")

    def describe(name: str, gaps: list[tuple[int, int]], rate: float) -> None:
        if gaps:
            n = sum(round((hi - lo) * rate / m.NS_PER_S) + 1 for lo, hi in gaps)
            spans = ", ".join(f"{m.seconds(lo):.4f}-{m.seconds(hi):.4f} s" for lo, hi in gaps[:3])
            more = f" and {len(gaps) - 3} more gaps" if len(gaps) > 3 else ""
            out.append(f"{name}: {n} steps missing ({spans}{more})")

    describe("ground truth", stamp_gaps(run.ground_truth.stamps, gt_rate, duration), gt_rate)
    for a in run.spec.agent_ids:
        describe(f"agent {a} velocity", stamp_gaps(run.velocity[a].stamps, control_rate, duration), control_rate)
        if wrenches:
            describe(f"agent {a} wrench", stamp_gaps(run.wrench[a].stamps, control_rate, duration), control_rate)
    if counts:
        for topic, n in sorted(counts.get("missing", {}).items()):
            if not topic.endswith(("/velocity", "/wrench", "/ground_truth")):
                out.append(f"{topic}: {n} messages published but not recorded")
        if counts.get("missed_start"):
            out.append(f"recorder: {counts['missed_start']}")
    return out


def _recorder_counts(custom: dict[str, str]) -> dict[str, Any] | None:
    """The recorder's counts, and per topic how many messages its publisher sent that are not in the bag."""
    try:
        counts = json.loads(custom["recorder_counts"])
    except (KeyError, ValueError):
        return None
    total = counts.get("published_total") or {}
    counts["missing"] = {
        t: n - counts["written"].get(t, 0)
        for t, n in total.items()
        if n is not None and n > counts["written"].get(t, 0) and not counts.get("decimate")
    }
    return counts


# -- ages -----------------------------------------------------------------------------------------


def _stats(x: list[float]) -> dict[str, float | int | None]:
    if not x:
        return {"count": 0, "mean": None, "median": None, "p95": None, "max": None}
    a = np.array(x)
    return {
        "count": int(a.size),
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
    }


def message_ages(run: RunData) -> dict[str, Any]:
    """Age of measurements and wrenches per edge link and agent (sim time and wall time, seconds).

    Only where the log times are receive times: a lockstep bag's log times are the simulation time
    of each message (its stamp), so there ages would be zero or negative by construction; its
    ``ages.json`` says so and holds no ages.
    """
    if not log_times_are_wall(run):
        return {
            "log_time": "sim",
            "note": "log times are simulation time (lockstep): message ages are not measured in this bag",
            "clock_messages": len(run.clock),
        }
    clock = run.clock
    clock_logs = sorted(zip(clock.log_times, clock.stamps))
    c_log = [c[0] for c in clock_logs]
    c_val = [c[1] for c in clock_logs]
    first_announce: dict[int, int] = {}
    for lg, val in clock_logs:
        first_announce.setdefault(val, lg)

    def ages(series: Series) -> dict[str, Any]:
        sim, wall = [], []
        for stamp, lg in zip(series.stamps, series.log_times):
            k = bisect.bisect_right(c_log, lg) - 1
            if k >= 0:
                sim.append((c_val[k] - stamp) / m.NS_PER_S)
            a = first_announce.get(stamp)
            if a is not None:
                wall.append((lg - a) / m.NS_PER_S)
        return {"sim_age": _stats(sim), "wall_latency": _stats(wall)}

    out: dict[str, Any] = {
        "log_time": "receive",
        "clock_messages": len(clock),
        "relative_pose": {f"{i}->{j}": ages(s) for (i, j), s in sorted(run.relative_pose.items())},
        "velocity": {a: ages(s) for a, s in run.velocity.items()},
        "wrench": {},
        "ground_truth": ages(run.ground_truth),
    }
    for a, s in run.wrench.items():
        entry = ages(s)
        vlog = dict(zip(run.velocity[a].stamps, run.velocity[a].log_times))
        entry["response_wall"] = _stats(
            [(lg - vlog[st]) / m.NS_PER_S for st, lg in zip(s.stamps, s.log_times) if st in vlog]
        )
        out["wrench"][a] = entry
    return out


# -- outputs ------------------------------------------------------------------------------------

#: What formation-analyze writes besides the outputs of every run (formation_sim.core.recorder): a
#: ``--force`` into an earlier analysis removes them first (formation_sim.preflight.prepare_out_dir).
ANALYSIS_OUTPUTS = ("ages.json", "errors.csv", "inputs.csv", "positions.csv", "ages.csv")


def write_csv(out: Path, recorder: RunRecorder, ages: dict[str, Any]) -> list[Path]:
    """errors.csv, inputs.csv, positions.csv (the decimated trajectory) and ages.csv."""
    arr = recorder.arrays()
    spec = recorder.spec
    names = [e.name for e in spec.edges]
    ids = list(spec.agent_ids)
    t = arr["t"]
    paths = []

    def write(name: str, header: list[str], rows: Any) -> None:
        path = out / name
        with path.open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(header)
            w.writerows(rows)
        paths.append(path)

    if t.size:
        K, N = len(names), len(ids)
        write(
            "errors.csv",
            ["t"]
            + [f"e_{n}" for n in names]
            + [f"psi_{n}" for n in names]
            + [f"rho_e_{n}" for n in names]
            + [f"rho_psi_{n}" for n in names],
            (
                [repr(float(t[k]))]
                + [
                    repr(float(x))
                    for x in np.concatenate([arr["e"][k], arr["psi"][k], arr["rho_e"][k], arr["rho_psi"][k]])
                ]
                for k in range(t.size)
            ),
        )
        comps = ("fx", "fy", "fz", "tx", "ty", "tz")
        write(
            "inputs.csv",
            ["t"] + [f"{c}_{a}" for a in ids for c in comps],
            ([repr(float(t[k]))] + [repr(float(x)) for x in arr["u"][k].reshape(N * 6)] for k in range(t.size)),
        )
        write(
            "positions.csv",
            ["t"] + [f"{c}_{a}" for a in ids for c in ("x", "y", "z")],
            ([repr(float(t[k]))] + [repr(float(x)) for x in arr["p"][k].reshape(N * 3)] for k in range(t.size)),
        )
        del K
    rows = []
    for kind in ("relative_pose", "velocity", "wrench"):
        for key, entry in ages.get(kind, {}).items():
            for measure in ("sim_age", "wall_latency", "response_wall"):
                if measure in entry:
                    s = entry[measure]
                    rows.append([kind, key, measure, s["count"], s["mean"], s["median"], s["p95"], s["max"]])
    write("ages.csv", ["topic_kind", "link_or_agent", "measure", "count", "mean_s", "median_s", "p95_s", "max_s"], rows)
    return paths


@guarded("formation-analyze")
def main(argv: list[str] | None = None) -> int:
    args = analyze_parser().parse_args(argv)
    started = time.perf_counter()
    bag = args.bag.resolve()
    out = args.out or bag.parent / f"{bag.stem if bag.is_file() else bag.name}-analysis"
    try:
        prepare_out_dir(out, args.force, ANALYSIS_OUTPUTS)
        run = load_run(args.bag, formation=args.formation, namespace=args.namespace, prog="formation-analyze")
    except (BagError, FormationError, FileNotFoundError) as exc:
        print(f"formation-analyze: {exc}", file=sys.stderr)
        return 2
    for lost in run.lost:
        print(f"formation-analyze: warning: lost {lost}", file=sys.stderr)
    if run.recovered:
        print("formation-analyze: warning: no usable metadata.yaml; read the segment files directly", file=sys.stderr)
    recorder, summary, _ = analyze_run(run, velocity_margins=args.velocity_margins)
    ages = message_ages(run)
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "ages.json", ages)
        write_csv(out, recorder, ages)
        write_outputs(out, recorder, summary, plots=not args.no_plots)
    except OSError as exc:
        print(f"formation-analyze: INCOMPLETE: could not write {out}: {exc}", file=sys.stderr)
        return ExitCode.INCOMPLETE
    if args.animate:
        report_animation(out, recorder.spec, recorder.arrays())
    print(format_summary(summary))
    b = summary["bag"]
    print(
        f"bag: {b['ground_truth_samples']} ground-truth samples of {b['ground_truth_expected']} expected over "
        f"{b['settings']['duration']:g} s (duration from the {b['settings']['from']['duration']}), "
        f"{b['ground_truth_gaps']} gaps{', TRUNCATED' if b['truncated'] else ''}; "
        f"analysed in {time.perf_counter() - started:.2f} s"
    )
    for item in b["settings"]["notes"]:
        print(f"  note: {item}")
    for item in b["missing"]:
        print(f"  missing: {item}")
    print(f"outputs in {out}/ (exit status {summary['exit_status']})")
    return summary["exit_status"]


if __name__ == "__main__":
    sys.exit(main())
