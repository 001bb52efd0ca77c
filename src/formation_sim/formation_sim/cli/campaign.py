"""Monte Carlo campaigns of headless runs: ``formation-campaign CAMPAIGN.yaml --out DIR``.

A campaign file (:mod:`formation_sim.cli.campaign_file`: its keys, validation and reference) names a
base formation, how many random samples to draw, the control rates to run each at and what varies
between samples (plant, disturbance and noise amplitudes, initial attitudes, link and gain grids).
This module draws the samples and runs them; :mod:`formation_sim.cli.campaign_results` writes what
they found.

Each run is the compiled headless runner (sampled control) with its own plant; the physics rate is
the file's, rounded to a multiple of the control rate. Runs go to a local process pool
(``--workers``, default the cores) or to a Dask distributed cluster (``--scheduler ADDRESS``; the
formation file must be readable at the same path on the workers). Every finished run is appended
to ``DIR/runs.jsonl`` at once, so an interrupted campaign resumes where it stopped. At the end
``DIR`` holds ``runs.csv`` (one row per sample and rate: verdict, first violation, worst margins,
peak wrench), ``summary.json`` (pass rate and its 95 % Wilson interval per control rate) and the
figures ``pass_rate.png`` and ``worst_margin.png``.

``formation-campaign --sweep-rate FILE RATE…`` runs the file's own plant at each rate and prints
the pass/fail table next to the rate each agent needs (:mod:`formation_sim.core.rates`).

Exit status (:mod:`formation_core.verdict`): 0 done, 2 invalid campaign or formation file (naming the
field), 4 an I/O or internal error (the runs finished are kept: a rerun resumes), 130 interrupted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from formation_core.errors import FormationSpecError
from formation_core.verdict import ExitCode, guarded

if TYPE_CHECKING:  # numpy, the loader of formations and the cores: imported where used, not for --help
    from formation_core.formation import FormationSpec, SignalModel
from formation_sim.cli.campaign_file import (
    CONDITIONS,
    Campaign,
    CampaignError,
    checked_number,
    load_campaign,
    reference_markdown,
)
from formation_sim.cli.campaign_results import (
    CampaignRow,
    CampaignSummary,
    condition_table,
    conditions_of,
    row_key,
    write_results,
)


@dataclass(frozen=True)
class Task:
    """One headless run: sample ``sample`` of the campaign at ``control_rate`` under ``condition``."""

    formation: str
    sample: int
    control_rate: float
    duration: float | None
    vary: Mapping[str, Any]
    entropy: int
    spawn_key: tuple[int, ...]
    #: values of :data:`CONDITIONS` (None: the file's)
    condition: tuple[float | None, ...] = (None,) * len(CONDITIONS)
    #: the channels the link values apply to
    apply_to: tuple[str, ...] = ()

    @property
    def key(self) -> tuple[object, ...]:
        return (self.sample, self.control_rate, *self.condition)


# --- the campaign file ---------------------------------------------------------------------------


def tasks(campaign: Campaign) -> list[Task]:
    """Every run, sample-major; sample i's plant is drawn from the i-th child seed, the same at every rate."""
    import numpy as np

    root = np.random.SeedSequence(campaign.seed)
    entropy = root.entropy
    assert isinstance(entropy, int)  # the campaign's seed
    out = []
    apply_to = tuple(campaign.links.get("apply_to", ()))
    for child in root.spawn(campaign.samples):
        i = child.spawn_key[-1]
        for condition in campaign.conditions():
            for rate in campaign.control_rates:
                out.append(
                    Task(
                        str(campaign.formation),
                        i,
                        rate,
                        campaign.duration,
                        campaign.vary,
                        entropy,
                        tuple(child.spawn_key),
                        condition,
                        apply_to,
                    )
                )
    return out


# --- one sample --------------------------------------------------------------------------------


def _scaled_amplitude(model: SignalModel, value: float) -> SignalModel:
    from formation_core.formation import SignalModel

    if model.model != "paper":
        return model
    return SignalModel(model.model, {**model.params, "amplitude": value})


