"""The closed loop in one process, no ROS: ``formation-headless FILE --out DIR``.

Every agent's controller (the same core the agent nodes run) and the simulated world step
together. ``sampled`` evaluates the controllers at the control rate and holds the wrenches
(as a deployment runs, and as the ROS 2 lockstep mode does, step for step); ``continuous``
evaluates them at every integrator stage, as the paper's continuous-time law assumes.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from formation_msgs_py.errors import FormationError, FormationSpecError
from formation_msgs_py.spec import FormationSpec, load_formation
from formation_sim.loop import ProgressFn, run_closed_loop
from formation_sim.rates import rate_needs
from formation_sim.report import RunRecorder, format_summary, write_outputs


class ControlRateError(FormationError):
    """The control rate is below what the velocity loop needs (NOTES.md)."""


@dataclass
class HeadlessResult:
    recorder: RunRecorder
    summary: dict[str, Any]


def check_control_rate(spec: FormationSpec) -> list[str]:
    """Messages for every agent whose needed rate exceeds the configured one (empty if fine)."""
    f_s = spec.simulation.control_rate
    return [
        f"agent {n.agent_id} needs {n.at_end:.0f} Hz by t={spec.simulation.duration:g} s "
        f"(insufficient from t={n.insufficient_from:.2f} s at {f_s:g} Hz)"
        for n in rate_needs(spec)
        if n.insufficient_from is not None
    ]


def run_headless(
    spec: FormationSpec,
    *,
    controller_mode: str | None = None,
    progress: ProgressFn | None = None,
    stop_on_violation: bool = False,
) -> HeadlessResult:
    """Run the closed loop for ``spec.simulation.duration``; funnels checked at every control step."""
    mode = controller_mode or spec.simulation.controller
    if mode not in ("sampled", "continuous"):
        raise ValueError(f"controller mode {mode!r} is not sampled or continuous")
    sim_spec = spec.simulation
    record_every = max(1, round(sim_spec.control_rate / sim_spec.record_rate))
    recorder = RunRecorder(spec, record_every=record_every, mode=f"headless-{mode}", control_rate=sim_spec.control_rate)
    wall = run_closed_loop(
        spec, recorder, continuous=mode == "continuous", stop_on_violation=stop_on_violation, progress=progress
    )
    summary = recorder.summary(wall_time=wall, extra={"controller": mode, "physics_rate": sim_spec.physics_rate})
    return HeadlessResult(recorder, summary)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-headless",
        description="Run a formation's closed loop in one process (no ROS) and write OUT as DESIGN.md §8: "
        "summary.json, trajectory.npz, errors.png, orientation_errors.png, inputs.png. "
        "Exit status: 0 every funnel held, 1 a funnel was violated, 2 invalid file or refused rate.",
    )
    p.add_argument("file", type=Path, help="formation file (YAML)")
    p.add_argument("--out", type=Path, default=None, help="output directory (default: out/<formation>-headless)")
    p.add_argument("--controller", choices=("sampled", "continuous"), help="override simulation.controller")
    add_override_options(p)
    p.add_argument(
        "--allow-low-rate", action="store_true", help="run even if the control rate is below the need (warn)"
    )
    p.add_argument("--stop-on-violation", action="store_true", help="stop at the first funnel violation")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.add_argument("--force", action="store_true", help="write into an existing non-empty output directory")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def add_override_options(p: argparse.ArgumentParser, *, ros: bool = False) -> None:
    """The ``simulation.*`` overrides every runner takes (``ros``: also mode and timeouts)."""
    if ros:
        p.add_argument("--mode", choices=("lockstep", "realtime"), help="override simulation.mode")
    p.add_argument("--duration", type=float, help="override simulation.duration [s]")
    p.add_argument("--control-rate", type=float, help="override simulation.control_rate [Hz]")
    p.add_argument("--physics-rate", type=float, help="override simulation.physics_rate [Hz]")
    p.add_argument("--record-rate", type=float, help="override simulation.record_rate [Hz]")
    p.add_argument("--seed", type=int, help="override simulation.seed")
    if ros:
        p.add_argument("--step-timeout", type=float, help="override simulation.step_timeout [wall s] (lockstep)")
        p.add_argument("--command-timeout", type=float, help="override simulation.command_timeout [sim s] (realtime)")


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """simulation.* overrides from the common command-line options."""
    keys = {
        "duration": "duration",
        "control_rate": "control_rate",
        "physics_rate": "physics_rate",
        "record_rate": "record_rate",
        "seed": "seed",
    }
    out = {k: getattr(args, a) for a, k in keys.items() if getattr(args, a, None) is not None}
    if getattr(args, "control_rate", None) is not None and getattr(args, "physics_rate", None) is None:
        # keep the physics step when it is a multiple of the new control rate, else match it
        out["_keep_physics"] = True
    return out


def load_with_overrides(path: Path, over: dict[str, Any]) -> FormationSpec:
    keep = over.pop("_keep_physics", False)
    spec = load_formation(path)
    if keep:
        ratio = spec.simulation.physics_rate / over["control_rate"]
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            over["physics_rate"] = over["control_rate"]
    if over:
        spec = load_formation(path, overrides=over)
    return spec


def prepare_out_dir(out: Path, force: bool) -> None:
    """Refuse to overwrite a non-empty directory unless ``force``."""
    if out.exists() and any(out.iterdir()) and not force:
        raise FileExistsError(f"output directory {out} exists and is not empty (use --force to overwrite)")
    out.mkdir(parents=True, exist_ok=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        spec = load_with_overrides(args.file, overrides_from_args(args))
        if args.controller:
            spec = spec.with_simulation(controller=args.controller)
        out = args.out or Path("out") / f"{spec.name}-headless"
        prepare_out_dir(out, args.force)
    except (FormationSpecError, FileExistsError) as exc:
        print(f"formation-headless: {exc}", file=sys.stderr)
        return 2
    mode = args.controller or spec.simulation.controller
    if spec.dropped_edges:
        dropped = ", ".join(f"({a}, {b})" for a, b in spec.dropped_edges)
        print(f"formation-headless: spanning tree: dropped edges {dropped}", file=sys.stderr)
    if mode == "sampled":
        problems = check_control_rate(spec)
        if problems:
            verdict = "warning" if args.allow_low_rate or spec.simulation.rate_check == "warn" else "error"
            for msg in problems:
                print(f"formation-headless: {verdict}: {msg}", file=sys.stderr)
            if verdict == "error":
                print(
                    "formation-headless: control rate too low; raise --control-rate or pass --allow-low-rate",
                    file=sys.stderr,
                )
                return 2

    def progress(t: float, rtf: float, margin: float) -> None:
        print(
            f"  t={t:7.3f}/{spec.simulation.duration:g} s  real-time factor {rtf:5.2f}  worst margin {margin:+.3f}",
            flush=True,
        )

    print(
        f"formation-headless: {spec.name}, {len(spec.agents)} agents, {mode} control at "
        f"{spec.simulation.control_rate:g} Hz, physics {spec.simulation.physics_rate:g} Hz",
        flush=True,
    )
    result = run_headless(
        spec, controller_mode=mode, progress=None if args.quiet else progress, stop_on_violation=args.stop_on_violation
    )
    write_outputs(out, result.recorder, result.summary, plots=not args.no_plots)
    print(format_summary(result.summary))
    print(f"outputs in {out}/")
    return 0 if result.summary["funnels_held"] else 1


if __name__ == "__main__":
    sys.exit(main())
