"""Controller re-run: feed an agent's recorded measurements to the agent core, offline.

``formation-rerun BAG [--agent ID …] [--override FILE] [--out DIR]``

As the agent node does (formation_agent.synchroniser.StepSynchroniser): for each recorded velocity
message of agent i (stamp t, in stamp order, duplicates answered once), the controller gets ṽ_i
and, per tree neighbour j, the relative pose with the *same* stamp, at time t = stamp_ns / 1e9.
A missing pose, or a measurement older than ``measurement_timeout`` behind both the latest recorded
/clock and the agent's time (its last step computed with a pose: the agent judges stamps against
its measurement stream, /clock only widens the window; formation_msgs_py.measurement_checks), gives a
zero wrench (a fault). The agent computed from exactly these decoded messages, so its wrench
(stamped t) is reproduced bit for bit by the same code form on the same platform, and elsewhere
within the step's round-off tolerance (formation_agent.roundoff, docs/controller.md): the default
comparison. ``--tolerance X`` compares to an absolute X instead. With an override file (gains,
funnels) the report lists where and how much the wrenches change.
"""

from __future__ import annotations

import bisect
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from formation_agent.controller import ERROR, LEVEL_NAMES, MissingMeasurementError
from formation_agent.roundoff import BoundedController
from formation_bag import messages as m
from formation_bag.dataset import RunData, Series, apply_overrides, load_run, spec_from_document
from formation_bag.progress import Progress
from formation_core.errors import BagError, FormationSpecError, OverrideError
from formation_core.formation import FormationSpec, agent_view
from formation_core.verdict import ExitCode, guarded
from formation_sim.offline.parsers import rerun_parser
from formation_sim.preflight import InvalidRunError, check_out_dir


@dataclass
class AgentRerun:
    """One agent's re-run, step by step (one step per recorded velocity message), in arrays: a run
    has ~10⁵ steps per agent, too many for one ControlOutput object each."""

    agent: str
    stamps: np.ndarray  # (T,) int64 ns
    faults: list[str | None]  # neighbours missing at that step ("2,3"), "stale", None if complete
    recorded: np.ndarray  # (T,6), NaN where no wrench with that stamp was recorded
    rerun: np.ndarray  # (T,6): the re-run's wrench (force N, torque N·m, body frame)
    tolerance: np.ndarray  # (T,6): how far another correct computation of that wrench may lie
    margin_v: np.ndarray  # (T,6): the re-run's velocity-funnel margins
    level: np.ndarray  # (T,) int8: the controller's level (formation_agent.controller.LEVEL_NAMES)
    messages: dict[int, str]  # the controller's message at each ERROR step

    @property
    def comparable(self) -> np.ndarray:
        """(T,) bool: the bag holds the agent's wrench and every measurement it answered."""
        complete = np.array([f is None or f == "stale" for f in self.faults], dtype=bool)
        return ~np.isnan(self.recorded[:, 0]) & complete

    @property
    def compared(self) -> int:
        return int(np.sum(self.comparable))

    @property
    def measurements_missing(self) -> int:
        """Steps the bag lacks a measurement of (re-run not comparable there)."""
        return sum(f is not None and f != "stale" for f in self.faults)

    @property
    def max_abs_diff(self) -> float:
        """The largest difference of one wrench component over the compared steps."""
        d = np.abs(self.recorded - self.rerun)[self.comparable]
        return float(d.max()) if d.size else 0.0

    def differences(self, tol: float | None) -> np.ndarray:
        """(T,) bool: the compared steps whose wrench differs by more than ``tol`` in a component (None: by
        more than that step's round-off tolerance); missing data is never a difference."""
        d = np.abs(self.recorded - self.rerun)
        beyond = d > (self.tolerance if tol is None else tol)
        return beyond.any(axis=1) & self.comparable

    def first_difference(self, tol: float | None) -> int | None:
        bad = np.nonzero(self.differences(tol))[0]
        return int(bad[0]) if bad.size else None

    def report(self, tol: float | None) -> dict[str, Any]:
        """Differences per component (the norm of the tolerance): overall, of the force and of the torque."""
        k = self.first_difference(tol)
        d = np.abs(self.recorded - self.rerun)
        valid = self.comparable
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(d == 0.0, 0.0, d / self.tolerance)  # a fault's exact zero wrench: 0 of 0
        return {
            "steps": len(self.stamps),
            "compared": self.compared,
            "missing_recorded_wrench": int(np.sum(np.isnan(self.recorded[:, 0]))),
            "measurements_missing": self.measurements_missing,
            "equal": k is None,
            "bit_for_bit": int(np.sum(valid & (d == 0.0).all(axis=1))),
            "max_abs_diff": self.max_abs_diff,
            "max_force_diff": float(d[valid, :3].max()) if valid.any() else 0.0,
            "max_torque_diff": float(d[valid, 3:].max()) if valid.any() else 0.0,
            "largest_ratio_to_round_off": float(ratio[valid].max()) if valid.any() else 0.0,
            "rms_diff": float(np.sqrt(np.nanmean(d[valid] ** 2))) if valid.any() else 0.0,
            "first_difference": None
            if k is None
            else {
                "t": m.seconds(int(self.stamps[k])),
                "recorded": self.recorded[k].tolist(),
                "rerun": self.rerun[k].tolist(),
                "round_off_tolerance": self.tolerance[k].tolist(),
            },
            "steps_differing": int(np.sum(self.differences(tol))),
            "faults": sum(f is not None for f in self.faults),
            "levels": {name: int(np.sum(self.level == i)) for i, name in enumerate(LEVEL_NAMES)},
            "min_margin_v_rerun": float(self.margin_v.min()) if self.margin_v.size else math.inf,
        }