def sample_spec(task: Task) -> FormationSpec:
    """The base formation with sample ``task.sample``'s plant, initial orientations and control rate."""
    import numpy as np

    from formation_core.so3 import exp_so3
    from formation_core.spec import load_formation

    spec = load_formation(task.formation)
    rng = np.random.default_rng(np.random.SeedSequence(task.entropy, spawn_key=task.spawn_key))
    vary = task.vary
    agents = []
    for a in spec.agents:
        d = a.dynamics
        mass = d.mass * rng.uniform(*vary["mass"]) if "mass" in vary else d.mass
        inertia = d.inertia * rng.uniform(*vary["inertia"]) if "inertia" in vary else d.inertia
        dist, noise = d.disturbance, d.velocity_noise
        if "disturbance_amplitude" in vary:
            dist = _scaled_amplitude(dist, rng.uniform(*vary["disturbance_amplitude"]))
        if "noise_amplitude" in vary:
            noise = _scaled_amplitude(noise, rng.uniform(*vary["noise_amplitude"]))
        R = a.R_world_body
        if "initial_rotation" in vary:
            axis = rng.normal(size=3)
            angle = vary["initial_rotation"] * rng.uniform() ** (1 / 3)  # uniform in the ball
            R = R @ exp_so3(axis / np.linalg.norm(axis) * angle)
        dyn = dataclasses.replace(d, mass=mass, inertia=inertia, disturbance=dist, velocity_noise=noise)
        agents.append(dataclasses.replace(a, dynamics=dyn, R_world_body=R))
    spec = dataclasses.replace(spec, agents=tuple(agents))
    spec = _with_condition(spec, task.condition, task.apply_to)
    physics = task.control_rate * max(1, round(spec.simulation.physics_rate / task.control_rate))
    changes: dict[str, Any] = {"control_rate": task.control_rate, "physics_rate": physics}
    changes["record_rate"] = min(spec.simulation.record_rate, task.control_rate)
    if task.duration is not None:
        changes["duration"] = task.duration
    if task.apply_to:  # a link grid: each sample its own losses and jitter (and noise), the same at every condition
        changes["seed"] = spec.simulation.seed + task.sample
    return spec.with_simulation(**changes)


def _with_condition(
    spec: FormationSpec, condition: tuple[float | None, ...], apply_to: tuple[str, ...]
) -> FormationSpec:
    """``spec`` with a run's link values on every agent's links of ``apply_to`` and its gains."""
    from formation_core.formation import EdgeLinks, MeasurementLink, SignalModel, WrenchLink

    delay, loss, jitter, sensor_rate, delta, gamma = condition
    agents = []
    for a in spec.agents:
        c = a.controller
        controller = dataclasses.replace(
            c, delta=c.delta if delta is None else delta, gamma=c.gamma if gamma is None else gamma
        )
        links = a.links
        if delay is not None:
            loss_model = SignalModel("independent", {"probability": loss}) if loss else SignalModel("none", {})
            spread = SignalModel("uniform", {"max": jitter}) if jitter else SignalModel("none", {})
            measured = MeasurementLink(sensor_rate, delay, spread, loss_model)
            links = dataclasses.replace(
                links,
                poses=measured if "poses" in apply_to else links.poses,
                velocity=measured if "velocity" in apply_to else links.velocity,
                wrench=WrenchLink(delay, loss_model) if "wrench" in apply_to else links.wrench,
            )
        agents.append(dataclasses.replace(a, controller=controller, links=links))
    edges = spec.edges
    if delay is not None and "poses" in apply_to:
        edges = tuple(dataclasses.replace(e, links=EdgeLinks(None, None)) for e in spec.edges)
    return dataclasses.replace(spec, agents=tuple(agents), edges=edges)


