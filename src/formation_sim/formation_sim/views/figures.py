"""The run's figures, like the paper's (errors in their funnels, control inputs), from trajectory.npz.

Edges and agents in a grid of at most two (edges) or three (agents) columns, so that the text stays
readable at a page's width; above the panels, the run's verdict with its short reason and the
simulated time covered of the requested duration (the figure's title, coloured by the verdict, and
the PNG's ``Description``: :func:`formation_sim.views.outputs.run_caption`), then one legend per
figure (every panel draws the same kinds of line):

- ``errors.png``: per edge k, e_k = ‖p_k2 − p_k1‖² − d_k² [m²] with its two bounds C_con·ρ_e (upper,
  dashed) and −C_col·ρ_e (lower, dash-dotted) over the whole run, and below it the second half of
  the run with its own scale, where the steady band (ρ_e∞-wide) is visible;
- ``orientation_errors.png``: per edge, ψ_k = ½ tr(I − R_desᵀ R_k2ᵀ R_k1) (dimensionless: 0 when the
  relative orientation is the desired one, 2 at a rotation by π from it) with its bound ρ_ψ, laid
  out the same way;
- ``inputs.png``: per agent, the body-frame force (f_x, f_y, f_z) [N] above the torque
  (τ_x, τ_y, τ_z) [N·m];
- ``velocity_errors.png``: per agent, e_v = v_i − v_i,des per channel inside ±ρ_v, linear [m/s]
  and angular [rad/s]. The agents' own e_v uses their noisy velocity; here it is recomputed from
  the recorded ground truth (the same controller on noise-free relative poses and velocity), so it
  differs by the noise;
- ``clearance.png``: per agent, its clearance to the nearest other body (the distance between
  centres minus both radii [m], every body, neighbour or not: the judge's
  :class:`formation_sim.core.judge.Pairs`), with contact (clearance ≤ 0) shaded;
- ``link_ages.png`` (runs with a link model only): the age [ms] of the sample each link's receiver
  holds, per channel (relative poses, velocities, wrenches), with the age past which it is missing
  (the agents' ``measurement_timeout``, the plant's ``command_timeout``).

Arrays as in trajectory.npz (agents and edges in file order).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from formation_agent.controller import AgentController
from formation_core import funnels
from formation_core.formation import EdgeSpec, FormationSpec, agent_view
from formation_sim.core.judge import Pairs

if TYPE_CHECKING:  # matplotlib is imported when figures are drawn, not with this module
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: the files :func:`plot_run` writes, in order, and with a link model :data:`LINK_FIGURE` after them
FIGURES = ("errors.png", "orientation_errors.png", "inputs.png", "velocity_errors.png", "clearance.png")
LINK_FIGURE = "link_ages.png"
VELOCITY_LABELS = ("$v_x$", "$v_y$", "$v_z$", r"$\omega_x$", r"$\omega_y$", r"$\omega_z$")
COMPONENT_COLOURS = ("C0", "C1", "C2")
ZOOM_FROM = 0.5  # the insets show the second half of the run, over which they sit
#: the colour of each verdict in the caption
VERDICT_COLOURS = {"PASS": "#1a7f37", "FAIL": "#c62828", "INCOMPLETE": "#b35c00"}
CAPTION_PT = 11
#: inches: one caption line at CAPTION_PT with its leading, the gap above the caption, and the mean
#: width of a character (DejaVu Sans, bold, at 11 pt; the caption is wrapped to the figure's width)
CAPTION_LINE, CAPTION_GAP, CAPTION_CHAR = 0.22, 0.08, 0.1


@dataclass(frozen=True)
class Caption:
    """What every figure of a run says above its panels: verdict, reason and run length, in the verdict's colour."""

    text: str
    colour: str


def _caption_height(fig: Figure) -> float:
    """Inches the caption (the figure's suptitle, wrapped) takes at the top of ``fig``."""
    return CAPTION_GAP + CAPTION_LINE * (fig.get_suptitle().count("\n") + 1)


