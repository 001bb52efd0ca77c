"""``formation-check FILE``: validate a formation file and say whether it is safe to run.

Exit status: 0 valid, 1 valid but unsafe (a control rate below what the velocity loop needs,
an initial error within a few percent of its funnel bound; with ``--realtime``, more cores than
this host has, or a simulator that no core keeps on time), 2 invalid (the message names the
field). ``--schema`` prints the reference of every field of a formation file.

``--realtime`` adds what a realtime run of the file needs (:mod:`formation_sim.capacity`):
the CPU per tick of the simulator and of each agent, and the cores that keep its ticks on time,
from this host's calibration (``--calibrate`` measures it first, 20-40 s) or built-in
costs; the prediction's first line says which. A calibration that fails exits 3 (a floor process
failed, its error printed); an unreadable calibration file is invalid input (2).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from formation_core import options
from formation_core.errors import FormationError
from formation_core.options import OptionParser
from formation_core.verdict import ExitCode

if TYPE_CHECKING:
    from formation_core.formation import FormationSpec

# The cores (numba) are imported only once the file has been validated (load_spec imports numpy
# and the loader only): a file that is not a formation at all (binary, alias bomb, duplicate keys)
# is refused in a fraction of a second and a few tens of MB.

#: An initial normalised error closer than this fraction to its bound is "unsafe".
INITIAL_MARGIN_WARN = 0.05


def report(spec: FormationSpec) -> tuple[list[str], list[str]]:
    """(lines of the readable summary, list of reasons the file is unsafe)."""
    import numpy as np

    from formation_core import funnels
    from formation_sim.core.loop import initial_rho_v0
    from formation_sim.core.rates import rate_needs

    sim = spec.simulation
    lines = [
        f"formation {spec.name} ({spec.source}): {len(spec.agents)} agents, {len(spec.edges)} edges, tree",
        f"  simulation: mode {sim.mode}, {sim.duration:g} s, control {sim.control_rate:g} Hz, "
        f"physics {sim.physics_rate:g} Hz, controller {sim.controller}, seed {sim.seed}, "
        f"gravity {np.asarray(sim.gravity).tolist()}",
    ]
    if spec.dropped_edges:
        lines.append("  spanning tree: dropped edges " + ", ".join(f"({a}, {b})" for a, b in spec.dropped_edges))
    unsafe: list[str] = []
    neighbours: dict[str, list[str]] = {a.id: [] for a in spec.agents}
    for e in spec.edges:
        neighbours[e.tail].append(e.head)
        neighbours[e.head].append(e.tail)
    lines.append("agents:")
    lines.append("  id        mass [kg]   delta   gamma   neighbours")
    for a in spec.agents:
        lines.append(
            f"  {a.id:<8} {a.dynamics.mass:>9.4g}   {a.controller.delta:>5.3g}   {a.controller.gamma:>5.3g}   "
            + ", ".join(neighbours[a.id])
        )
    lines.append("edges (tail-head):")
    lines.append("  edge      d_col  d_des  d_con   d(0)     e(0)   margin_e  psi(0)  rho_psi0  margin_psi")
    by_id = {a.id: a for a in spec.agents}
    for e in spec.edges:
        tail, head = by_id[e.tail], by_id[e.head]
        d0 = float(np.linalg.norm(head.position - tail.position))
        e0, psi0 = funnels.edge_errors_from_arrays(
            tail.position, head.position, tail.R_world_body, head.R_world_body, e.d_des, e.R_des
        )
        m_e = float(funnels.margin_e(e0, e.c_col, e.c_con))  # ρ_e(0) = 1: ξ_e(0) = e(0)
        m_psi = float(funnels.margin_psi(psi0 / e.rho_psi_0))
        lines.append(
            f"  {e.name:<8} {e.d_col:>6.3g} {e.d_des:>6.3g} {e.d_con:>6.3g} {d0:>6.3f} {e0:>8.3f} {m_e:>10.3f} "
            f"{psi0:>7.4f} {e.rho_psi_0:>9.3g} {m_psi:>11.3f}"
        )
        if m_e < INITIAL_MARGIN_WARN:
            unsafe.append(f"edge {e.name}: initial distance error within {m_e:.1%} of its bound")
        if m_psi < INITIAL_MARGIN_WARN:
            unsafe.append(f"edge {e.name}: initial orientation error within {m_psi:.1%} of rho_psi0")
    lines.append(f"control rate needed by the velocity loop (zero-order hold at {sim.control_rate:g} Hz):")
    lines.append("  agent     at t=0 [Hz]   at t=T [Hz]   verdict   continuous: RK4 step <= [s]")
    for n in rate_needs(spec, initial_rho_v0(spec)):
        if n.insufficient_from is None:
            verdict = "ok"
        else:
            verdict = f"TOO LOW from t={n.insufficient_from:.2f} s"
            unsafe.append(
                f"agent {n.agent_id}: control rate {sim.control_rate:g} Hz is below the {n.at_end:.0f} Hz "
                f"its velocity loop needs by t={sim.duration:g} s (from t={n.insufficient_from:.2f} s)"
            )
        lines.append(f"  {n.agent_id:<8} {n.at_start:>11.0f}   {n.at_end:>11.0f}   {verdict:<7}   {n.physics_step:.3g}")
    if spec.has_links:
        lines += link_report(spec, unsafe)
    return lines, unsafe


def link_report(spec: FormationSpec, unsafe: list[str]) -> list[str]:
    """What the file's link model costs, where a bound is known: each link's largest age without a loss
    against its receiver's time-out (a sample older than that is never used), and how many losses in a
    row make a measurement too old (and how likely one sample starts such a run); the margin it costs is
    bounded nowhere in the paper's analysis, which assumes every measurement at once."""
    import math

    from formation_core.formation import simulator_view
    from formation_sim.core.links import (
        CHANNELS,
        P_BAD_GOOD,
        P_LOSS,
        P_LOSS_GOOD,
        P_RATIO,
        P_TIMEOUT,
        link_names,
        longest_delay_steps,
        new_link_set,
    )

    view = simulator_view(spec)
    links = new_link_set(view)
    names = link_names(view)
    rate = spec.simulation.control_rate
    lines = [
        "links (docs/links.md): largest age of a sample with none lost, against the receiver's time-out",
        "  link            worst age [ms]   time-out [ms]   losses in a row to miss it   loss",
    ]
    for channel, ch in zip(CHANNELS, links[:3]):
        for i, name in enumerate(names[channel]):
            prm = ch.params[i]
            period = 1 if prm[P_RATIO] >= 1.0 else math.ceil(1.0 / prm[P_RATIO] - 1e-9)  # steps between samples
            worst = longest_delay_steps(prm[None, :], rate) + period - 1
            timeout = int(prm[P_TIMEOUT])
            loss_model = int(prm[P_LOSS])
            if worst > timeout:
                unsafe.append(
                    f"link {channel} {name}: its samples are {worst / rate * 1e3:.3g} ms old with none lost, older "
                    f"than the {timeout / rate * 1e3:.3g} ms its receiver uses: they are never used"
                )
            misses = max(0, math.ceil((timeout - worst + 1) / period)) if worst <= timeout else 0
            if loss_model == 0:
                loss = "none"
            elif loss_model == 1:
                loss = f"{prm[P_LOSS_GOOD]:.3g} independent: {prm[P_LOSS_GOOD] ** max(misses, 1):.2g} per sample"
            else:
                mean = 1 / prm[P_BAD_GOOD] if prm[P_BAD_GOOD] > 0 else math.inf
                loss = f"bursts, mean length {mean:.3g} samples"
            lines.append(
                f"  {channel + ' ' + name:<15} {worst / rate * 1e3:>14.3g}   {timeout / rate * 1e3:>13.3g}   "
                f"{misses:>26}   {loss}"
            )
    lines.append(
        "  what a link model costs in margin is bounded nowhere in the paper's analysis (every measurement at "
        "once): only a campaign can tell (formation-campaign with links:, docs/campaigns.md)"
    )
    return lines


