"""The run's figures, like the paper's (errors in their funnels, control inputs), from trajectory.npz.

- ``errors.png``: per edge k, e_k [m²] with its two bounds C_con·ρ_e (upper, dashed) and
  −C_col·ρ_e (lower, dash-dotted); an inset zooms on the second half of the run, where the steady
  band (ρ_e∞-wide) is visible;
- ``orientation_errors.png``: per edge, ψ_k with its bound ρ_ψ, and the same zoomed inset;
- ``inputs.png``: per agent, the body-frame force (f_x, f_y, f_z) [N] above the torque
  (τ_x, τ_y, τ_z) [N·m];
- ``velocity_errors.png``: per agent, e_v = v_i − v_i,des per channel inside ±ρ_v. The agents'
  own e_v uses their noisy velocity; here it is recomputed from the recorded ground truth (the
  same controller on noise-free relative poses and velocity), so it differs by the noise.

Each panel has its own legend, in its upper right corner: the transients (and the lower bound's
start at −C_col) are at the left, the converged part at the bottom right is under the inset.
Arrays as in trajectory.npz (agents and edges in file order).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from formation_agent.controller import AgentController
from formation_msgs_py import funnels
from formation_msgs_py.spec import FormationSpec, agent_view

VELOCITY_LABELS = ("$v_x$", "$v_y$", "$v_z$", r"$\omega_x$", r"$\omega_y$", r"$\omega_z$")
COMPONENT_COLOURS = ("C0", "C1", "C2")
ZOOM_FROM = 0.5  # the insets show the second half of the run, over which they sit


def _grid(plt, rows: int, cols: int, width: float, height: float, **kwargs):
    """``plt.subplots`` of rows x cols panels, each cell ``width`` x ``height`` inches, with fixed margins.

    Margins and gaps are set in inches (room for a title above each panel, tick labels and an axis
    label left and below), not computed by ``tight_layout``: that costs a second drawing of every
    text, about half the CPU of a run's figures (BENCHMARKS.md, issue 13).
    """
    left, right, top, bottom, gap_w, gap_h = 0.75, 0.15, 0.35, 0.5, 0.75, 0.7
    fig_w, fig_h = width * cols, height * rows
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
    return fig, axes


def _panels(plt, n: int, *, stacked: int = 1, max_cols: int = 4, width: float = 4.2, height: float = 3.0):
    """A grid of n cells (at most ``max_cols`` per row), each a column of ``stacked`` panels sharing t;
    returns the figure and, per cell, its list of panels."""
    cols = min(n, max_cols)
    rows = math.ceil(n / cols) * stacked
    fig, axes = _grid(plt, rows, cols, width, height)
    cells = [[axes[(k // cols) * stacked + j][k % cols] for j in range(stacked)] for k in range(n)]
    for k in range(n, rows // stacked * cols):
        for j in range(stacked):
            axes[(k // cols) * stacked + j][k % cols].axis("off")
    return fig, cells


def _zoom_inset(ax, t: np.ndarray, series: list[tuple[np.ndarray, dict]]) -> None:
    """An inset of the last part of the run, y-limits fitted to what is drawn there."""
    if len(t) < 10:
        return
    sel = t >= t[0] + ZOOM_FROM * (t[-1] - t[0])
    ins = ax.inset_axes([0.5, 0.1, 0.47, 0.42])
    lo, hi = np.inf, -np.inf
    for y, style in series:
        ins.plot(t[sel], y[sel], **style)
        lo, hi = min(lo, float(np.min(y[sel]))), max(hi, float(np.max(y[sel])))
    pad = 0.1 * (hi - lo) if hi > lo else 0.1
    ins.set_ylim(lo - pad, hi + pad)
    ins.set_xlim(t[sel][0], t[sel][-1])
    ins.tick_params(labelsize=6)
    ins.grid(alpha=0.3)
    ins.set_title("zoom: steady band", fontsize=6, pad=2)


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=110)
    return path


def plot_run(out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray]) -> list[Path]:
    """errors.png, orientation_errors.png, inputs.png and velocity_errors.png in ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # titles at the top of their axes: matplotlib's default (axes.titley None) places each one
    # clear of top decorations that these figures do not have, at the price of laying out every
    # tick label once more (~1/6 of the figures' time)
    with plt.rc_context({"axes.titley": 1.0}):
        return _plot_all(plt, out_dir, spec, arrays)