def rerun_agent(
    run: RunData, agent_id: str, spec: FormationSpec | None = None, *, check_age: bool = True
) -> AgentRerun:
    """Re-run agent ``agent_id``'s controller on its recorded measurements (``spec`` may differ).

    ``check_age=False`` skips the agent's staleness check (the simulator's shadow controllers,
    which the analysis mirrors, compute on every published step).
    """
    spec = spec or run.spec
    view = agent_view(spec, agent_id)
    ctrl = BoundedController(view)
    timeout_ns = round(view.controller.measurement_timeout * m.NS_PER_S)
    vel = run.velocity[agent_id]
    empty = Series(7)
    rel = {j: run.relative_pose.get((agent_id, j), empty) for j in view.neighbours}
    clock = sorted(zip(run.clock.log_times, run.clock.stamps))
    clock_logs = [c[0] for c in clock]
    wr = run.wrench[agent_id]
    T = len(vel)
    stamps = np.empty(T, dtype=np.int64)
    recorded = np.full((T, 6), math.nan)
    rerun = np.empty((T, 6))
    tolerance = np.empty((T, 6))
    margin_v = np.empty((T, 6))
    level = np.empty(T, dtype=np.int8)
    faults: list[str | None] = []
    messages: dict[int, str] = {}
    n = 0
    last = None
    confirmed: int | None = None  # the agent's time: its last step computed with a pose [ns]
    for idx, (stamp, log_time) in enumerate(zip(vel.stamps, vel.log_times)):
        if stamp == last:
            continue  # a re-sent step: the agent answers it once
        last = stamp
        t = m.seconds(stamp)
        poses = {j: series.value(k) for j, series in rel.items() if (k := series.exactly_at(stamp)) is not None}
        c = bisect.bisect_right(clock_logs, log_time) - 1
        clock_ns = clock[c][1] if c >= 0 else 0
        try:
            behind = clock_ns if confirmed is None else min(clock_ns, confirmed)
            if check_age and clock_ns and behind - stamp > timeout_ns:
                age = (behind - stamp) / m.NS_PER_S
                out = ctrl.fault_output(t, f"measurement too old: {age:.3f} s behind the agent's time")
                fault = "stale"
            else:
                out = ctrl.compute(t, poses, vel.value(idx))
                fault = None
        except MissingMeasurementError as exc:
            out = ctrl.fault_output(t, str(exc))
            fault = ",".join(exc.neighbours)
        if poses and fault != "stale" and (confirmed is None or stamp > confirmed):
            confirmed = stamp  # answered from the velocity and at least one pose
        stamps[n] = stamp
        rerun[n] = out.wrench
        tolerance[n] = ctrl.wrench_tolerance
        margin_v[n] = out.margin_v
        level[n] = out.level
        if out.level == ERROR:
            messages[n] = out.message
        if (k := wr.exactly_at(stamp)) is not None:
            recorded[n] = wr.value(k)
        faults.append(fault)
        n += 1
    return AgentRerun(
        agent_id, stamps[:n], faults, recorded[:n], rerun[:n], tolerance[:n], margin_v[:n], level[:n], messages
    )