def _grid(
    plt: ModuleType,
    rows: int,
    cols: int,
    width: float,
    height: float,
    caption: Caption,
    *,
    top: float = 0.35,
    **kwargs: Any,
) -> tuple[Figure, Any]:
    """``plt.subplots`` of rows x cols panels, each cell ``width`` x ``height`` inches, with fixed margins,
    and ``caption`` above them, wrapped to the figure's width.

    Margins and gaps are set in inches (room for the caption, a title above each panel, tick labels
    and an axis label left and below), not computed by ``tight_layout``: that costs a second drawing
    of every text, about half the CPU of a run's figures.
    """
    left, right, bottom, gap_w, gap_h = 0.75, 0.15, 0.5, 0.75, 0.7
    fig_w = width * cols
    text = textwrap.fill(caption.text, width=max(20, int((fig_w - 0.3) / CAPTION_CHAR)))
    top += CAPTION_GAP + CAPTION_LINE * (text.count("\n") + 1)
    fig_h = height * rows + top
    axes_w = (fig_w - left - right - gap_w * (cols - 1)) / cols
    axes_h = (fig_h - top - bottom - gap_h * (rows - 1)) / rows
    fig, axes = plt.subplots(rows, cols, figsize=(fig_w, fig_h), squeeze=False, **kwargs)
    fig.subplots_adjust(
        left=left / fig_w,
        right=1 - right / fig_w,
        top=1 - top / fig_h,
        bottom=bottom / fig_h,
        wspace=gap_w / axes_w,
        hspace=gap_h / axes_h,
    )
    fig.suptitle(
        text, y=1 - CAPTION_GAP / fig_h, va="top", fontsize=CAPTION_PT, fontweight="bold", color=caption.colour
    )
    return fig, axes


