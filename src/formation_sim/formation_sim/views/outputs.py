"""What a run leaves and prints: trajectory.npz, the figures and summary.json written atomically,
the animation, and the summary as text (docs/outputs.md)."""

from __future__ import annotations

import io
import os
import shutil
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np

from formation_core.faults import fault_lines, fault_meanings, write_atomic, write_json
from formation_core.formation import FormationSpec
from formation_core.verdict import ExitCode, Verdict
from formation_deploy.publisher_watch import intruder_lines
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.summary import Clearance, FirstViolation, LinkReport, RunSummary
from formation_sim.views.foxglove_layout import write_layout


def write_outputs(out_dir: Path, recorder: RunRecorder, summary: RunSummary, *, plots: bool = True) -> float:
    """trajectory.npz, the figures (:mod:`formation_sim.views.figures`) and the formation's Foxglove layout
    (:mod:`formation_sim.views.foxglove_layout`) unless ``plots`` is false, then
    summary.json; each written under a temporary name and renamed. summary.json comes last and names what is there.
    Returns the wall seconds the figures took.

    Raises OSError (disk full, …) after writing a summary marked INCOMPLETE if it still can.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        npz = io.BytesIO()
        # numpy's stub types the keyword arrays as its allow_pickle flag too
        np.savez(npz, **recorder.arrays())  # type: ignore[arg-type]
        write_atomic(out_dir / "trajectory.npz", npz.getvalue())
        written.append("trajectory.npz")
        figures = 0.0
        if plots:
            t_figures = time.monotonic()
            write_figures(out_dir, recorder.spec, recorder.arrays(), summary, written)
            written.append(write_layout(out_dir, recorder.spec).name)
            figures = time.monotonic() - t_figures
    except OSError as exc:
        failed = dict(summary)
        failed.update(
            verdict=Verdict.INCOMPLETE.value,
            funnels_held=None if summary.get("verdict") != Verdict.FAIL.value else False,
            incomplete_reason=f"I/O error writing {out_dir}: {exc}",
            exit_status=int(ExitCode.INCOMPLETE),
            outputs=written,
        )
        try:
            write_json(out_dir / "summary.json", failed)
        except OSError:
            pass
        raise
    write_json(out_dir / "summary.json", {**summary, "outputs": [*written, "summary.json"]})
    return figures


def write_figures(
    out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], summary: RunSummary, written: list[str]
) -> None:
    """The figures (:mod:`formation_sim.views.figures`) captioned with ``summary``'s verdict, drawn in
    a staging directory and each renamed into ``out_dir``; appends each name to ``written`` once there."""
    from formation_sim.views.figures import VERDICT_COLOURS, Caption, plot_run  # matplotlib only when drawn

    t_start = float(arrays["t"][0]) if len(arrays["t"]) else 0.0
    caption = Caption(run_caption(summary, t_start), VERDICT_COLOURS.get(summary["verdict"], "black"))
    staging = Path(tempfile.mkdtemp(dir=out_dir, prefix=".figures."))
    try:
        for path in plot_run(staging, spec, arrays, caption):
            os.replace(path, out_dir / path.name)
            written.append(path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def redraw_figures(out_dir: Path, spec: FormationSpec, summary: RunSummary) -> list[str]:
    """The figures ``summary["outputs"]`` lists, drawn again from OUT/trajectory.npz with ``summary``'s
    verdict in their caption (formation-launch's verdict, when it differs from the simulator's); the
    names written. Raises OSError."""
    from formation_sim.views.figures import FIGURES

    written: list[str] = []
    if any(name in summary.get("outputs", ()) for name in FIGURES):
        with np.load(out_dir / "trajectory.npz") as data:
            arrays = dict(data)
        write_figures(out_dir, spec, arrays, summary, written)
    return written


def report_animation(out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray]) -> Path:
    """Write OUT/animation.gif (:mod:`formation_sim.views.animation`) and print where and how long it took."""
    from formation_sim.views.animation import write_animation

    path, frames, wall = write_animation(out_dir, spec, arrays)
    print(f"animation: {path} ({frames} frames, written in {wall:.1f} s)", flush=True)
    return path


def format_summary(summary: RunSummary) -> str:
    """A short human-readable summary of a run (printed by every command): the verdict line, the
    margins per edge and agent, and every fault kind with its first and last occurrence."""
    wall = summary["wall_time"]
    timing = (
        ", wall time not recorded"  # a bag whose writer did not note it
        if wall is None
        else f" in {wall:.2f} s wall, real-time factor {summary['real_time_factor'] or 0:.3g}"
    )
    lines = [
        f"formation {summary['formation']} ({summary['mode']}, control {summary['control_rate']:g} Hz, "
        f"{summary['duration']:g} s simulated{timing})"
    ]
    lines.append(verdict_line(summary))
    lines.append("  edge     min margin e   min margin psi   settle e [s]   settle psi [s]")
    for name, s in summary["edges"].items():
        lines.append(
            f"  {name:<8} {_f(s['min_margin_e']):>12}   {_f(s['min_margin_psi']):>14}   "
            f"{_f(s['settle_time_e']):>12}   {_f(s['settle_time_psi']):>14}"
        )
    lines.append("  agent    peak force [N]   peak torque [N·m]   min margin v")
    for aid, a in summary["agents"].items():
        lines.append(f"  {aid:<8} {a['peak_force']:>14.4g}   {a['peak_torque']:>17.4g}   {_f(a['min_margin_v']):>12}")
    lines.extend(clearance_lines(summary.get("clearance")))
    lines.extend(link_lines(summary.get("links")))
    lines.extend(fault_lines(summary.get("faults") or {}))
    lines.extend(fault_meanings(summary.get("faults") or {}))
    return "\n".join(lines)


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1e3:.3g} ms"


def link_lines(links: LinkReport | None) -> list[str]:
    """Per channel of a link model: samples sent, lost, and the held samples' ages; the worst link."""
    if not links:
        return []
    lines = []
    channels = (("poses", links.get("poses")), ("velocity", links.get("velocity")), ("wrench", links.get("wrench")))
    for channel, c in channels:
        if not c:
            continue
        age = c["age"]
        lost = 0.0 if c["loss_rate"] is None else 100.0 * c["loss_rate"]
        lines.append(
            f"  links: {channel}: {c['sent']} samples sent, {lost:.3g} % lost; age median {_ms(age['median'])}, "
            f"99th percentile {_ms(age['p99'])}, max {_ms(age['max'])}"
        )
    real = links.get("real_latency_ms")
    if real and real.get("samples"):
        lines.append(
            f"  links: the real network under them (realtime, publish to answer): median {real['p50']:.3g} ms, "
            f"99th percentile {real['p99']:.3g} ms, max {real['max']:.3g} ms"
        )
    worst = links.get("worst")
    if worst:
        lines.append(
            f"  links: worst {worst['channel']} {worst['link']}: 99th percentile age {_ms(worst['age_p99'])}, "
            f"{100.0 * worst['loss_rate']:.3g} % lost"
        )
    return lines