def _plot_all(plt, out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray]) -> list[Path]:
    t = arrays["t"]
    paths = []
    upper = {"color": "C3", "ls": "--", "lw": 1.0}
    lower = {"color": "C2", "ls": "-.", "lw": 1.0}
    fig, cells = _panels(plt, len(spec.edges))
    for k, (e, (ax,)) in enumerate(zip(spec.edges, cells)):
        series = [
            (arrays["e"][:, k], {"color": "C0", "lw": 1.3, "label": f"$e_{{{e.tail}{e.head}}}$"}),
            (e.c_con * arrays["rho_e"][:, k], {**upper, "label": r"$C_{con}\,\rho_e$ (connectivity)"}),
            (-e.c_col * arrays["rho_e"][:, k], {**lower, "label": r"$-C_{col}\,\rho_e$ (collision)"}),
        ]
        for y, style in series:
            ax.plot(t, y, **style)
        ax.set_title(f"edge {e.tail}-{e.head}: distance error", fontsize=9)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("e [m²]")
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
        _zoom_inset(ax, t, [(y, {k2: v for k2, v in s.items() if k2 != "label"}) for y, s in series])
    paths.append(_save(fig, out_dir / "errors.png"))
    plt.close(fig)

    fig, cells = _panels(plt, len(spec.edges))
    for k, (e, (ax,)) in enumerate(zip(spec.edges, cells)):
        series = [
            (arrays["psi"][:, k], {"color": "C0", "lw": 1.3, "label": rf"$\psi_{{{e.tail}{e.head}}}$"}),
            (arrays["rho_psi"][:, k], {**upper, "label": r"$\rho_\psi$"}),
        ]
        for y, style in series:
            ax.plot(t, y, **style)
        ax.set_title(f"edge {e.tail}-{e.head}: orientation error", fontsize=9)
        ax.set_xlabel("t [s]")
        ax.set_ylabel(r"$\psi$")
        ax.set_ylim(-0.05, 2.05)
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
        _zoom_inset(ax, t, [(y, {k2: v for k2, v in s.items() if k2 != "label"}) for y, s in series])
    paths.append(_save(fig, out_dir / "orientation_errors.png"))
    plt.close(fig)

    u = arrays["u"]
    fig, cells = _panels(plt, len(spec.agents), stacked=2, max_cols=5, width=3.6, height=2.4)
    for i, (a, (ax_f, ax_t)) in enumerate(zip(spec.agents, cells)):
        for ax, lo, symbol, what, unit in ((ax_f, 0, "f", "force", "N"), (ax_t, 3, r"\tau", "torque", "N·m")):
            for c, axis in enumerate("xyz"):
                ax.plot(t, u[:, i, lo + c], color=COMPONENT_COLOURS[c], lw=1.0, label=f"${symbol}_{axis}$")
            ax.set_title(f"agent {a.id}: body {what}", fontsize=9)
            ax.set_ylabel(f"{what} [{unit}]")
            ax.legend(fontsize=7, ncol=3, loc="upper right")
            ax.grid(alpha=0.3)
        ax_t.set_xlabel("t [s]")
    paths.append(_save(fig, out_dir / "inputs.png"))
    plt.close(fig)

    e_v, rho_v = velocity_errors(spec, arrays)
    n = len(spec.agents)
    fig, axes = _grid(plt, n, 2, 4.5, 2.3, sharex=True)
    for i, a in enumerate(spec.agents):
        for half, (ax, unit) in enumerate(zip(axes[i], ("m/s", "rad/s"))):
            for c in range(3 * half, 3 * half + 3):
                colour = COMPONENT_COLOURS[c % 3]
                ax.plot(t, e_v[:, i, c], color=colour, lw=1.0, label=f"$e$ {VELOCITY_LABELS[c]}")
                ax.plot(t, rho_v[:, i, c], color=colour, lw=0.8, ls="--", label=r"$\pm\rho_v$")
                ax.plot(t, -rho_v[:, i, c], color=colour, lw=0.8, ls="--")
            ax.set_title(f"agent {a.id}: {'linear' if half == 0 else 'angular'} velocity error", fontsize=9)
            ax.set_ylabel(unit)
            ax.legend(fontsize=6, ncol=3, loc="upper right")
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    paths.append(_save(fig, out_dir / "velocity_errors.png"))
    plt.close(fig)
    return paths


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