def run_task(task: Task) -> CampaignRow:
    """One sample's headless run, as a row of ``runs.csv``."""
    from formation_sim.cli.headless import run_headless

    spec = sample_spec(task)
    summary = run_headless(spec, stop_on_violation=True).summary
    fv = summary["first_violation"]
    edges, agents = summary["edges"].values(), summary["agents"].values()

    def worst(values: Iterable[float | None]) -> float | None:
        vals = [v for v in values if v is not None]
        return min(vals) if vals else None

    return {
        "sample": task.sample,
        "control_rate": task.control_rate,
        **conditions_of(task.condition),
        "seed": f"{task.entropy}:{'/'.join(map(str, task.spawn_key))}",
        "verdict": summary["verdict"],  # PASS, FAIL or INCOMPLETE
        "violation_t": None if fv is None else fv["t"],
        "violation_kind": None if fv is None else fv["kind"],
        "violation_where": None if fv is None else fv.get("edge") or fv.get("agent"),
        "violation_channel": None if fv is None else fv["channel"],
        "worst_margin_e": worst(e["min_margin_e"] for e in edges),
        "worst_margin_psi": worst(e["min_margin_psi"] for e in edges),
        "worst_margin_v": worst(a["min_margin_v"] for a in agents),
        "peak_force": max(a["peak_force"] for a in agents),
        "peak_torque": max(a["peak_torque"] for a in agents),
        "wall_time": summary["wall_time"],
    }


# --- running many ------------------------------------------------------------------------------


def _finished(log: Path) -> dict[tuple[object, ...], CampaignRow]:
    """Rows of an earlier (interrupted) campaign in ``log``; a torn last line is ignored."""
    rows: dict[tuple[object, ...], CampaignRow] = {}
    if log.exists():
        for line in log.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            rows[row_key(row)] = row  # a line run_task wrote (a CampaignRow as JSON)
    return rows


def _progress(done: int, total: int, started: float) -> None:
    elapsed = time.perf_counter() - started
    eta = elapsed / done * (total - done) if done else float("nan")
    print(f"\r  {done}/{total} runs  {elapsed:6.1f} s elapsed  ETA {eta:6.1f} s", end="", flush=True)


def run_tasks(todo: list[Task], log: Path, *, workers: int, scheduler: str | None, quiet: bool = False) -> None:
    """Run ``todo`` and append each row to ``log`` as it finishes."""
    started = time.perf_counter()
    torn = log.exists() and log.stat().st_size > 0 and not log.read_bytes().endswith(b"\n")
    with log.open("a", encoding="utf-8") as out:
        if torn:  # a killed writer left half a line: end it, so that it stays one ignored line
            out.write("\n")

        def record(row: CampaignRow, done: int) -> None:
            out.write(json.dumps(row) + "\n")
            out.flush()
            os.fsync(out.fileno())
            if not quiet:
                _progress(done, len(todo), started)

        if scheduler is not None:
            from distributed import Client
            from distributed import as_completed as dask_completed

            with Client(scheduler) as client:
                futures = client.map(run_task, todo, pure=False)
                for done, fut in enumerate(dask_completed(futures), 1):
                    record(fut.result(), done)
        elif workers == 1:
            for done, task in enumerate(todo, 1):
                record(run_task(task), done)
        else:
            pool = ProcessPoolExecutor(max_workers=workers)
            try:
                futures = [pool.submit(run_task, t) for t in todo]
                for done, fut in enumerate(as_completed(futures), 1):
                    record(fut.result(), done)
            finally:  # interrupted: the runs not started are dropped, not waited for
                pool.shutdown(wait=True, cancel_futures=True)
    if not quiet and todo:
        print()