def build_parser() -> OptionParser:
    p = options.build_parser(
        options.CHECK,
        "formation-check",
        "Validate a formation file and print a summary: agents, tree, edges, initial errors and "
        "margins, and the control rate each agent needs over the run. "
        "Exit status: 0 valid, 1 valid but unsafe, 2 invalid.",
        file_required=False,
    )
    p.add_argument(
        "--schema", action="store_true", help="print the reference of every formation-file field (Markdown) and exit"
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="also predict the CPU per tick of a realtime run (simulator, each agent) and the cores it needs, and "
        "say whether this host has them (exit 1 if not)",
    )
    p.add_argument(
        "--calibrate",
        action="store_true",
        help="measure this host's CPU per message first (20-40 s of ROS 2 processes) and store it in "
        "$XDG_CACHE_HOME/formation/capacity.json for --realtime; with no FILE, only that",
    )
    p.add_argument(
        "--no-record",
        dest="predict_record",
        action="store_false",
        help="with --realtime: a run that does not record a bag (formation-launch --no-record)",
    )
    return p


def realtime_report(spec: FormationSpec, record: bool) -> tuple[list[str], list[str]]:
    """(lines of the realtime prediction for this host, reasons this host cannot run it on time)."""
    from formation_sim import capacity

    prediction = capacity.predict(spec, capacity.load_costs(), record=record)
    return capacity.report_lines(prediction, capacity.available_cores())


