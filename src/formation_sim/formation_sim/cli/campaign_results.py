"""What a campaign found: ``runs.csv`` (one row per sample, rate and condition: :data:`COLUMNS`), the pass
rate per control rate and condition with its 95 % Wilson interval (:func:`summarise`), the largest
delay and loss that still passed (:func:`tolerance`), ``summary.json`` and the figures
``pass_rate.png``, ``worst_margin.png`` and, with a link grid, ``link_pass_rate.png``.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal, NotRequired, TypedDict, cast

from formation_sim.cli.campaign_file import CONDITIONS, Campaign

COLUMNS = (
    "sample",
    "control_rate",
    *CONDITIONS,
    "seed",
    "verdict",
    "violation_t",
    "violation_kind",
    "violation_where",
    "violation_channel",
    "worst_margin_e",
    "worst_margin_psi",
    "worst_margin_v",
    "peak_force",
    "peak_torque",
    "wall_time",
)


class Conditions(TypedDict):
    """A run's values of :data:`CONDITIONS`: link delay and jitter [s], loss probability, sensor rate
    [Hz], the gains δ and γ (None: the formation file's)."""

    link_delay: float | None
    link_loss: float | None
    link_jitter: float | None
    sensor_rate: float | None
    delta: float | None
    gamma: float | None


def conditions_of(values: Sequence[float | None]) -> Conditions:
    """:class:`Conditions` of values in :data:`CONDITIONS`' order (a task's ``condition``)."""
    delay, loss, jitter, sensor_rate, delta, gamma = values
    return {
        "link_delay": delay,
        "link_loss": loss,
        "link_jitter": jitter,
        "sensor_rate": sensor_rate,
        "delta": delta,
        "gamma": gamma,
    }


class CampaignRow(Conditions):
    """One run of a campaign: a line of runs.jsonl and a row of runs.csv (:data:`COLUMNS`)."""

    sample: int
    control_rate: float  # Hz
    seed: str  # entropy:spawn key of the sample's plant
    verdict: str  # PASS, FAIL or INCOMPLETE
    violation_t: float | None
    violation_kind: str | None
    violation_where: str | None
    violation_channel: str | None
    worst_margin_e: float | None
    worst_margin_psi: float | None
    worst_margin_v: float | None
    peak_force: float  # N
    peak_torque: float  # N·m
    wall_time: float | None  # s


class RateResult(TypedDict):
    """The runs at one control rate: how many passed, the pass rate's 95 % Wilson interval, and the
    first violations by kind."""

    runs: int
    passes: int
    pass_rate: float | None  # None: no runs
    pass_rate_ci95: list[float]
    first_violation_kinds: dict[str, int]


class ConditionCell(Conditions):
    """The runs of one condition of a grid at one control rate."""

    control_rate: float
    runs: int
    passes: int
    pass_rate: float | None
    pass_rate_ci95: list[float]


class Tolerance(TypedDict):
    """The largest delay [s] and loss that still hold (:data:`HOLDS`) for one group of the other conditions."""

    control_rate: float
    link_jitter: float | None
    sensor_rate: float | None
    delta: float | None
    gamma: float | None
    largest_delay: float | None
    largest_loss: float | None


class CampaignSummary(TypedDict):
    """A campaign's summary.json (docs/campaigns.md)."""

    formation: str
    samples: int
    seed: int
    vary: dict[str, object]
    duration: float | None
    per_control_rate: dict[str, RateResult]
    links: NotRequired[dict[str, object]]
    gains: NotRequired[dict[str, list[float]]]
    per_condition: NotRequired[list[ConditionCell]]
    tolerance: NotRequired[list[Tolerance]]


def _condition_values(row: Mapping[str, object]) -> tuple[float | None, ...]:
    """A row's values of :data:`CONDITIONS`, in their order (None where absent: a runs.jsonl line of a
    campaign without grids may lack them)."""
    return tuple(cast("float | None", row.get(c)) for c in CONDITIONS)


def row_key(row: Mapping[str, object]) -> tuple[object, ...]:
    """The :attr:`Task.key` of a finished run's row."""
    return (row["sample"], row["control_rate"], *_condition_values(row))


def _sort_key(row: CampaignRow) -> tuple[float, ...]:
    """runs.csv's order: sample, control rate, then the conditions (None, the file's, first)."""
    values = (row["sample"], row["control_rate"], *_condition_values(row))
    return tuple(-1.0 if v is None else v for v in values)


def wilson(passes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval (low, high) of the pass rate ``passes / n``; low <= rate <= high
    (a 100 % rate has high == 1.0, a 0 % rate low == 0.0); no runs: (0, 1)."""
    if n == 0:
        return 0.0, 1.0
    p = passes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # the interval contains p exactly; rounding leaves the upper bound of a 100 % rate (the lower of
    # a 0 % rate) a unit in the last place inside it, so p itself bounds it
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def summarise(rows: list[CampaignRow], campaign: Campaign) -> CampaignSummary:
    """Pass rate and its 95 % interval, worst margins, per control rate."""
    per_rate: dict[str, RateResult] = {}
    for rate in campaign.control_rates:
        sel = [r for r in rows if r["control_rate"] == rate]
        passes = sum(r["verdict"] == "PASS" for r in sel)
        lo, hi = wilson(passes, len(sel))
        per_rate[f"{rate:g}"] = {
            "runs": len(sel),
            "passes": passes,
            "pass_rate": passes / len(sel) if sel else None,
            "pass_rate_ci95": [lo, hi],
            "first_violation_kinds": {
                k: sum(r["violation_kind"] == k for r in sel)
                for k in sorted({r["violation_kind"] or "" for r in sel})
                if k
            },
        }
    out: CampaignSummary = {
        "formation": str(campaign.formation),
        "samples": campaign.samples,
        "seed": campaign.seed,
        "vary": {k: list(v) if isinstance(v, tuple) else v for k, v in campaign.vary.items()},
        "duration": campaign.duration,
        "per_control_rate": per_rate,
    }
    if campaign.links or campaign.gains:
        out["links"] = {k: list(v) if isinstance(v, tuple) else v for k, v in campaign.links.items()}
        out["gains"] = {k: list(v) for k, v in campaign.gains.items()}
        cells = per_condition(rows, campaign)
        out["per_condition"] = cells
        out["tolerance"] = tolerance(cells)
    return out


#: a pass rate at least this is what ``tolerance`` calls holding
HOLDS = 0.95


def _largest(
    group: list[ConditionCell], axis: Literal["link_delay", "link_loss"], fixed: Literal["link_delay", "link_loss"]
) -> float | None:
    """The largest value of ``axis`` up to which every cell passes :data:`HOLDS` (``fixed`` at its least)."""
    least = min((v for c in group if (v := c[fixed]) is not None), default=None)
    line = sorted((c for c in group if c[fixed] == least), key=lambda c: c[axis] or 0.0)
    best = None
    for c in line:
        if (c["pass_rate"] or 0.0) < HOLDS:
            break
        best = c[axis]
    return best


def per_condition(rows: list[CampaignRow], campaign: Campaign) -> list[ConditionCell]:
    """Pass rate and its 95 % interval of every condition of the grids at every control rate."""
    out: list[ConditionCell] = []
    for condition in campaign.conditions():
        for rate in campaign.control_rates:
            sel = [r for r in rows if r["control_rate"] == rate and _condition_values(r) == tuple(condition)]
            passes = sum(r["verdict"] == "PASS" for r in sel)
            lo, hi = wilson(passes, len(sel))
            out.append(
                {
                    "control_rate": rate,
                    **conditions_of(condition),
                    "runs": len(sel),
                    "passes": passes,
                    "pass_rate": passes / len(sel) if sel else None,
                    "pass_rate_ci95": [lo, hi],
                }
            )
    return out


def tolerance(cells: list[ConditionCell]) -> list[Tolerance]:
    """Per group of conditions that differ only in delay and loss: the largest delay at which at least
    :data:`HOLDS` of the runs pass at every delay up to it (at the grid's smallest loss), and the
    largest loss likewise (at the smallest delay); None where even the smallest fails."""
    groups: dict[tuple[float | None, ...], list[ConditionCell]] = {}
    for c in cells:
        key = (c["control_rate"], c["link_jitter"], c["sensor_rate"], c["delta"], c["gamma"])
        groups.setdefault(key, []).append(c)
    out: list[Tolerance] = []
    for (rate, jitter, sensor, delta, gamma), group in groups.items():
        assert rate is not None  # a control rate is always given
        out.append(
            {
                "control_rate": rate,
                "link_jitter": jitter,
                "sensor_rate": sensor,
                "delta": delta,
                "gamma": gamma,
                "largest_delay": _largest(group, "link_delay", "link_loss"),
                "largest_loss": _largest(group, "link_loss", "link_delay"),
            }
        )
    return out


def write_results(out: Path, rows: list[CampaignRow], campaign: Campaign) -> CampaignSummary:
    """runs.csv, summary.json and the figures, each written atomically."""
    rows = sorted(rows, key=_sort_key)
    tmp = out / "runs.csv.tmp"
    with tmp.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(out / "runs.csv")
    summary = summarise(rows, campaign)
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    tmp.replace(out / "summary.json")
    plot_campaign(out, rows, summary)
    if "per_condition" in summary:
        plot_links(out, summary)
    return summary


def plot_campaign(out: Path, rows: list[CampaignRow], summary: CampaignSummary) -> None:
    """pass_rate.png (pass rate vs control rate, 95 % intervals) and worst_margin.png (histograms)."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per = summary["per_control_rate"]
    rates = [float(r) for r in per]
    rate_vals = np.array([per[r]["pass_rate"] or 0.0 for r in per])
    ci = np.array([per[r]["pass_rate_ci95"] for r in per])
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.errorbar(rates, rate_vals, yerr=[rate_vals - ci[:, 0], ci[:, 1] - rate_vals], fmt="o-", capsize=4)
    ax.set_xscale("log")
    ax.set_xlabel("control rate [Hz]")
    ax.set_ylabel("pass rate (95 % CI)")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    runs = max(per[r]["runs"] for r in per)
    ax.set_title(f"{Path(summary['formation']).name}: {runs} random plants per rate")
    fig.tight_layout()
    tmp = out / "pass_rate.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "pass_rate.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for r in rates:
        margins = (
            [m for m in (row["worst_margin_e"], row["worst_margin_psi"], row["worst_margin_v"]) if m is not None]
            for row in rows
            if row["control_rate"] == r
        )
        worst = [min(m) for m in margins if m]  # a run stopped before its first check has no margin
        ax.hist(worst, bins=30, alpha=0.5, label=f"{r:g} Hz")
    ax.axvline(0.0, color="r", lw=1)
    ax.set_xlabel("worst margin over the run (< 0: a funnel was left)")
    ax.set_ylabel("runs")
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = out / "worst_margin.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "worst_margin.png")
    plt.close(fig)


def plot_links(out: Path, summary: CampaignSummary) -> None:
    """link_pass_rate.png: per group of the other conditions (at most 6), the pass rate of every delay and
    loss of the grid, a cell per pair (the number in it), coloured from red (0) to green (1)."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = summary.get("per_condition", [])
    groups: dict[tuple[float | None, ...], list[ConditionCell]] = {}
    for c in cells:
        groups.setdefault((c["control_rate"], c["link_jitter"], c["sensor_rate"], c["delta"], c["gamma"]), []).append(c)
    shown = list(groups.items())[:6]
    cols = min(3, len(shown))
    rows_n = math.ceil(len(shown) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.6 * rows_n), squeeze=False)
    for ax, ((rate, jitter, sensor, delta, gamma), group) in zip(axes.flat, shown):
        delays = sorted({c["link_delay"] or 0.0 for c in group})
        losses = sorted({c["link_loss"] or 0.0 for c in group})
        grid = np.full((len(losses), len(delays)), np.nan)
        for c in group:
            grid[losses.index(c["link_loss"] or 0.0), delays.index(c["link_delay"] or 0.0)] = c["pass_rate"]
        ax.imshow(grid, origin="lower", cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
        for (y, x), value in np.ndenumerate(grid):
            ax.text(x, y, "-" if np.isnan(value) else f"{value:.2f}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(delays)), [f"{d * 1e3:g}" for d in delays], fontsize=7)
        ax.set_yticks(range(len(losses)), [f"{p * 100:g}" for p in losses], fontsize=7)
        ax.set_xlabel("delay [ms]")
        ax.set_ylabel("loss [%]")
        extra = [f"{rate:g} Hz"]
        extra += [f"jitter {jitter * 1e3:g} ms"] if jitter else []
        extra += [f"sensor {sensor:g} Hz"] if sensor else []
        extra += [f"δ {delta:g}"] if delta else []
        extra += [f"γ {gamma:g}"] if gamma else []
        ax.set_title(", ".join(extra), fontsize=9)
    for ax in list(axes.flat)[len(shown) :]:
        ax.axis("off")
    fig.suptitle(f"{Path(summary['formation']).name}: pass rate per delay and loss", fontsize=10)
    fig.tight_layout()
    tmp = out / "link_pass_rate.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "link_pass_rate.png")
    plt.close(fig)


def condition_table(summary: CampaignSummary) -> str:
    """The pass rates of a grid campaign as text, one line per condition, then the tolerances."""

    def fmt(value: float | None, scale: float = 1.0, unit: str = "") -> str:
        return "file" if value is None else f"{value * scale:g}{unit}"

    def sensor(value: float | None) -> str:
        if value is None:  # a grid's null: every control step; no grid: the file's
            return "each step" if summary.get("links") else "file"
        return f"{value:g} Hz"

    lines = ["  rate [Hz]  delay     loss   jitter    sensor   delta  gamma   pass    95 % interval"]
    for c in summary.get("per_condition", []):
        lo, hi = c["pass_rate_ci95"]
        lines.append(
            f"  {c['control_rate']:>9g}  {fmt(c['link_delay'], 1e3, ' ms'):>8}  {fmt(c['link_loss'], 100, ' %'):>6}  "
            f"{fmt(c['link_jitter'], 1e3, ' ms'):>7}  {sensor(c['sensor_rate']):>8}  {fmt(c['delta']):>5}  "
            f"{fmt(c['gamma']):>5}  {c['passes']:>3}/{c['runs']:<3}  {lo:.2f}-{hi:.2f}"
        )
    for t in summary.get("tolerance", []):
        delay = "none" if t["largest_delay"] is None else f"{t['largest_delay'] * 1e3:g} ms"
        loss = "none" if t["largest_loss"] is None else f"{t['largest_loss'] * 100:g} %"
        lines.append(
            f"  holds (≥ {HOLDS:.0%} pass) at {t['control_rate']:g} Hz, jitter {fmt(t['link_jitter'], 1e3, ' ms')}, "
            f"sensor {sensor(t['sensor_rate'])}: largest delay {delay}, largest loss {loss}"
        )
    return "\n".join(lines)
