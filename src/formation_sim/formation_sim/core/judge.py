"""The judge of a run: e_k, ψ_k and their funnel margins from world poses, the first violation, settle
times and the worst margin (docs/outputs.md).

The funnel rule and the formulas of the margins live here once, as
:func:`formation_core.numba_kernels.formula` functions: :func:`edge_margins`, :func:`outside` (the
rule), :func:`in_steady_band` and :func:`settle`; e and ψ from world poses are
:func:`formation_core.funnels.edge_errors` (also what a formation file's checks and formation-check
compute at t = 0). The run core compiles them
into its loop (formation_sim.core.loop, on floats); :class:`Judge` calls the same functions on
numpy arrays, where they work elementwise with the same operations in the same order.

:func:`judge` is a pure function over trajectory arrays (t, p, R and, where known, the agents'
velocity-funnel margins); :class:`Judge` is the same check fed in time order, one sample or a
stack of samples at a time.

Margins are the fraction of a funnel left between an error and its nearest bound (1 at zero
error, 0 on the bound, negative outside); see :mod:`formation_core.funnels`. A fault (a
missing measurement, a zeroed wrench, a saturated controller) is counted, never a violation:
only the funnels decide FAIL, and missing data makes a run INCOMPLETE, never FAIL.

Every pair of bodies is watched too, not only the tree's edges (the paper guarantees distances on
the edges only): the *clearance* of a pair is the distance between their centres minus both radii
[m] (:func:`pair_clearance`), and a clearance ≤ 0 is a *contact* (:func:`in_contact`). The smallest
clearance of each pair, when, and its first contact are kept; a contact is a violation only where
the formation file says so (``simulation.contact: fail``; default ``report``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from formation_core import funnels
from formation_core.formation import FormationSpec
from formation_core.funnels import edge_errors
from formation_core.numba_kernels import formula
from formation_sim.core.summary import Clearance, Contact, FirstViolation

VELOCITY_CHANNELS = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Violation kinds that name an edge; ``velocity`` names an agent, ``contact`` a pair of agents.
EDGE_KINDS = ("distance", "orientation")
CONTACT = "contact"


@formula
def edge_margins(t, e, psi, c_col, c_con, rho_e_floor, decay_e, rho_psi_0, rho_psi_inf, decay_psi):
    """(ρ_e, ρ_ψ, ξ_e, margin_e, margin_ψ) of an edge at t [s] with errors e [m²] and ψ: the distance
    funnel normalised (ρ_e(0) = 1, floor :func:`formation_core.funnels.rho_e_floor`), decays in 1/s."""
    rho_e = funnels.rho(t, 1.0, rho_e_floor, decay_e)
    rho_psi = funnels.rho(t, rho_psi_0, rho_psi_inf, decay_psi)
    xi_e = e / rho_e
    return rho_e, rho_psi, xi_e, funnels.margin_e(xi_e, c_col, c_con), funnels.margin_psi(psi / rho_psi)


@formula
def outside(margin):
    """The funnel rule: a margin ≤ 0 (on a funnel's bound or beyond it) is a violation."""
    return margin <= 0.0


@formula
def pair_clearance(p_i, p_j, r_sum):
    """‖p_j − p_i‖ − (r_i + r_j) [m] of two bodies at world positions p_i, p_j (3-tuples, of floats or
    of arrays) with radii summing to ``r_sum``: the gap between their spheres, negative when they overlap."""
    d0, d1, d2 = p_j[0] - p_i[0], p_j[1] - p_i[1], p_j[2] - p_i[2]
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - r_sum


@formula
def in_contact(clearance):
    """The contact rule: two bodies touching or overlapping (clearance ≤ 0)."""
    return clearance <= 0.0


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


class Pairs:
    """Every pair of bodies (i < j, in formation-file order): who, their radii's sum [m], and a name."""

    def __init__(self, spec: FormationSpec) -> None:
        n = len(spec.agents)
        i, j = np.triu_indices(n, k=1)
        radii = np.array([a.radius for a in spec.agents])
        self.i, self.j = i.astype(np.int64), j.astype(np.int64)
        self.r_sum = radii[i] + radii[j]
        self.names = [f"{spec.agents[a].id}-{spec.agents[b].id}" for a, b in zip(i.tolist(), j.tolist())]
        self.ids = [(spec.agents[a].id, spec.agents[b].id) for a, b in zip(i.tolist(), j.tolist())]

    def clearances(self, p: np.ndarray) -> np.ndarray:
        """The clearance [m] of every pair (P,) at world positions p (N,3), or (T,P) of p (T,N,3)."""
        p = np.asarray(p, dtype=np.float64)
        return pair_clearance(_vec(p[..., self.i, :]), _vec(p[..., self.j, :]), self.r_sum)


class CheckedSteps(NamedTuple):
    """The check of every sample so far, made by the run core itself (formation_sim.core.loop, compiled,
    with :class:`Judge`'s rules): running minimum margins per edge (K,) and agent (N,), settle
    times (K,) (NaN: none), peak force and torque per agent (N,), and per pair of bodies (P,) the
    smallest clearance [m], when [s], and its first contact [s] (NaN: none)."""

    min_margin_e: np.ndarray
    min_margin_psi: np.ndarray
    min_margin_v: np.ndarray
    settle_e: np.ndarray
    settle_psi: np.ndarray
    peak_force: np.ndarray
    peak_torque: np.ndarray
    min_clearance: np.ndarray
    min_clearance_t: np.ndarray
    contact_t: np.ndarray


@dataclass(frozen=True)
class Violation:
    """The first sample outside a funnel: time [s], kind, edge or agent, channel."""

    t: float
    kind: str
    where: str
    channel: str

    def as_dict(self) -> FirstViolation:
        """summary.json's ``first_violation``: where is an ``edge``, a ``pair`` or an ``agent``."""
        if self.kind in EDGE_KINDS:
            return {"t": self.t, "kind": self.kind, "edge": self.where, "channel": self.channel}
        if self.kind == CONTACT:
            return {"t": self.t, "kind": self.kind, "pair": self.where, "channel": self.channel}
        return {"t": self.t, "kind": self.kind, "agent": self.where, "channel": self.channel}


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
        self.pairs = Pairs(spec)
        P = len(self.pairs.names)
        self.min_clearance = np.full(P, np.inf)
        self.min_clearance_t = np.full(P, np.nan)
        self.contact_t = np.full(P, np.nan)
        self.contact_fails = spec.simulation.contact == "fail"
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
        clearance = self._clearances(t, p)
        if self.first_violation is None:
            self.first_violation = _first_violation(self, t, xi_e, m_e, m_psi, margin_v, mv, clearance)
        np.minimum(self.min_margin_e, m_e.min(axis=0), out=self.min_margin_e)
        np.minimum(self.min_margin_psi, m_psi.min(axis=0), out=self.min_margin_psi)
        self._settle(t, sample.e, sample.psi)
        self.samples += len(t)
        self.t_first = float(t[0]) if self.t_first is None else self.t_first
        self.t_last = float(t[-1])
        if single:
            return EdgeSample(sample.e[0], sample.psi[0], sample.rho_e[0], sample.rho_psi[0])
        return sample

    def _clearances(self, t: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The clearance of every pair at samples t (T,) of p (T,N,3), (T,P); keeps each pair's smallest
        (and when) and its first contact."""
        clearance = self.pairs.clearances(p)
        if clearance.shape[1] == 0:
            return clearance
        k = np.argmin(clearance, axis=0)
        smallest = clearance[k, np.arange(clearance.shape[1])]
        lower = smallest < self.min_clearance
        self.min_clearance[lower] = smallest[lower]
        self.min_clearance_t[lower] = t[k[lower]]
        touching = in_contact(clearance)
        first = touching.argmax(axis=0)
        new = touching.any(axis=0) & np.isnan(self.contact_t)
        self.contact_t[new] = t[first[new]]
        return clearance

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
        clearance = self.pairs.clearances(p[None])
        return _first_violation(self, np.array([t]), xi_e, m_e, m_psi, margin_v, margin_v.min(axis=2), clearance)

    def take_checked(self, t: np.ndarray, checked: CheckedSteps, violation: Violation | None) -> None:
        """Samples at t (T,) that a run core checked itself: its running minima and settle times
        replace the judge's, ``violation`` is their first (see :class:`CheckedSteps`)."""
        self.min_margin_e[:] = checked.min_margin_e
        self.min_margin_psi[:] = checked.min_margin_psi
        self.min_margin_v[:] = checked.min_margin_v
        self.settle_e = [None if np.isnan(s) else float(s) for s in checked.settle_e]
        self.settle_psi = [None if np.isnan(s) else float(s) for s in checked.settle_psi]
        self.min_clearance[:] = checked.min_clearance
        self.min_clearance_t[:] = checked.min_clearance_t
        self.contact_t[:] = checked.contact_t
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
        """The settle times after samples at t (T,): :func:`settle` folded over the stack, per edge. Only two
        samples can change the fold's result: the last one outside the band (it resets the time) and the
        first inside after it (it sets it); :func:`settle` is applied to those."""
        inside_e, inside_psi = in_steady_band(e, psi, self.band_lo, self.band_hi, self.band_psi)
        for settled, inside in ((self.settle_e, inside_e), (self.settle_psi, inside_psi)):
            for k in range(inside.shape[1]):
                prior = settled[k]
                s: float = np.nan if prior is None else prior
                out = np.flatnonzero(~inside[:, k])
                first_inside = 0
                if out.size:
                    s = settle(s, float(t[out[-1]]), False)
                    first_inside = int(out[-1]) + 1
                if first_inside < len(t):
                    s = settle(s, float(t[first_inside]), True)
                settled[k] = None if np.isnan(s) else float(s)

    def clearance(self) -> Clearance:
        """summary.json ``clearance``: the smallest clearance of any pair of bodies [m], which pair and when,
        the first contact (null: none) and every pair that touched, with the policy (``simulation.contact``)."""
        policy = "fail" if self.contact_fails else "report"
        if not len(self.pairs.names) or not np.isfinite(self.min_clearance).any():
            return {"policy": policy, "min": None, "pair": None, "t": None, "first_contact": None, "contacts": []}
        k = int(np.argmin(self.min_clearance))
        touched = np.flatnonzero(~np.isnan(self.contact_t))
        contacts: list[Contact] = [
            {"pair": list(self.pairs.ids[c]), "first_t": float(self.contact_t[c]), "min": float(self.min_clearance[c])}
            for c in touched[np.argsort(self.contact_t[touched], kind="stable")].tolist()
        ]
        return {
            "policy": policy,
            "min": float(self.min_clearance[k]),
            "pair": list(self.pairs.ids[k]),
            "t": float(self.min_clearance_t[k]),
            "first_contact": None if not contacts else {"t": contacts[0]["first_t"], "pair": contacts[0]["pair"]},
            "contacts": contacts,
        }

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
    clearance: np.ndarray,
) -> Violation | None:
    """The earliest sample :func:`outside` a funnel (or, where contacts fail the run, in contact); at one
    sample the worst edge before any agent, and any funnel before a contact."""
    m_edge = np.minimum(m_e, m_psi)
    bad_edge = np.flatnonzero(outside(m_edge.min(axis=1)))
    bad_v = np.flatnonzero(outside(mv.min(axis=1))) if mv is not None else np.empty(0, dtype=int)
    if judge.contact_fails and clearance.shape[1]:
        touching = np.flatnonzero(in_contact(clearance.min(axis=1)))
        funnel = min([*bad_edge[:1].tolist(), *bad_v[:1].tolist()], default=None)
        if touching.size and (funnel is None or touching[0] < funnel):
            j = int(touching[0])
            return Violation(float(t[j]), CONTACT, judge.pairs.names[int(np.argmin(clearance[j]))], "clearance")
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