def run_campaign(
    campaign: Campaign, out: Path, *, workers: int = 1, scheduler: str | None = None, quiet: bool = False
) -> CampaignSummary:
    """Run what ``out/runs.jsonl`` does not hold yet, then write the results."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "runs.jsonl"
    finished = _finished(log)
    todo = [t for t in tasks(campaign) if t.key not in finished]
    if not quiet:
        print(f"formation-campaign: {len(todo)} runs to do, {len(finished)} already done", flush=True)
    run_tasks(todo, log, workers=workers, scheduler=scheduler, quiet=quiet)
    wanted = {t.key for t in tasks(campaign)}
    rows = [r for k, r in _finished(log).items() if k in wanted]
    return write_results(out, rows, campaign)


# --- command line ------------------------------------------------------------------------------


def sweep_rate(formation: Path, rates: list[float], out: Path, *, workers: int, scheduler: str | None) -> int:
    """The file's own plant at each rate, with the rate each agent needs."""
    from formation_core.spec import load_formation

    spec = load_formation(formation)
    from formation_sim.core.loop import initial_rho_v0  # numba: once the file is valid
    from formation_sim.core.rates import rate_needs

    campaign = Campaign(formation.resolve(), 1, 0, tuple(rates), None, {})
    summary = run_campaign(campaign, out, workers=workers, scheduler=scheduler, quiet=True)
    rows = {r["control_rate"]: r for r in _finished(out / "runs.jsonl").values()}
    print(f"formation-campaign: rate sweep of {spec.name}, {spec.simulation.duration:g} s")
    print("  control rate [Hz]   verdict   first violation")
    for rate in rates:
        r = rows[rate]
        where = (
            "" if r["verdict"] == "PASS" else f"t={r['violation_t']:.3f} s {r['violation_kind']} {r['violation_where']}"
        )
        print(f"  {rate:>17g}   {r['verdict']:<7}   {where}")
    needs = rate_needs(spec, initial_rho_v0(spec))
    print("  needed (formation-check): " + ", ".join(f"agent {n.agent_id} {n.at_end:.0f} Hz" for n in needs))
    print(f"outputs in {out}/")
    return 0 if summary else 4


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-campaign",
        description="Monte Carlo campaign of headless runs (the campaign file: docs/campaigns.md, --schema), "
        "or a rate sweep. "
        "Exit status: 0 done, 2 invalid input, 4 I/O or internal error (a rerun resumes), 130 interrupted.",
    )
    p.add_argument("campaign", type=Path, nargs="?", help="campaign file (YAML)")
    p.add_argument("--out", type=Path, help="output directory (default out/<campaign>-campaign); resumes if it exists")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local worker processes (default: cores)")
    p.add_argument("--scheduler", help="address of a Dask distributed scheduler (e.g. tcp://host:8786)")
    p.add_argument(
        "--sweep-rate", nargs="+", metavar=("FILE", "RATE"), help="a formation file and control rates [Hz] to try"
    )
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--schema", action="store_true", help="print the reference of the campaign file's keys and exit")
    return p


@guarded("formation-campaign")
def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.schema:
        print(reference_markdown(), end="")
        return 0
    try:
        if args.sweep_rate:
            formation = Path(args.sweep_rate[0])
            try:
                rates = [
                    float(checked_number(f"--sweep-rate[{k}]", float(r), positive=True))
                    for k, r in enumerate(args.sweep_rate[1:], 1)
                ]
            except ValueError as exc:
                raise CampaignError("--sweep-rate", f"rates must be numbers [Hz]: {exc}") from None
            if not rates:
                raise CampaignError("--sweep-rate", "give a formation file and at least one rate")
            out = args.out or Path("out") / f"{formation.stem}-sweep"
            return sweep_rate(formation, rates, out, workers=args.workers, scheduler=args.scheduler)
        if args.campaign is None:
            parser.error("give a campaign file or --sweep-rate FILE RATE…")
        campaign = load_campaign(args.campaign)
        if args.workers < 1:
            raise CampaignError("--workers", f"expected at least 1, got {args.workers}")
    except (CampaignError, FormationSpecError) as exc:
        print(f"formation-campaign: {exc}", file=sys.stderr)
        return 2
    out = args.out or Path("out") / f"{args.campaign.stem}-campaign"
    try:
        summary = run_campaign(campaign, out, workers=args.workers, scheduler=args.scheduler, quiet=args.quiet)
    except KeyboardInterrupt:
        print("\nformation-campaign: interrupted; run again to resume", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except OSError as exc:  # the runs finished are in runs.jsonl: a rerun resumes
        print(f"\nformation-campaign: could not write {out}: {exc}; run again to resume", file=sys.stderr)
        return ExitCode.INCOMPLETE
    if "per_condition" in summary:
        print(condition_table(summary))
    else:
        for rate, s in summary["per_control_rate"].items():
            lo, hi = s["pass_rate_ci95"]
            print(f"  {rate:>8} Hz: {s['passes']}/{s['runs']} pass ({lo:.2f}-{hi:.2f} at 95 %)")
    print(f"outputs in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
