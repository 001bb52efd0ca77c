"""The judge of a run: e_k, ψ_k and their funnel margins from world poses, the first violation, settle
times and the worst margin (docs/outputs.md).

:func:`judge` is a pure function over trajectory arrays (t, p, R and, where known, the agents'
velocity-funnel margins); :class:`Judge` is the same check fed in time order, one sample or a
stack of samples at a time.

Margins are the fraction of a funnel left between an error and its nearest bound (1 at zero
error, 0 on the bound, negative outside); see :mod:`formation_msgs_py.funnels`. A fault (a
missing measurement, a zeroed wrench, a saturated controller) is counted, never a violation:
only the funnels decide FAIL, and missing data makes a run INCOMPLETE, never FAIL.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from formation_msgs_py import funnels
from formation_msgs_py.spec import FormationSpec

VELOCITY_CHANNELS = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Violation kinds that name an edge; ``velocity`` names an agent.
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


class CheckedSteps(NamedTuple):
    """The check of every sample so far, made by the run core itself (formation_sim.core.loop, compiled,
    with :class:`Judge`'s rules): running minimum margins per edge (K,) and agent (N,), settle
    times (K,) (NaN: none), peak force and torque per agent (N,)."""

    min_margin_e: np.ndarray
    min_margin_psi: np.ndarray
    min_margin_v: np.ndarray
    settle_e: np.ndarray
    settle_psi: np.ndarray
    peak_force: np.ndarray
    peak_torque: np.ndarray


@dataclass(frozen=True)
class Violation:
    """The first sample outside a funnel: time [s], kind, edge or agent, channel."""

    t: float
    kind: str
    where: str
    channel: str

    def as_dict(self) -> dict[str, Any]:
        key = "edge" if self.kind in EDGE_KINDS else "agent"
        return {"t": self.t, "kind": self.kind, key: self.where, "channel": self.channel}


@dataclass
class EdgeSample:
    """e, ψ and their funnels at one sample or a stack of samples ((K,) or (T,K))."""

    e: np.ndarray
    psi: np.ndarray
    rho_e: np.ndarray
    rho_psi: np.ndarray


class Judge:
    """Every funnel checked on ground truth, fed in time order (one sample or a (T,…) stack).

    Keeps the minimum margins, the first violation and the settle times (the first time from
    which an error stays inside its funnel's steady-state band until the last sample fed).
    """

    def __init__(self, spec: FormationSpec) -> None:
        self.spec = spec
        self.edges = EdgeErrors(spec)
        K, N = len(spec.edges), len(spec.agents)
        self.min_margin_e = np.full(K, np.inf)
        self.min_margin_psi = np.full(K, np.inf)
        self.min_margin_v = np.full(N, np.inf)
        self.first_violation: Violation | None = None
        self.settle_e: list[float | None] = [None] * K
        self.settle_psi: list[float | None] = [None] * K
        self.band_lo, self.band_hi, self.band_psi = self.edges.steady_band()
        self.samples = 0
        self.t_first: float | None = None
        self.t_last: float | None = None

    def update(
        self,
        t: np.ndarray | float,
        p: np.ndarray,
        R: np.ndarray,
        margin_v: np.ndarray | None = None,
    ) -> EdgeSample:
        """Check samples at t ((T,) or scalar) of p (…,N,3), R (…,N,3,3); margin_v (…,N,6) if known."""
        single = np.ndim(t) == 0
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        p = np.asarray(p, dtype=np.float64).reshape(len(t), -1, 3)
        R = np.asarray(R, dtype=np.float64).reshape(len(t), -1, 3, 3)
        sample, xi_e, m_e, m_psi = self._margins(t, p, R)
        mv = None
        if margin_v is not None:
            margin_v = np.asarray(margin_v, dtype=np.float64).reshape(len(t), -1, 6)
            mv = margin_v.min(axis=2)  # (T,N); inf where unknown
            np.minimum(self.min_margin_v, mv.min(axis=0), out=self.min_margin_v)
        if self.first_violation is None:
            self.first_violation = _first_violation(self, t, xi_e, m_e, m_psi, margin_v, mv)
        np.minimum(self.min_margin_e, m_e.min(axis=0), out=self.min_margin_e)
        np.minimum(self.min_margin_psi, m_psi.min(axis=0), out=self.min_margin_psi)
        self._settle(t, sample.e, sample.psi)
        self.samples += len(t)
        self.t_first = float(t[0]) if self.t_first is None else self.t_first
        self.t_last = float(t[-1])
        if single:
            return EdgeSample(sample.e[0], sample.psi[0], sample.rho_e[0], sample.rho_psi[0])
        return sample

    def _margins(
        self, t: np.ndarray, p: np.ndarray, R: np.ndarray
    ) -> tuple[EdgeSample, np.ndarray, np.ndarray, np.ndarray]:
        """(e, ψ, ρ_e, ρ_ψ), ξ_e and the margins of every edge at samples t (T,) of p (T,N,3), R (T,N,3,3)."""
        e, psi = self.edges.errors(p, R)
        rho_e, rho_psi = self.edges.rho(t)
        xi_e = e / rho_e
        m_e = funnels.margin_e(xi_e, self.edges.c_col, self.edges.c_con)
        return EdgeSample(e, psi, rho_e, rho_psi), xi_e, m_e, funnels.margin_psi(psi / rho_psi)

    def violation_at(self, t: float, p: np.ndarray, R: np.ndarray, margin_v: np.ndarray) -> Violation | None:
        """The violation one sample (p (N,3), R (N,3,3), margin_v (N,6)) shows, without taking it."""
        _, xi_e, m_e, m_psi = self._margins(np.array([t]), p[None], R[None])
        margin_v = margin_v[None]
        return _first_violation(self, np.array([t]), xi_e, m_e, m_psi, margin_v, margin_v.min(axis=2))

    def take_checked(self, t: np.ndarray, checked: CheckedSteps, violation: Violation | None) -> None:
        """Samples at t (T,) that a run core checked itself: its running minima and settle times
        replace the judge's, ``violation`` is their first (see :class:`CheckedSteps`)."""
        self.min_margin_e[:] = checked.min_margin_e
        self.min_margin_psi[:] = checked.min_margin_psi
        self.min_margin_v[:] = checked.min_margin_v
        self.settle_e = [None if np.isnan(s) else float(s) for s in checked.settle_e]
        self.settle_psi = [None if np.isnan(s) else float(s) for s in checked.settle_psi]
        self.first_violation = self.first_violation or violation
        self.samples += len(t)
        self.t_first = float(t[0]) if self.t_first is None else self.t_first
        self.t_last = float(t[-1])

    def update_velocity(self, t: float, margin_v: np.ndarray) -> None:
        """Velocity-funnel margins (N,6) at a control step without a ground-truth sample (inf: unknown)."""
        margin_v = np.asarray(margin_v, dtype=np.float64)
        mv = margin_v.min(axis=1)
        np.minimum(self.min_margin_v, mv, out=self.min_margin_v)
        if self.first_violation is None and mv.min() <= 0:
            i = int(np.argmin(mv))
            channel = VELOCITY_CHANNELS[int(np.argmin(margin_v[i]))]
            self.first_violation = Violation(float(t), "velocity", self.spec.agents[i].id, channel)

    def _settle(self, t: np.ndarray, e: np.ndarray, psi: np.ndarray) -> None:
        for settle, inside in (
            (self.settle_e, (e >= self.band_lo) & (e <= self.band_hi)),
            (self.settle_psi, psi <= self.band_psi),
        ):
            for k in range(inside.shape[1]):
                out = np.flatnonzero(~inside[:, k])
                if out.size == 0:
                    settle[k] = float(t[0]) if settle[k] is None else settle[k]
                elif out[-1] == len(t) - 1:
                    settle[k] = None
                else:
                    settle[k] = float(t[out[-1] + 1])

    def worst_margin(self) -> float:
        vals = [self.min_margin_e.min(initial=np.inf), self.min_margin_psi.min(initial=np.inf)]
        if np.isfinite(self.min_margin_v).any():
            vals.append(self.min_margin_v.min())
        return float(min(vals))


def _first_violation(
    judge: Judge,
    t: np.ndarray,
    xi_e: np.ndarray,
    m_e: np.ndarray,
    m_psi: np.ndarray,
    margin_v: np.ndarray | None,
    mv: np.ndarray | None,
) -> Violation | None:
    """The earliest sample with a margin ≤ 0; at one sample the worst edge before any agent."""
    m_edge = np.minimum(m_e, m_psi)
    bad_edge = np.flatnonzero(m_edge.min(axis=1) <= 0)
    bad_v = np.flatnonzero(mv.min(axis=1) <= 0) if mv is not None else np.empty(0, dtype=int)
    if bad_edge.size and (not bad_v.size or bad_edge[0] <= bad_v[0]):
        j = int(bad_edge[0])
        k = int(np.argmin(m_edge[j]))
        name = judge.edges.names[k]
        if m_e[j, k] <= m_psi[j, k]:
            return Violation(float(t[j]), "distance", name, "collision" if xi_e[j, k] < 0 else "connectivity")
        return Violation(float(t[j]), "orientation", name, "psi")
    if bad_v.size:
        assert margin_v is not None and mv is not None
        j = int(bad_v[0])
        i = int(np.argmin(mv[j]))
        channel = VELOCITY_CHANNELS[int(np.argmin(margin_v[j, i]))]
        return Violation(float(t[j]), "velocity", judge.spec.agents[i].id, channel)
    return None


def judge(
    spec: FormationSpec, t: np.ndarray, p: np.ndarray, R: np.ndarray, margin_v: np.ndarray | None = None
) -> Judge:
    """Every funnel of ``spec`` checked on a trajectory: t (T,) [s], p (T,N,3) [m] and
    R_world_body (T,N,3,3) in the world frame, margin_v (T,N,6) (inf where unknown)."""
    j = Judge(spec)
    j.update(t, p, R, margin_v)
    return j
