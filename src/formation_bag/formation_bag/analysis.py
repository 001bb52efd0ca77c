"""Offline analysis of a recorded run (no ROS): ``formation-analyze BAG --out DIR``.

From ``/formation/ground_truth`` it recomputes every e_k and ψ_k and checks every funnel with
the same :class:`formation_sim.core.recorder.RunRecorder` the headless runner and the simulator use,
so the outputs have the format of docs/outputs.md (summary.json, trajectory.npz, errors.png,
orientation_errors.png, inputs.png). Per ground-truth sample (stamp t_k) it uses:

- u: the wrench each agent published with stamp t_k; if the bag misses it (a recorder that matched
  an agent late), the re-run's wrench for t_k (equal to the agent's on every recorded step), else
  the latest earlier one (zero-order hold);
  realtime runs: the latest wrench received before the next sample, zero if older than
  ``command_timeout`` (the simulator's rule, with the recorder's receive order);
- ṽ (trajectory ``v``): the recorded noisy twist (the bag has no true velocity);
- the velocity-funnel margins and controller levels: from re-running each agent's controller on
  its recorded measurements (:mod:`formation_bag.rerun`; exactly what the agent computed), with
  the same fault order as the headless runner (missing measurement, funnels, controller ERROR).

It also writes CSV exports (errors.csv, inputs.csv, positions.csv), and ``ages.json``/``ages.csv``:
the age of every measurement and wrench per edge and agent, in simulation time (latest /clock at
receipt − header stamp) and in wall time (receipt − receipt of the /clock that announced the
stamp), and each agent's response time (wrench receipt − receipt of its velocity with that stamp).
A bag truncated by a killed recorder, or missing messages, is analysed as far as it goes: the
verdict is then INCOMPLETE with what is missing listed (``bag.missing``), never FAIL for lack of
data; a violation seen in the data present is still FAIL.
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from formation_agent.controller import ERROR
from formation_bag import messages as m
from formation_bag.dataset import RunData, Series, load_run
from formation_bag.parsers import VELOCITY_MARGIN_MODES, analyze_parser
from formation_bag.rerun import AgentRerun, rerun_all
from formation_msgs_py.errors import BagError, FormationError
from formation_msgs_py.faults import write_json
from formation_msgs_py.outcome import ExitCode, Incomplete, guarded
from formation_sim.core.preflight import prepare_out_dir
from formation_sim.core.recorder import RunRecorder
from formation_sim.views.outputs import format_summary, report_animation, write_outputs


def _rate_from_stamps(stamps: list[int]) -> float | None:
    if len(stamps) < 2:
        return None
    d = np.diff(np.array(stamps, dtype=np.int64))
    d = d[d > 0]
    if not d.size:
        return None
    return m.NS_PER_S / float(np.median(d))


def analyze_run(
    run: RunData,
    *,
    velocity_margins: str = "rerun",
    reruns: dict[str, AgentRerun] | None = None,
) -> tuple[RunRecorder, dict[str, Any], dict[str, AgentRerun]]:
    """Check every funnel on a decoded run; returns (recorder, summary, re-runs)."""
    if velocity_margins not in VELOCITY_MARGIN_MODES:
        raise ValueError(f"velocity_margins {velocity_margins!r} is not one of {VELOCITY_MARGIN_MODES}")
    started = time.perf_counter()
    spec = run.spec
    ids = list(spec.agent_ids)
    gt = run.ground_truth
    gt_rate = _rate_from_stamps(gt.stamps)
    custom = run.custom_data
    try:
        control_rate = float(custom["control_rate"])
    except (KeyError, ValueError):
        control_rate = _rate_from_stamps(run.velocity[ids[0]].stamps) or gt_rate or spec.simulation.control_rate
    mode = custom.get("mode") or spec.simulation.mode
    record_every = max(1, round((gt_rate or control_rate) / spec.simulation.record_rate))
    recorder = RunRecorder(spec, record_every=record_every, mode=mode, control_rate=control_rate)

    if velocity_margins == "rerun" and reruns is None:
        reruns = rerun_all(run, check_age=False)
    reruns = reruns or {}
    rerun_index = {a: {int(s): k for k, s in enumerate(r.stamps)} for a, r in reruns.items()}

    def at(series: Series, stamp: int) -> Any:
        k = series.latest_at(stamp)
        return None if k is None else series.values[k]

    wrench_exact = {a: dict(zip(run.wrench[a].stamps, run.wrench[a].values)) for a in ids}
    zeros6 = [0.0] * 6
    realtime = "realtime" in mode
    substituted: dict[str, int] = {}
    # realtime: the simulator applies, over the period after sample k, the latest wrench it has
    # received when it ticks (just before it publishes sample k+1), zero if older than
    # command_timeout. Approximated with the recorder's receive order.
    by_log = {a: sorted(zip(run.wrench[a].log_times, run.wrench[a].stamps, run.wrench[a].values)) for a in ids}
    by_log_t = {a: [x[0] for x in rows] for a, rows in by_log.items()}
    timeout_ns = round(spec.simulation.command_timeout * m.NS_PER_S)

    def held(a: str, k: int) -> list[float]:
        nxt = gt.log_times[k + 1] if k + 1 < len(gt) else run.last_log + 1
        j = bisect.bisect_left(by_log_t[a], nxt) - 1
        if j < 0:
            return zeros6
        _, st, val = by_log[a][j]
        return val if gt.stamps[k] - st <= timeout_ns else zeros6

    # control steps without a ground-truth sample (ground truth recorded below the control rate):
    # their velocity margins, faults and wrench peaks are still known from the re-run and the bag
    gt_set = set(gt.stamps)
    between = sorted({int(s) for r in reruns.values() for s in r.stamps} - gt_set) if reruns else []
    between_pos = 0

    def between_steps(until: int | None) -> None:
        nonlocal between_pos
        while between_pos < len(between) and (until is None or between[between_pos] < until):
            step = between[between_pos]
            between_pos += 1
            if not lockstep_checks:
                continue
            t_s = m.seconds(step)
            margin_v = np.full((len(ids), 6), math.inf)
            for i, a in enumerate(ids):
                k = rerun_index[a].get(step) if a in reruns else None
                if k is None:
                    continue
                out, fault = reruns[a].outputs[k], reruns[a].faults[k]
                w = wrench_exact[a].get(step) or list(out.wrench)
                recorder.peak_force[i] = max(recorder.peak_force[i], math.sqrt(sum(x * x for x in w[:3])))
                recorder.peak_torque[i] = max(recorder.peak_torque[i], math.sqrt(sum(x * x for x in w[3:])))
                if _count_fault(recorder, t_s, a, out, fault):
                    margin_v[i] = out.margin_v
            recorder.update_velocity(t_s, margin_v)

    lockstep_checks = not realtime
    for kk, (stamp, (p_list, R_list)) in enumerate(zip(gt.stamps, gt.values)):
        between_steps(stamp)
        t = m.seconds(stamp)
        outs = []
        if reruns:
            for a in ids:
                r = reruns.get(a)
                k = None if r is None else rerun_index[a].get(stamp)
                if k is None and r is not None:
                    j = bisect.bisect_right(r.stamps, stamp) - 1
                    k = j if j >= 0 else None
                outs.append(None if k is None or r is None else (r.outputs[k], r.faults[k], int(r.stamps[k]) == stamp))
        if realtime:
            u = np.array([held(a, kk) for a in ids])
        else:
            rows = []
            for a, o in zip(ids, outs or [None] * len(ids)):
                w = wrench_exact[a].get(stamp)
                if w is None and o is not None and o[2] and o[1] is None:
                    # not in the bag (the recorder matched this agent late): the re-run's wrench,
                    # which equals the agent's on every recorded step
                    w = list(o[0].wrench)
                    substituted[a] = substituted.get(a, 0) + 1
                rows.append(w or at(run.wrench[a], stamp) or zeros6)
            u = np.array(rows)
        v = np.array([at(run.velocity[a], stamp) or zeros6 for a in ids])
        margin_v = None
        if reruns:
            # a step whose measurements are missing from the bag has unknown margins (inf), not −1
            margin_v = np.full((len(ids), 6), math.inf)
            for i, (a, o) in enumerate(zip(ids, outs)):
                if o is not None and o[2] and _count_fault(recorder, t, a, o[0], o[1]):
                    margin_v[i] = o[0].margin_v
                elif o is not None and not o[2] and o[1] is None:
                    margin_v[i] = o[0].margin_v  # the latest step before this sample
        recorder.add(t, np.array(p_list), np.array(R_list), v, u, margin_v)
    between_steps(gt.stamps[-1] + 1 if len(gt) else None)  # not past the last sample: the run's end
    wall = (run.last_log - run.first_log) / m.NS_PER_S
    try:
        duration = float(custom["duration"])
    except (KeyError, ValueError):
        duration = spec.simulation.duration  # a recorder started without --meta: the file's duration
    expected = round(duration * (gt_rate or control_rate)) + 1
    gaps = stamp_gaps(gt.stamps, gt_rate or control_rate, duration)
    missing = missing_data(
        run, control_rate, gt_rate or control_rate, duration, _recorder_counts(custom), wrenches=not realtime
    )
    truncated = bool(missing)
    incomplete = Incomplete(ExitCode.INCOMPLETE, "data missing: " + "; ".join(missing)) if missing else None
    bag_info = {
        "path": str(run.path),
        "recovered_without_metadata": run.recovered,
        "lost": run.lost,
        "truncated": truncated,
        "ground_truth_samples": len(gt),
        "ground_truth_expected": expected,
        "ground_truth_gaps": len(gaps),
        "ground_truth_missing": [[m.seconds(lo), m.seconds(hi)] for lo, hi in gaps],
        "missing": missing,
        "ground_truth_rate": gt_rate,
        "steps_between_ground_truth": len(between) if lockstep_checks else 0,
        "topics": run.topic_counts,
        "velocity_margins": velocity_margins,
        "wrenches_from_rerun": substituted,
        "recorder_counts": _recorder_counts(custom),
        "rerun": {
            a: {"equal": r.first_difference(1e-12) is None, "max_abs_diff": r.max_abs_diff, "compared": r.compared}
            for a, r in reruns.items()
        },
        "analysis_time": time.perf_counter() - started,
    }
    summary = recorder.summary(
        wall_time=wall,
        requested_duration=duration,
        incomplete=incomplete,
        extra={"source": "bag", "bag": bag_info},
    )
    return recorder, summary, reruns


def stamp_gaps(stamps: list[int], rate: float, duration: float) -> list[tuple[int, int]]:
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


def _count_fault(recorder: RunRecorder, t: float, agent: str, out: Any, missing: str | None) -> bool:
    """Count a re-run step's fault; True if its margins are known (no measurement missing in the bag)."""
    if out.level == ERROR:
        recorder.fault(t, "controller", agent, out.message)
    if missing is not None:
        recorder.fault(t, "measurement", agent, missing)
        return False
    return True


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
    """Age of measurements and wrenches per edge link and agent (sim time and wall time, seconds)."""
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
#: ``--force`` into an earlier analysis removes them first (formation_sim.core.preflight.prepare_out_dir).
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
        for key, entry in ages[kind].items():
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
        run = load_run(args.bag, formation=args.formation, namespace=args.namespace)
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
        f"bag: {b['ground_truth_samples']} ground-truth samples of {b['ground_truth_expected']} expected, "
        f"{b['ground_truth_gaps']} gaps{', TRUNCATED' if b['truncated'] else ''}; "
        f"analysed in {time.perf_counter() - started:.2f} s"
    )
    for item in b["missing"]:
        print(f"  missing: {item}")
    print(f"outputs in {out}/ (exit status {summary['exit_status']})")
    return summary["exit_status"]


if __name__ == "__main__":
    sys.exit(main())
