"""Funnel checks on ground truth and the outputs every run leaves (docs/outputs.md).

Headless runs, ROS 2 runs and bag analyses all fill a :class:`RunRecorder` with samples of
the ground truth (and, where known, the agents' wrenches and velocity-funnel margins), then
call :func:`write_outputs`: ``summary.json``, ``trajectory.npz`` and the paper's three figures.

Margins are the fraction of a funnel left between an error and its nearest bound (1 at zero
error, 0 on the bound, negative outside); see :mod:`formation_msgs_py.funnels`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from formation_msgs_py import funnels
from formation_msgs_py.spec import FormationSpec

VELOCITY_CHANNELS = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Violation kinds that name an edge; every other kind (velocity, measurement, controller,
#: command, plant) names an agent.
EDGE_KINDS = ("distance", "orientation")


class EdgeErrors:
    """e_k and ψ_k of every edge from world poses, and their funnels, vectorised over edges."""

    def __init__(self, spec: FormationSpec) -> None:
        index = {a.id: a.index for a in spec.agents}
        self.spec = spec
        self.tail = np.array([index[e.tail] for e in spec.edges])
        self.head = np.array([index[e.head] for e in spec.edges])
        self.d2 = np.array([e.d_des**2 for e in spec.edges])
        self.R_des = np.array([e.R_des for e in spec.edges])
        self.c_col = np.array([e.c_col for e in spec.edges])
        self.c_con = np.array([e.c_con for e in spec.edges])
        self.names = [e.name for e in spec.edges]
        self._floor_e = np.array([e.rho_e_inf for e in spec.edges]) / np.maximum(self.c_col, self.c_con)
        self._decay_e = np.array([e.decay_e for e in spec.edges])
        self._rho_psi_0 = np.array([e.rho_psi_0 for e in spec.edges])
        self._rho_psi_inf = np.array([e.rho_psi_inf for e in spec.edges])
        self._decay_psi = np.array([e.decay_psi for e in spec.edges])

    def errors(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(e, ψ), each (K,), from p (N,3) and R_world_body (N,3,3); or stacks (T,N,..) -> (T,K)."""
        d = p[..., self.head, :] - p[..., self.tail, :]
        e = np.sum(d * d, axis=-1) - self.d2
        # ψ = ½ tr(I − R_desᵀ R_k2ᵀ R_k1) = ½(3 − Σ (R_k2 R_des)∘R_k1)
        A = R[..., self.head, :, :] @ self.R_des
        psi = 0.5 * (3.0 - np.sum(A * R[..., self.tail, :, :], axis=(-2, -1)))
        return e, psi

    def rho(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(ρ_e, ρ_ψ) of every edge at t: (K,) or (T,K)."""
        t = np.asarray(t, dtype=np.float64)[..., None]
        return (
            funnels.rho(t, 1.0, self._floor_e, self._decay_e),
            funnels.rho(t, self._rho_psi_0, self._rho_psi_inf, self._decay_psi),
        )

    def steady_band(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lower_e, upper_e, upper_psi): the funnels' limits as t → ∞."""
        c_max = np.maximum(self.c_col, self.c_con)
        inf = np.array([e.rho_e_inf for e in self.spec.edges]) / c_max
        return -self.c_col * inf, self.c_con * inf, np.array([e.rho_psi_inf for e in self.spec.edges])


@dataclass
class Violation:
    t: float
    kind: str
    where: str
    channel: str

    def as_dict(self) -> dict[str, Any]:
        key = "edge" if self.kind in EDGE_KINDS else "agent"
        return {"t": self.t, "kind": self.kind, key: self.where, "channel": self.channel}


@dataclass
class RunRecorder:
    """Checks every sample against the funnels; keeps a decimated trajectory for the outputs."""

    spec: FormationSpec
    record_every: int = 1
    mode: str = "headless"
    control_rate: float = 0.0
    samples: int = 0
    first_violation: Violation | None = None
    _rows: dict[str, list[np.ndarray]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.edges = EdgeErrors(self.spec)
        K, N = len(self.spec.edges), len(self.spec.agents)
        self.min_margin_e = np.full(K, np.inf)
        self.min_margin_psi = np.full(K, np.inf)
        self.min_margin_v = np.full(N, np.inf)
        self.peak_force = np.zeros(N)
        self.peak_torque = np.zeros(N)
        self._settle_e: list[float | None] = [None] * K
        self._settle_psi: list[float | None] = [None] * K
        self.band_lo, self.band_hi, self.band_psi = self.edges.steady_band()
        self.t_last = 0.0
        for key in ("t", "p", "R", "v", "u", "e", "psi", "rho_e", "rho_psi"):
            self._rows[key] = []

    # -- per sample ---------------------------------------------------------------------------

    def add(
        self,
        t: float,
        p: np.ndarray,
        R: np.ndarray,
        v: np.ndarray,
        u: np.ndarray | None,
        margin_v: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Check one sample (ground truth at t; ``margin_v`` (N,6) from the agents if known).

        ``u`` None: the wrenches are not known yet; give them with :meth:`set_inputs`.
        """
        e, psi = self.edges.errors(p, R)
        rho_e, rho_psi = self.edges.rho(t)
        xi_e = e / rho_e
        m_e = np.minimum(1.0 + xi_e / self.edges.c_col, 1.0 - xi_e / self.edges.c_con)
        m_psi = 1.0 - psi / rho_psi
        np.minimum(self.min_margin_e, m_e, out=self.min_margin_e)
        np.minimum(self.min_margin_psi, m_psi, out=self.min_margin_psi)
        if self.first_violation is None and (m_e.min() <= 0 or m_psi.min() <= 0):
            k = int(np.argmin(np.minimum(m_e, m_psi)))
            if m_e[k] <= m_psi[k]:
                channel = "collision" if xi_e[k] < 0 else "connectivity"
                self.first_violation = Violation(t, "distance", self.edges.names[k], channel)
            else:
                self.first_violation = Violation(t, "orientation", self.edges.names[k], "psi")
        if margin_v is not None:
            mv = margin_v.min(axis=1)
            np.minimum(self.min_margin_v, mv, out=self.min_margin_v)
            if self.first_violation is None and mv.min() <= 0:
                i = int(np.argmin(mv))
                ch = VELOCITY_CHANNELS[int(np.argmin(margin_v[i]))]
                self.first_violation = Violation(t, "velocity", self.spec.agents[i].id, ch)
        if u is not None:
            np.maximum(self.peak_force, np.linalg.norm(u[:, :3], axis=1), out=self.peak_force)
            np.maximum(self.peak_torque, np.linalg.norm(u[:, 3:], axis=1), out=self.peak_torque)
        in_e = (e >= self.band_lo) & (e <= self.band_hi)
        in_psi = psi <= self.band_psi
        for k in range(len(e)):
            self._settle_e[k] = (self._settle_e[k] if self._settle_e[k] is not None else t) if in_e[k] else None
            self._settle_psi[k] = (self._settle_psi[k] if self._settle_psi[k] is not None else t) if in_psi[k] else None
        if self.samples % self.record_every == 0:
            rows = self._rows
            rows["t"].append(np.float64(t))
            rows["p"].append(np.array(p, dtype=np.float64))
            rows["R"].append(np.array(R, dtype=np.float64))
            rows["v"].append(np.array(v, dtype=np.float64))
            rows["u"].append(np.zeros((len(p), 6)) if u is None else np.array(u, dtype=np.float64))
            rows["e"].append(e)
            rows["psi"].append(psi)
            rows["rho_e"].append(rho_e)
            rows["rho_psi"].append(rho_psi)
        self.samples += 1
        self.t_last = t
        return e, psi

    def add_many(
        self,
        t: np.ndarray,
        p: np.ndarray,
        R: np.ndarray,
        v: np.ndarray,
        u: np.ndarray,
        margin_v: np.ndarray,
        *,
        stop_at_violation: bool = False,
    ) -> int:
        """:meth:`add` of T consecutive samples at once (arrays with a leading axis T); returns how many.

        The same checks in the same order, vectorised over the samples (the run core's path).
        With ``stop_at_violation`` the samples after the first violation are not added.
        """
        e, psi = self.edges.errors(p, R)
        rho_e, rho_psi = self.edges.rho(t)
        xi_e = e / rho_e
        m_e = funnels.margin_e(xi_e, self.edges.c_col, self.edges.c_con)
        m_psi = funnels.margin_psi(psi / rho_psi)
        mv = margin_v.min(axis=2)
        n = len(t)
        if self.first_violation is None:
            bad = np.flatnonzero((m_e.min(axis=1) <= 0) | (m_psi.min(axis=1) <= 0) | (mv.min(axis=1) <= 0))
            if bad.size:
                j = int(bad[0])
                if m_e[j].min() <= 0 or m_psi[j].min() <= 0:
                    k = int(np.argmin(np.minimum(m_e[j], m_psi[j])))
                    if m_e[j, k] <= m_psi[j, k]:
                        channel = "collision" if xi_e[j, k] < 0 else "connectivity"
                        self.first_violation = Violation(float(t[j]), "distance", self.edges.names[k], channel)
                    else:
                        self.first_violation = Violation(float(t[j]), "orientation", self.edges.names[k], "psi")
                else:
                    i = int(np.argmin(mv[j]))
                    ch = VELOCITY_CHANNELS[int(np.argmin(margin_v[j, i]))]
                    self.first_violation = Violation(float(t[j]), "velocity", self.spec.agents[i].id, ch)
                if stop_at_violation:
                    n = j + 1
        np.minimum(self.min_margin_e, m_e[:n].min(axis=0), out=self.min_margin_e)
        np.minimum(self.min_margin_psi, m_psi[:n].min(axis=0), out=self.min_margin_psi)
        np.minimum(self.min_margin_v, mv[:n].min(axis=0), out=self.min_margin_v)
        np.maximum(self.peak_force, np.linalg.norm(u[:n, :, :3], axis=2).max(axis=0), out=self.peak_force)
        np.maximum(self.peak_torque, np.linalg.norm(u[:n, :, 3:], axis=2).max(axis=0), out=self.peak_torque)
        in_e = (e[:n] >= self.band_lo) & (e[:n] <= self.band_hi)
        in_psi = psi[:n] <= self.band_psi
        for settle, inside in ((self._settle_e, in_e), (self._settle_psi, in_psi)):
            for k in range(inside.shape[1]):
                out = np.flatnonzero(~inside[:, k])
                if out.size == 0:
                    settle[k] = settle[k] if settle[k] is not None else float(t[0])
                else:
                    settle[k] = float(t[out[-1] + 1]) if out[-1] + 1 < n else None
        rows = np.flatnonzero((self.samples + np.arange(n)) % self.record_every == 0)
        for key, arr in (("t", t), ("p", p), ("R", R), ("v", v), ("u", u), ("e", e), ("psi", psi)):
            self._rows[key].extend(np.array(arr[rows], dtype=np.float64))
        self._rows["rho_e"].extend(rho_e[rows])
        self._rows["rho_psi"].extend(rho_psi[rows])
        self.samples += n
        self.t_last = float(t[n - 1])
        return n

    def set_inputs(self, u: np.ndarray) -> None:
        """Wrenches (N,6) applied from the sample added last (which was added with ``u=None``).

        Lets a simulator check the funnels of step k while the agents compute, then record u_k.
        """
        np.maximum(self.peak_force, np.linalg.norm(u[:, :3], axis=1), out=self.peak_force)
        np.maximum(self.peak_torque, np.linalg.norm(u[:, 3:], axis=1), out=self.peak_torque)
        if (self.samples - 1) % self.record_every == 0:
            self._rows["u"][-1] = np.array(u, dtype=np.float64)

    def fault(self, t: float, kind: str, agent: str, channel: str) -> None:
        """Record a fault that is not a funnel check (e.g. a missing measurement)."""
        if self.first_violation is None:
            self.first_violation = Violation(t, kind, agent, channel)

    # -- results ------------------------------------------------------------------------------

    @property
    def funnels_held(self) -> bool:
        return self.first_violation is None

    def worst_margin(self) -> float:
        vals = [self.min_margin_e.min(), self.min_margin_psi.min()]
        if np.isfinite(self.min_margin_v).any():
            vals.append(self.min_margin_v.min())
        return float(min(vals))

    def arrays(self) -> dict[str, np.ndarray]:
        """The decimated trajectory (docs/outputs.md)."""
        return {k: np.array(v) for k, v in self._rows.items()}

    def summary(
        self, *, wall_time: float, duration: float | None = None, extra: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        duration = self.t_last if duration is None else duration

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        out: dict[str, Any] = {
            "formation": self.spec.name,
            "formation_file": Path(self.spec.source).name,
            "mode": self.mode,
            "control_rate": self.control_rate,
            "duration": duration,
            "samples": self.samples,
            "wall_time": wall_time,
            "real_time_factor": duration / wall_time if wall_time > 0 else None,
            "funnels_held": self.funnels_held,
            "first_violation": None if self.first_violation is None else self.first_violation.as_dict(),
            "worst_margin": num(self.worst_margin()),
            "edges": {
                name: {
                    "min_margin_e": num(self.min_margin_e[k]),
                    "min_margin_psi": num(self.min_margin_psi[k]),
                    "settle_time_e": self._settle_e[k],
                    "settle_time_psi": self._settle_psi[k],
                }
                for k, name in enumerate(self.edges.names)
            },
            "agents": {
                a.id: {
                    "peak_force": float(self.peak_force[i]),
                    "peak_torque": float(self.peak_torque[i]),
                    "min_margin_v": num(self.min_margin_v[i]),
                }
                for i, a in enumerate(self.spec.agents)
            },
        }
        if extra:
            out.update(extra)
        return out


def write_outputs(out_dir: Path, recorder: RunRecorder, summary: dict[str, Any], *, plots: bool = True) -> None:
    """Write summary.json, trajectory.npz and (unless ``plots`` is false) the figures (:mod:`formation_sim.figures`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    arrays = recorder.arrays()
    np.savez(out_dir / "trajectory.npz", **arrays)
    if plots:
        from formation_sim.figures import plot_run  # matplotlib only when figures are wanted

        plot_run(out_dir, recorder.spec, arrays)


def report_animation(out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray]) -> Path:
    """Write OUT/animation.gif (:mod:`formation_sim.animation`) and print where and how long it took."""
    from formation_sim.animation import write_animation

    path, frames, wall = write_animation(out_dir, spec, arrays)
    print(f"animation: {path} ({frames} frames, written in {wall:.1f} s)", flush=True)
    return path


def format_summary(summary: dict[str, Any]) -> str:
    """A short human-readable summary of a run (printed by every command)."""
    lines = [
        f"formation {summary['formation']} ({summary['mode']}, control {summary['control_rate']:g} Hz, "
        f"{summary['duration']:g} s simulated in {summary['wall_time']:.2f} s wall, "
        f"real-time factor {summary['real_time_factor'] or 0:.3g})"
    ]
    fv = summary["first_violation"]
    if summary["funnels_held"]:
        lines.append(f"PASS: every funnel held (worst margin {summary['worst_margin']:.3f})")
    else:
        where = fv.get("edge") or fv.get("agent")
        lines.append(f"FAIL: first violation at t={fv['t']:.4f} s: {fv['kind']} {where} ({fv['channel']})")
    lines.append("  edge     min margin e   min margin psi   settle e [s]   settle psi [s]")
    for name, s in summary["edges"].items():
        lines.append(
            f"  {name:<8} {_f(s['min_margin_e']):>12}   {_f(s['min_margin_psi']):>14}   "
            f"{_f(s['settle_time_e']):>12}   {_f(s['settle_time_psi']):>14}"
        )
    lines.append("  agent    peak force [N]   peak torque [N·m]   min margin v")
    for aid, s in summary["agents"].items():
        lines.append(f"  {aid:<8} {s['peak_force']:>14.4g}   {s['peak_torque']:>17.4g}   {_f(s['min_margin_v']):>12}")
    return "\n".join(lines)


def _f(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


