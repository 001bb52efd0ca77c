"""The closed loop in one process, no ROS: ``formation-headless FILE --out DIR``.

Every agent's controller (the same core the agent nodes run) and the simulated world step
together. ``sampled`` evaluates the controllers at the control rate and holds the wrenches
(as a deployment runs, and as the ROS 2 lockstep mode does, step for step); ``continuous``
evaluates them at every integrator stage, as the paper's continuous-time law assumes.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from formation_core import options
from formation_core.errors import FormationError
from formation_core.options import OptionParser
from formation_core.verdict import EXIT_STATUS_HELP, ExitCode, Incomplete, guarded
from formation_sim.preflight import preflight

if TYPE_CHECKING:  # the cores (numba) are imported once the options and the file are valid
    from formation_core.formation import FormationSpec
    from formation_sim.core.loop import ProgressFn
    from formation_sim.core.recorder import RunRecorder
    from formation_sim.core.summary import RunSummary


@dataclass
class HeadlessResult:
    recorder: RunRecorder
    summary: RunSummary


def run_headless(
    spec: FormationSpec,
    *,
    controller_mode: str | None = None,
    progress: ProgressFn | None = None,
    stop_on_violation: bool = False,
) -> HeadlessResult:
    """Run the closed loop for ``spec.simulation.duration``; funnels checked at every control step."""
    from formation_sim.core.loop import run_closed_loop
    from formation_sim.core.recorder import RunRecorder

    mode = controller_mode or spec.simulation.controller
    if mode not in ("sampled", "continuous"):
        raise ValueError(f"controller mode {mode!r} is not sampled or continuous")
    sim_spec = spec.simulation
    record_every = max(1, round(sim_spec.control_rate / sim_spec.record_rate))
    recorder = RunRecorder(spec, record_every=record_every, mode=f"headless-{mode}", control_rate=sim_spec.control_rate)
    wall, reason = run_closed_loop(
        spec, recorder, continuous=mode == "continuous", stop_on_violation=stop_on_violation, progress=progress
    )
    summary = recorder.summary(
        wall_time=wall,
        requested_duration=sim_spec.duration,
        incomplete=Incomplete(ExitCode.INCOMPLETE, reason) if reason else None,
        extra={"controller": mode, "physics_rate": sim_spec.physics_rate},
    )
    return HeadlessResult(recorder, summary)


def build_parser() -> OptionParser:
    return options.build_parser(
        options.HEADLESS,
        "formation-headless",
        "Run a formation's closed loop in one process (no ROS) and write OUT as docs/outputs.md: "
        "summary.json, trajectory.npz, errors.png, orientation_errors.png, inputs.png, velocity_errors.png, "
        "clearance.png, link_ages.png (with a link model), foxglove_layout.json (not with --no-plots), "
        "animation.gif (with --animate). " + EXIT_STATUS_HELP + ".",
    )


@guarded("formation-headless")
def main(argv: list[str] | None = None) -> int:
    opts = options.parse(options.HEADLESS, build_parser(), argv)
    try:
        run = preflight(opts, lambda spec, _: Path("out") / f"{spec.name}-headless")
    except FormationError as exc:
        print(f"formation-headless: {exc}", file=sys.stderr)
        return ExitCode.INVALID
    spec, out, mode = run.spec, run.out, run.options.controller
    assert out is not None  # preflight names OUT from the default above
    for msg in run.warnings:
        print(f"formation-headless: warning: {msg}", file=sys.stderr)
    from formation_sim.views.outputs import format_summary, report_animation, write_outputs

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
        spec, controller_mode=mode, progress=None if opts.quiet else progress, stop_on_violation=opts.stop_on_violation
    )
    try:
        write_outputs(out, result.recorder, result.summary, plots=not opts.no_plots)
    except OSError as exc:
        print(f"formation-headless: INCOMPLETE: could not write {out}: {exc}", file=sys.stderr)
        return ExitCode.INCOMPLETE
    if opts.animate:
        report_animation(out, spec, result.recorder.arrays())
    print(format_summary(result.summary))
    print(f"outputs in {out}/ (exit status {result.summary['exit_status']})")
    return result.summary["exit_status"]


if __name__ == "__main__":
    sys.exit(main())