def run_calibration(quiet: bool) -> int:
    """``--calibrate``: measure and store this host's message costs; 0, or 3 if a floor process failed."""
    from formation_sim.launch.calibrate import calibrate

    if not quiet:
        print("formation-check: calibrating: the floor of a realtime run of 20 agents (20-40 s)…", flush=True)
    try:
        path, costs, detail = calibrate()
    except FormationError as exc:
        print(f"formation-check: {exc}", file=sys.stderr)
        return ExitCode.PROCESS_DIED
    if not quiet:
        print(
            f"calibration: {costs.sim_message_s * 1e6:.1f} µs per simulator message, "
            f"{costs.agent_message_s * 1e6:.1f} µs per agent message (load {detail['load_1min']:.1f}, "
            f"floor on time {detail['on_time_fraction']:.1%}); written to {path}"
        )
    return ExitCode.PASS


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    ns = parser.parse_args(argv)
    opts = options.RunOptions.from_namespace(options.CHECK, ns)
    if opts.schema:
        from formation_core.schema import schema_markdown

        sys.stdout.write(schema_markdown())
        return ExitCode.PASS
    if ns.calibrate:
        code = run_calibration(opts.quiet)
        if code != ExitCode.PASS or opts.file is None:
            return code
    if opts.file is None:
        parser.error("a formation file is required (or --schema, --calibrate)")
    from formation_sim.preflight import InvalidRunError, duration_problem, load_spec

    try:
        spec = load_spec(opts)
        problem = duration_problem(spec, opts)  # no run can take it: invalid, not merely unsafe
        if problem is not None:
            raise InvalidRunError(problem)
    except FormationError as exc:
        print(f"formation-check: INVALID: {exc}", file=sys.stderr)
        return ExitCode.INVALID
    lines, unsafe = report(spec)
    if ns.realtime or ns.calibrate:
        try:
            more, why = realtime_report(spec, ns.predict_record)
        except FormationError as exc:  # an unreadable calibration file
            print(f"formation-check: INVALID: {exc}", file=sys.stderr)
            return ExitCode.INVALID
        lines += more
        unsafe += why
    if not opts.quiet:
        print("\n".join(lines))
    if unsafe:
        print("UNSAFE:", file=sys.stderr)
        for reason in unsafe:
            print(f"  - {reason}", file=sys.stderr)
        return ExitCode.FAIL
    if not opts.quiet:
        print("VALID: safe to run at these settings")
    return ExitCode.PASS


if __name__ == "__main__":
    sys.exit(main())