def contact_note(summary: RunSummary) -> str:
    """``; but agents 1 and 3 touched at t=0.2000 s`` after a PASS with a contact reported, else ``""``."""
    first = (summary.get("clearance") or {}).get("first_contact")
    if not first:
        return ""
    a, b = first["pair"]
    return f"; but agents {a} and {b} touched at t={first['t']:.4f} s (not a funnel: simulation.contact: report)"


def clearance_lines(clearance: Clearance | None) -> list[str]:
    """The smallest clearance between any two bodies, and every contact (a contact is never silent)."""
    if not clearance or clearance.get("min") is None or clearance["pair"] is None:
        return []
    a, b = clearance["pair"]
    lines = [f"  clearance: smallest {clearance['min']:.4g} m, agents {a} and {b} at t={clearance['t']:.4f} s"]
    for c in clearance.get("contacts", []):
        a, b = c["pair"]
        effect = (
            "fails the run" if clearance["policy"] == "fail" else "reported (simulation.contact: fail fails the run)"
        )
        lines.append(
            f"  CONTACT: agents {a} and {b} touched at t={c['first_t']:.4f} s "
            f"(smallest clearance {c['min']:.4g} m); {effect}"
        )
    return lines


def verdict_line(summary: RunSummary) -> str:
    """``PASS: …``, ``FAIL: first violation …`` or ``INCOMPLETE: reason``, then one line per intruder."""
    verdict = summary["verdict"]
    fv = summary["first_violation"]
    if verdict == Verdict.PASS.value:
        text = f"PASS: every funnel held over {summary['duration']:g} s (worst margin {_f(summary['worst_margin'])})"
        return "\n".join([text + contact_note(summary), *tls_lines(summary.get("security"))])
    if verdict == Verdict.FAIL.value:
        text = f"FAIL: first violation {violation_text(fv)}{after_violation(summary)}"
        return "\n".join([text, *tls_lines(summary.get("security"))])
    reason = str(summary.get("incomplete_reason"))
    intruders = intruder_lines(summary.get("security"))
    if intruders:  # the reason names them on one line; here one line each
        reason = reason.replace(": " + "; ".join(intruders), "")
    if fv:  # untrusted input, or after an agent died: a violation seen is no evidence about the controller
        seen = f"a violation seen {violation_text(fv)}"
    else:
        seen = f"no violation in the {_f(summary['duration'])} s checked"
    text = f"INCOMPLETE: {reason} ({seen}, worst margin {_f(summary['worst_margin'])})"
    return "\n".join([text, *(f"  intruder: {line}" for line in intruders)])