def rerun_all(
    run: RunData,
    agents: list[str] | None = None,
    spec: FormationSpec | None = None,
    *,
    check_age: bool = True,
    prog: str = "formation-rerun",
) -> dict[str, AgentRerun]:
    """Every agent's re-run (or those of ``agents``), with a progress line per agent when it takes a while."""
    spec = spec or run.spec
    ids = agents or list(spec.agent_ids)
    for a in ids:
        spec.agent(a)  # names the bad id
    progress = Progress(prog, "re-running the controllers", len(ids), unit="agents", stride=1)
    out = {}
    for a in ids:
        out[a] = rerun_agent(run, a, spec, check_age=check_age)
        progress.update(len(out))
    progress.finish(len(out))
    return out


def load_override(path: Path) -> dict[str, Any]:
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OverrideError(str(path), f"cannot read: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise OverrideError(str(path), f"not valid YAML: {exc}") from None
    return doc or {}


@guarded("formation-rerun")
def main(argv: list[str] | None = None) -> int:
    args = rerun_parser().parse_args(argv)
    try:
        if args.out is not None:
            check_out_dir(args.out, args.force)  # before the long read: a full or read-only disk, a file
        started = time.perf_counter()
        run = load_run(
            args.bag,
            formation=args.formation,
            namespace=args.namespace,
            need_ground_truth=False,
            prog="formation-rerun",
        )
        spec = run.spec
        if args.override is not None:
            doc = apply_overrides(run.document, load_override(args.override), where=str(args.override))
            spec = spec_from_document(doc, run.spec.source)
        results = rerun_all(run, args.agent, spec, prog="formation-rerun")
    except (BagError, FormationSpecError, InvalidRunError, FileNotFoundError) as exc:
        print(f"formation-rerun: {exc}", file=sys.stderr)
        return 2
    agents = {a: r.report(args.tolerance) for a, r in results.items()}
    report: dict[str, Any] = {
        "bag": str(args.bag),
        "override": None if args.override is None else str(args.override),
        "tolerance": "round-off bound" if args.tolerance is None else args.tolerance,
        "agents": agents,
        "time": time.perf_counter() - started,
    }
    equal = all(r["equal"] for r in agents.values())
    report["equal"] = equal
    for a, rep in agents.items():
        verdict = "equal" if rep["equal"] else "DIFFERENT"
        line = (
            f"agent {a}: {rep['compared']}/{rep['steps']} steps compared ({rep['bit_for_bit']} bit for bit), largest "
            f"component of |Δu| {rep['max_abs_diff']:.3g} (force {rep['max_force_diff']:.3g} N, torque "
            f"{rep['max_torque_diff']:.3g} N·m; {rep['largest_ratio_to_round_off']:.3g} of the round-off tolerance): "
            f"{verdict}"
        )
        if rep["first_difference"] is not None:
            line += f", first at t={rep['first_difference']['t']:.6f} s, {rep['steps_differing']} steps differ"
        if rep["missing_recorded_wrench"]:
            line += f"; {rep['missing_recorded_wrench']} steps without a recorded wrench"
        if rep["measurements_missing"]:
            line += f"; {rep['measurements_missing']} steps with a measurement missing from the bag (not compared)"
        print(line)
    if args.out is not None:
        try:
            args.out.mkdir(parents=True, exist_ok=True)
            # an earlier re-run's report and agents (only those: --out may be a run's own OUT), not
            # to be read as this one's
            for earlier in [args.out / "rerun.json", *args.out.glob("rerun_*.npz")]:
                earlier.unlink(missing_ok=True)
        except OSError as exc:
            print(f"formation-rerun: INCOMPLETE: output directory {args.out}: {exc.strerror or exc}", file=sys.stderr)
            return ExitCode.INCOMPLETE
        (args.out / "rerun.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        for a, r in results.items():
            np.savez(
                args.out / f"rerun_{a}.npz",
                t=r.stamps / m.NS_PER_S,
                recorded=r.recorded,
                rerun=r.rerun,
                round_off_tolerance=r.tolerance,
                margin_v=r.margin_v,
                level=r.level,
            )
        print(f"report in {args.out}/rerun.json")
    incomplete = any(r["missing_recorded_wrench"] or r["measurements_missing"] for r in agents.values())
    if not equal:
        verdict, code = "differ", ExitCode.FAIL
    elif incomplete:
        verdict, code = "reproduced where the bag has the data (INCOMPLETE: data missing)", ExitCode.INCOMPLETE
    else:
        verdict, code = "reproduced", ExitCode.PASS
    within = "each step's round-off bound" if args.tolerance is None else f"{args.tolerance:g}"
    print(f"formation-rerun: wrenches {verdict} (tolerance: {within})")
    return code


if __name__ == "__main__":
    sys.exit(main())
