"""The judge of a run: e_k, ψ_k and their funnel margins from world poses, the first violation, settle
times and the worst margin (docs/outputs.md).

The funnel rule and the formulas of e, ψ and their margins live here once, as
:func:`formation_msgs_py.compiled.formula` functions: :func:`edge_errors`, :func:`edge_margins`,
:func:`outside` (the rule), :func:`in_steady_band` and :func:`settle`. The run core compiles them
into its loop (formation_sim.core.loop, on floats); :class:`Judge` calls the same functions on
numpy arrays, where they work elementwise with the same operations in the same order.

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
from formation_msgs_py.compiled import formula
from formation_msgs_py.so3 import matmul3
from formation_msgs_py.spec import FormationSpec

VELOCITY_CHANNELS = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Violation kinds that name an edge; ``velocity`` names an agent.
EDGE_KINDS = ("distance", "orientation")


@formula
def edge_errors(p_tail, p_head, R_tail, R_head, d2, R_des):
    """(e_k [m²], ψ_k) of edge k from world poses: e = ‖p_head − p_tail‖² − d_k,des² and
    ψ = ½ tr(I − R_desᵀ R_headᵀ R_tail) = ½(3 − Σ (R_head R_des)∘R_tail), d2 = d_k,des² [m²].

    Vectors are 3-tuples and matrices row tuples (:func:`formation_msgs_py.so3.vec3`,
    :func:`formation_msgs_py.so3.matrix_rows`) of floats, or of numpy arrays (elementwise).
    """
    d = (p_head[0] - p_tail[0], p_head[1] - p_tail[1], p_head[2] - p_tail[2])
    e = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - d2
    A = matmul3(R_head, R_des)
    trace = 0.0
    for a in range(3):
        for b in range(3):
            trace += A[a][b] * R_tail[a][b]
    return e, 0.5 * (3.0 - trace)


@formula
def edge_margins(t, e, psi, c_col, c_con, rho_e_floor, decay_e, rho_psi_0, rho_psi_inf, decay_psi):
    """(ρ_e, ρ_ψ, ξ_e, margin_e, margin_ψ) of an edge at t [s] with errors e [m²] and ψ: the distance
    funnel normalised (ρ_e(0) = 1, floor :func:`formation_msgs_py.funnels.rho_e_floor`), decays in 1/s."""
    rho_e = funnels.rho(t, 1.0, rho_e_floor, decay_e)
    rho_psi = funnels.rho(t, rho_psi_0, rho_psi_inf, decay_psi)
    xi_e = e / rho_e
    return rho_e, rho_psi, xi_e, funnels.margin_e(xi_e, c_col, c_con), funnels.margin_psi(psi / rho_psi)


@formula
def outside(margin):
    """The funnel rule: a margin ≤ 0 (on a funnel's bound or beyond it) is a violation."""
    return margin <= 0.0


@formula
def in_steady_band(e, psi, band_lo, band_hi, band_psi):
    """(band_lo ≤ e ≤ band_hi, ψ ≤ band_psi): whether the errors are inside their funnels' limits as t → ∞."""
    return (band_lo <= e) & (e <= band_hi), psi <= band_psi


@formula
def settle(s, t, inside):
    """The settle time after a sample at t: NaN (none) while outside the band, else the first t inside."""
    if not inside:
        return np.nan
    return t if np.isnan(s) else s


def _vec(a: np.ndarray) -> tuple[np.ndarray, ...]:
    """A stack (…,3) as a 3-tuple of arrays (…)."""
    return a[..., 0], a[..., 1], a[..., 2]


def _rows(A: np.ndarray) -> tuple[tuple[np.ndarray, ...], ...]:
    """A stack (…,3,3) as row tuples of arrays (…)."""
    return tuple(tuple(A[..., r, c] for c in range(3)) for r in range(3))


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
        self._floor_e = funnels.rho_e_floor(self.c_col, self.c_con, np.array([e.rho_e_inf for e in spec.edges]))
        self._decay_e = np.array([e.decay_e for e in spec.edges])
        self._rho_psi_0 = np.array([e.rho_psi_0 for e in spec.edges])
        self._rho_psi_inf = np.array([e.rho_psi_inf for e in spec.edges])
        self._decay_psi = np.array([e.decay_psi for e in spec.edges])
        self._R_des_rows = _rows(self.R_des)

    def errors(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(e, ψ), each (K,), from p (N,3) and R_world_body (N,3,3); or stacks (T,N,..) -> (T,K)."""
        p, R = np.asarray(p, dtype=np.float64), np.asarray(R, dtype=np.float64)
        return edge_errors(
            _vec(p[..., self.tail, :]),
            _vec(p[..., self.head, :]),
            _rows(R[..., self.tail, :, :]),
            _rows(R[..., self.head, :, :]),
            self.d2,
            self._R_des_rows,
        )

    def margins(
        self, t: np.ndarray | float, e: np.ndarray, psi: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ρ_e, ρ_ψ, ξ_e, margin_e, margin_ψ) of errors e, ψ (K,) at t, or (T,K) at t (T,)."""
        t = np.asarray(t, dtype=np.float64)[..., None]
        return edge_margins(
            t, e, psi, self.c_col, self.c_con, self._floor_e, self._decay_e,
            self._rho_psi_0, self._rho_psi_inf, self._decay_psi,
        )  # fmt: skip

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
        rho_e, rho_psi, xi_e, m_e, m_psi = self.edges.margins(t, e, psi)
        return EdgeSample(e, psi, rho_e, rho_psi), xi_e, m_e, m_psi

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
        if self.first_violation is None and outside(mv.min()):
            i = int(np.argmin(mv))
            channel = VELOCITY_CHANNELS[int(np.argmin(margin_v[i]))]
            self.first_violation = Violation(float(t), "velocity", self.spec.agents[i].id, channel)

    def _settle(self, t: np.ndarray, e: np.ndarray, psi: np.ndarray) -> None:
        """The settle times after samples at t (T,): :func:`settle` over a stack, per edge."""
        inside_e, inside_psi = in_steady_band(e, psi, self.band_lo, self.band_hi, self.band_psi)
        for settled, inside in ((self.settle_e, inside_e), (self.settle_psi, inside_psi)):
            for k in range(inside.shape[1]):
                out = np.flatnonzero(~inside[:, k])
                if out.size == 0:
                    settled[k] = float(t[0]) if settled[k] is None else settled[k]
                elif out[-1] == len(t) - 1:
                    settled[k] = None
                else:
                    settled[k] = float(t[out[-1] + 1])

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
    """The earliest sample :func:`outside` a funnel; at one sample the worst edge before any agent."""
    m_edge = np.minimum(m_e, m_psi)
    bad_edge = np.flatnonzero(outside(m_edge.min(axis=1)))
    bad_v = np.flatnonzero(outside(mv.min(axis=1))) if mv is not None else np.empty(0, dtype=int)
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