def after_violation(summary: RunSummary) -> str:
    """What a FAIL's ``incomplete_reason`` adds to its first violation: ``; then the run stopped early:
    REASON`` when it did (its data ends short of the requested duration), else ``; then REASON`` (a
    realtime run that went on after an agent died, a duration nobody requested), or nothing."""
    reason = summary.get("incomplete_reason")
    if not reason:
        return ""
    end, asked, rate = summary.get("duration"), summary.get("requested_duration"), summary.get("control_rate")
    # reached to half a control period, as the recorder judges a duration reached
    tol = 0.5 / rate if rate else 1e-9
    early = end is not None and asked is not None and end < asked - tol
    return f"; then the run stopped early: {reason}" if early else f"; then {reason}"


def violation_text(fv: FirstViolation | None) -> str:
    """``at t=2.0345 s: velocity 1 (vx)``: a first violation of summary.json (time [s], kind, edge or
    agent, channel); a FAIL always has one, a summary edited by hand may not."""
    if fv is None:
        return "(not in the summary)"
    where = fv.get("edge") or fv.get("pair") or fv.get("agent")
    return f"at t={fv['t']:.4f} s: {fv['kind']} {where} ({fv['channel']})"


#: characters of the verdict and its reason a figure's caption shows (the whole reason is in summary.json)
CAPTION_REASON_CHARS = 120


def run_caption(summary: RunSummary, t_start: float) -> str:
    """The verdict with its short reason and the simulated time covered of the requested duration,
    for a figure's title: ``INCOMPLETE: duration not reached: t=2.159 s of 5 s — t = 0–2.159 s of 5 s``.

    ``t_start`` [s]: the first recorded sample's time; the end is summary.json's ``duration`` (the
    last sample checked)."""
    verdict, fv = summary["verdict"], summary["first_violation"]
    reason = summary.get("incomplete_reason")
    if verdict == Verdict.PASS.value:
        text = "PASS: every funnel held" + contact_note(summary)
    elif verdict == Verdict.FAIL.value:
        text = f"FAIL: first violation {violation_text(fv)}{after_violation(summary)}"
    else:
        text = f"{verdict}: {reason}"
    text = textwrap.shorten(text, CAPTION_REASON_CHARS, placeholder=" …")
    end, asked = summary.get("duration"), summary.get("requested_duration")
    if end is None:
        covered = "no sample checked"
    else:
        covered = f"t = {t_start:g}–{end:g} s " + ("(no requested duration)" if asked is None else f"of {asked:g} s")
    return f"{text} — {covered}"


def _tls_failures(security: Any) -> dict[str, dict[str, Any]]:
    found = (security or {}).get("tls_handshake_failures") if isinstance(security, dict) else None
    return found if isinstance(found, dict) else {}


def tls_reason(security: Any) -> str | None:
    """One line naming the failed TLS handshakes of a secure run (``security.tls_handshake_failures``
    of summary.json: process -> count and the last error), or None when there were none."""
    failures = _tls_failures(security)
    if not failures:
        return None
    counts = ", ".join(f"{name} {f.get('count')}x" for name, f in failures.items())
    last = next(reversed(failures.values())).get("last")
    return (
        f"TLS handshake failed ({counts} in their logs; {last}): a certificate the others refuse "
        "(another CA, expired or not yet valid; formation-keys check)"
    )


def tls_lines(security: Any) -> list[str]:
    """The lines of the failed TLS handshakes under a PASS or FAIL, one per process that saw them
    (an INCOMPLETE run's reason names them: :func:`tls_reason`)."""
    return [
        f"  TLS: {name} failed {f.get('count')} handshake(s), the last: {f.get('last')}"
        for name, f in _tls_failures(security).items()
    ]


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"