def _panels(
    plt: ModuleType,
    n: int,
    caption: Caption,
    *,
    stacked: int = 1,
    max_cols: int = 4,
    width: float = 4.2,
    height: float = 3.0,
    top: float = 0.35,
) -> tuple[Figure, list[list[Axes]]]:
    """A grid of n cells (at most ``max_cols`` per row), each a column of ``stacked`` panels sharing t;
    returns the figure and, per cell, its list of panels."""
    cols = min(n, max_cols)
    rows = math.ceil(n / cols) * stacked
    fig, axes = _grid(plt, rows, cols, width, height, caption, top=top)
    cells = [[axes[(k // cols) * stacked + j][k % cols] for j in range(stacked)] for k in range(n)]
    for k in range(n, rows // stacked * cols):
        for j in range(stacked):
            axes[(k // cols) * stacked + j][k % cols].axis("off")
    return fig, cells


def _zoom(ax: Axes, t: np.ndarray, series: list[tuple[np.ndarray, dict]]) -> None:
    """The second half of the run (where the steady band is) in its own panel, y-limits fitted to it."""
    sel = t >= t[0] + ZOOM_FROM * (t[-1] - t[0]) if len(t) else np.zeros(0, dtype=bool)
    if np.count_nonzero(sel) < 2:
        sel = np.ones(len(t), dtype=bool)
    lo, hi = np.inf, -np.inf
    for y, style in series:
        ax.plot(t[sel], y[sel], **style)
        lo, hi = min(lo, float(np.min(y[sel]))), max(hi, float(np.max(y[sel])))
    if np.isfinite(lo) and np.isfinite(hi):
        pad = 0.1 * (hi - lo) if hi > lo else 0.1
        ax.set_ylim(lo - pad, hi + pad)
    ax.grid(alpha=0.3)


def _figure_legend(fig: Figure, handles: list, ncol: int) -> None:
    """One legend for the whole figure, under the caption and above the panels: every panel draws the
    same kinds of line."""
    y = 1 - _caption_height(fig) / fig.get_figheight()
    fig.legend(handles=handles, loc="upper center", ncol=ncol, fontsize=9, frameon=False, bbox_to_anchor=(0.5, y))


def _save(fig: Figure, path: Path) -> Path:
    # the caption also as the PNG's text: a viewer or a script reads the verdict without the pixels
    fig.savefig(path, dpi=110, metadata={"Description": " ".join(fig.get_suptitle().split("\n"))})
    return path


def plot_run(out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption) -> list[Path]:
    """errors.png, orientation_errors.png, inputs.png and velocity_errors.png in ``out_dir``, each
    captioned with the run's verdict and run length (:func:`formation_sim.views.outputs.run_caption`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # titles at the top of their axes: matplotlib's default (axes.titley None) places each one
    # clear of top decorations that these figures do not have, at the price of laying out every
    # tick label once more (~1/6 of the figures' time)
    with plt.rc_context({"axes.titley": 1.0}):
        return _plot_all(plt, out_dir, spec, arrays, caption)


def _plot_all(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> list[Path]:
    paths = [
        _distance_errors(plt, out_dir, spec, arrays, caption),
        _orientation_errors(plt, out_dir, spec, arrays, caption),
        _inputs(plt, out_dir, spec, arrays, caption),
        _velocity_errors(plt, out_dir, spec, arrays, caption),
        _clearance(plt, out_dir, spec, arrays, caption),
    ]
    if "link_age" in arrays and arrays["link_age"].size:
        paths.append(_link_ages(plt, out_dir, spec, arrays, caption))
    return paths


def _link_ages(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from formation_core.formation import simulator_view
    from formation_sim.core.links import CHANNELS, link_names

    t, ages = arrays["t"], arrays["link_age"] * 1e3
    names = link_names(simulator_view(spec))
    timeouts = {
        "poses": max(a.controller.measurement_timeout for a in spec.agents),
        "velocity": max(a.controller.measurement_timeout for a in spec.agents),
        "wrench": spec.simulation.command_timeout,
    }
    fig, axes = _grid(plt, 3, 1, 9.0, 2.4, caption, top=0.75)
    first = 0
    for row, channel in enumerate(CHANNELS):
        ax = axes[row][0]
        for j, name in enumerate(names[channel]):
            ax.plot(t, ages[:, first + j], lw=0.9, label=name, color=f"C{j % 10}", drawstyle="steps-post")
        first += len(names[channel])
        ax.axhline(timeouts[channel] * 1e3, color="#c62828", lw=0.8, ls="--")
        ax.set_ylabel("age [ms]")
        what = {"poses": "relative poses (observer->neighbour)", "velocity": "velocities", "wrench": "wrenches"}
        ax.set_title(f"{what[channel]}: age of the sample held (dashed: missing beyond)", fontsize=10)
        ax.grid(alpha=0.3)
        if len(names[channel]) <= 12:
            ax.legend(fontsize=7, ncol=6, loc="upper right")
    axes[-1][0].set_xlabel("t [s]")
    path = _save(fig, out_dir / LINK_FIGURE)
    plt.close(fig)
    return path


UPPER: dict[str, Any] = {"color": "C3", "ls": "--", "lw": 1.0}
LOWER: dict[str, Any] = {"color": "C2", "ls": "-.", "lw": 1.0}
ERROR: dict[str, Any] = {"color": "C0", "lw": 1.3}
#: a cell of an edge figure: the whole run above, its second half (the steady band) below
EDGE_CELL: dict[str, Any] = {"stacked": 2, "max_cols": 2, "width": 4.4, "height": 2.1, "top": 0.75}


def _edge_figure(
    plt: ModuleType,
    spec: FormationSpec,
    t: np.ndarray,
    per_edge: Callable[[int, EdgeSpec], list],
    title: str,
    ylabel: str,
    legend: list,
    caption: Caption,
) -> Figure:
    """A 2-column grid with one cell per edge; ``per_edge(k)`` gives the cell's (y, style) series."""
    fig, cells = _panels(plt, len(spec.edges), caption, **EDGE_CELL)
    for k, (e, (ax, ax_zoom)) in enumerate(zip(spec.edges, cells)):
        series = per_edge(k, e)
        for y, style in series:
            ax.plot(t, y, **style)
        ax.set_title(f"edge {e.tail}-{e.head}: {title}", fontsize=10)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        _zoom(ax_zoom, t, series)
        ax_zoom.set_title(f"edge {e.tail}-{e.head}, second half of the run", fontsize=9)
        ax_zoom.set_xlabel("t [s]")
        ax_zoom.set_ylabel(ylabel)
    _figure_legend(fig, legend, ncol=len(legend))
    return fig


def _distance_errors(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from matplotlib.lines import Line2D

    def per_edge(k: int, e: EdgeSpec) -> list:
        rho = arrays["rho_e"][:, k]
        return [(arrays["e"][:, k], ERROR), (e.c_con * rho, UPPER), (-e.c_col * rho, LOWER)]

    legend = [
        Line2D([], [], **ERROR, label=r"$e_k = \|p_{k_2} - p_{k_1}\|^2 - d_k^2$"),
        Line2D([], [], **UPPER, label=r"$C_{con}\,\rho_e$ (connectivity bound)"),
        Line2D([], [], **LOWER, label=r"$-C_{col}\,\rho_e$ (collision bound)"),
    ]
    fig = _edge_figure(plt, spec, arrays["t"], per_edge, "distance error", "e [m²]", legend, caption)
    path = _save(fig, out_dir / "errors.png")
    plt.close(fig)
    return path


def _orientation_errors(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from matplotlib.lines import Line2D

    def per_edge(k: int, e: EdgeSpec) -> list:
        return [(arrays["psi"][:, k], ERROR), (arrays["rho_psi"][:, k], UPPER)]

    legend = [
        Line2D([], [], **ERROR, label=r"$\psi_k = \frac{1}{2}\,\mathrm{tr}(I - R_{des}^\top R_{k_2}^\top R_{k_1})$"),
        Line2D([], [], **UPPER, label=r"$\rho_\psi$ (bound)"),
    ]
    ylabel = r"$\psi$ [-] (0 aligned, 2 at $\pi$)"
    fig = _edge_figure(plt, spec, arrays["t"], per_edge, "orientation error", ylabel, legend, caption)
    path = _save(fig, out_dir / "orientation_errors.png")
    plt.close(fig)
    return path


def _inputs(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from matplotlib.lines import Line2D

    t, u = arrays["t"], arrays["u"]
    fig, cells = _panels(plt, len(spec.agents), caption, stacked=2, max_cols=3, width=3.6, height=2.2, top=0.7)
    for i, (a, (ax_f, ax_t)) in enumerate(zip(spec.agents, cells)):
        for ax, lo, what, unit in ((ax_f, 0, "force", "N"), (ax_t, 3, "torque", "N·m")):
            for c in range(3):
                ax.plot(t, u[:, i, lo + c], color=COMPONENT_COLOURS[c], lw=1.0)
            ax.set_title(f"agent {a.id}: body {what}", fontsize=10)
            ax.set_ylabel(f"{what} [{unit}]")
            ax.grid(alpha=0.3)
        ax_t.set_xlabel("t [s]")
    legend = [
        Line2D([], [], color=COMPONENT_COLOURS[c], lw=1.0, label=f"$f_{axis}$, $\\tau_{axis}$ (body {axis})")
        for c, axis in enumerate("xyz")
    ]
    _figure_legend(fig, legend, ncol=3)
    path = _save(fig, out_dir / "inputs.png")
    plt.close(fig)
    return path


def _velocity_errors(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from matplotlib.lines import Line2D

    t = arrays["t"]
    e_v, rho_v = velocity_errors(spec, arrays)
    n = len(spec.agents)
    fig, axes = _grid(plt, n, 2, 4.5, 2.2, caption, top=0.75, sharex=True)
    quantities = (("linear", "m/s"), ("angular", "rad/s"))
    for i, a in enumerate(spec.agents):
        for half, (ax, (kind, unit)) in enumerate(zip(axes[i], quantities)):
            for c in range(3 * half, 3 * half + 3):
                colour = COMPONENT_COLOURS[c % 3]
                ax.plot(t, e_v[:, i, c], color=colour, lw=1.0)
                ax.plot(t, rho_v[:, i, c], color=colour, lw=0.8, ls="--")
                ax.plot(t, -rho_v[:, i, c], color=colour, lw=0.8, ls="--")
            ax.set_title(f"agent {a.id}: {kind} velocity error", fontsize=10)
            ax.set_ylabel(f"{kind} $e_v$ [{unit}]")
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    legend = [
        *(
            Line2D([], [], color=COMPONENT_COLOURS[c], lw=1.0, label=f"{VELOCITY_LABELS[c]}, {VELOCITY_LABELS[c + 3]}")
            for c in range(3)
        ),
        Line2D([], [], color="0.3", lw=0.8, ls="--", label=r"$\pm\rho_v$ (bounds, dashed)"),
    ]
    _figure_legend(fig, legend, ncol=4)
    path = _save(fig, out_dir / "velocity_errors.png")
    plt.close(fig)
    return path


def nearest_clearances(spec: FormationSpec, p: np.ndarray) -> np.ndarray:
    """(T,N): each agent's clearance [m] to its nearest other body at world positions p (T,N,3)."""
    pairs = Pairs(spec)
    clearance = pairs.clearances(p)  # (T,P)
    nearest = np.full((len(p), len(spec.agents)), np.inf)
    for k, (i, j) in enumerate(zip(pairs.i.tolist(), pairs.j.tolist())):
        np.minimum(nearest[:, i], clearance[:, k], out=nearest[:, i])
        np.minimum(nearest[:, j], clearance[:, k], out=nearest[:, j])
    return nearest


def _clearance(
    plt: ModuleType, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], caption: Caption
) -> Path:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    t = arrays["t"]
    nearest = nearest_clearances(spec, arrays["p"]) if len(spec.agents) > 1 else np.zeros((len(t), 1))
    fig, axes = _grid(plt, 1, 1, 9.0, 3.2, caption, top=0.75)
    ax = axes[0][0]
    for i, a in enumerate(spec.agents):
        ax.plot(t, nearest[:, i], lw=1.0, label=f"agent {a.id}")
    ax.axhline(0.0, color="#c62828", lw=0.8)
    low = min(float(nearest.min(initial=0.0)), 0.0)
    ax.axhspan(low - 0.05 * (1 + abs(low)), 0.0, color="#c62828", alpha=0.12)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("clearance to the nearest body [m]")
    ax.set_title("every body's clearance to its nearest other body (distance − both radii)", fontsize=10)
    ax.grid(alpha=0.3)
    handles: list[Any] = [
        Line2D([], [], color=f"C{i % 10}", lw=1.0, label=f"agent {a.id}") for i, a in enumerate(spec.agents)
    ]
    handles.append(Patch(color="#c62828", alpha=0.12, label="contact (clearance ≤ 0)"))
    _figure_legend(fig, handles[:20] + handles[-1:] if len(handles) > 21 else handles, ncol=min(6, len(handles)))
    path = _save(fig, out_dir / "clearance.png")
    plt.close(fig)
    return path


def velocity_errors(spec: FormationSpec, arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(e_v, ρ_v), each (T,N,6): the controller on the recorded ground truth (noise-free)."""
    t, p, R, v = arrays["t"], arrays["p"], arrays["R"], arrays["v"]
    index = {a.id: a.index for a in spec.agents}
    e_v = np.zeros(v.shape)
    rho_v = np.zeros(v.shape)
    for a in spec.agents:
        ctrl = AgentController(agent_view(spec, a.id))
        i = index[a.id]
        vf = ctrl.view.controller.velocity_funnel
        others = [index[j] for j in ctrl.view.neighbours]
        # every sample's relative poses at once: p_i_j_in_i = R_iᵀ(p_j − p_i), R_i_j = R_iᵀ R_j
        p_rel = np.einsum("tba,tnb->tna", R[:, i], p[:, others] - p[:, i : i + 1])
        R_rel = np.einsum("tba,tnbc->tnac", R[:, i], R[:, others])
        xi_v = np.zeros((len(t), 6))
        for s in range(len(t)):
            rel = dict(zip(ctrl.view.neighbours, zip(p_rel[s], R_rel[s])))
            xi_v[s] = ctrl.compute(float(t[s]), rel, v[s, i]).xi_v
        # ρ_v0 and t0 are set at the first step and kept (no reset offline)
        rho = funnels.rho((t - ctrl.t0)[:, None], np.array(ctrl.rho_v0), np.array(vf.rho_inf), np.array(vf.decay))
        rho_v[:, i] = rho
        e_v[:, i] = xi_v * rho
    return e_v, rho_v
