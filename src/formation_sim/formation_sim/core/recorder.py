"""The streaming recorder of a run: :class:`RunRecorder` is what the headless runner, the simulator
node, the synthesiser and the bag analysis fill sample by sample. It feeds the judge
(:class:`formation_sim.core.judge.Judge`), keeps the decimated trajectory, counts faults per agent and
kind (:class:`formation_core.faults.FaultLog`) and builds the summary, whose verdict comes from
:func:`formation_core.verdict.decide` (docs/outputs.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from formation_core.faults import FaultLog, strict_json
from formation_core.formation import FormationSpec
from formation_core.verdict import ExitCode, Incomplete, Outcome, Verdict, decide
from formation_deploy.publisher_watch import untrusted_input
from formation_sim.core.judge import CheckedSteps, EdgeSample, Judge, Violation
from formation_sim.core.summary import LinkReport, RunnerKeys, RunSummary

#: samples :meth:`RunRecorder.add` queues before checking them together
CHECK_BATCH = 64


@dataclass
class _Batch:
    """Samples queued for one check: t (B,), p (B,N,3), R (B,N,3,3), v and u (B,N,6), margin_v (B,N,6)."""

    t: np.ndarray
    p: np.ndarray
    R: np.ndarray
    v: np.ndarray
    u: np.ndarray
    margin_v: np.ndarray
    n: int = 0

    @classmethod
    def empty(cls, n_agents: int) -> _Batch:
        b, n = CHECK_BATCH, n_agents
        six = (b, n, 6)
        return cls(
            np.zeros(b), np.zeros((b, n, 3)), np.zeros((b, n, 3, 3)), np.zeros(six), np.zeros(six), np.zeros(six)
        )


@dataclass
class RunRecorder:
    """The streaming judge of one run: checks every sample, counts faults, keeps the trajectory."""

    spec: FormationSpec
    record_every: int = 1
    mode: str = "headless"
    control_rate: float = 0.0
    _rows: dict[str, list[np.ndarray]] = field(default_factory=dict)
    #: summary.json's ``links`` (formation_sim.core.links.link_summary), set by a run with a link model
    links: LinkReport | None = None

    def __post_init__(self) -> None:
        self.judge = Judge(self.spec)
        self._batch = _Batch.empty(len(self.spec.agents))
        self.faults = FaultLog()
        self.peak_force = np.zeros(len(self.spec.agents))
        self.peak_torque = np.zeros(len(self.spec.agents))
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
    ) -> None:
        """Queue one sample (ground truth at t; ``margin_v`` (N,6) from the agents if known).

        ``u`` None: the wrenches are not known yet; give them with :meth:`set_inputs`. Samples are
        checked :data:`CHECK_BATCH` at a time (:meth:`flush`): numpy's cost is per call, not per
        sample, and one sample's check cost a simulator ~0.2 ms per step. Every result flushes first.
        """
        b = self._batch
        if b.n == CHECK_BATCH:
            self.flush()
        k = b.n
        b.t[k] = t
        b.p[k] = p
        b.R[k] = R
        b.v[k] = v
        b.u[k] = 0.0 if u is None else u
        b.margin_v[k] = np.inf if margin_v is None else margin_v
        b.n = k + 1

    def set_inputs(self, u: np.ndarray, margin_v: np.ndarray | None = None) -> None:
        """Wrenches (N,6) applied from the sample added last (which was added with ``u=None``), and
        the agents' velocity margins (N,6) of that step if they were not known then.

        Lets a simulator queue step k while the agents compute, then record what they answered.
        """
        b = self._batch
        if b.n > 0:
            b.u[b.n - 1] = u
            if margin_v is not None:
                b.margin_v[b.n - 1] = margin_v
            return
        if margin_v is not None:
            raise RuntimeError("RunRecorder.set_inputs: the sample was checked before its velocity margins came")
        if self.judge.samples == 0:
            raise RuntimeError("RunRecorder.set_inputs: no sample added yet")
        # a result was read since that sample was added, so it is checked already: complete it in place
        u = np.array(u, dtype=np.float64)
        self._peaks(u[None])
        if (self.judge.samples - 1) % self.record_every == 0:
            self._rows["u"][-1] = u

    def flush(self) -> None:
        """Check the queued samples: margins, first violation, settling, peaks, decimated rows."""
        b = self._batch
        if b.n == 0:
            return
        n, b.n = b.n, 0
        start = self.judge.samples
        sample = self.judge.update(b.t[:n], b.p[:n], b.R[:n], b.margin_v[:n])
        self._peaks(b.u[:n])
        self._keep(start, b.t[:n], b.p[:n], b.R[:n], b.v[:n], b.u[:n], sample)

    def _peaks(self, u: np.ndarray) -> None:
        """Peak force and torque per agent over wrenches u (T,N,6)."""
        np.maximum(self.peak_force, np.linalg.norm(u[..., :3], axis=2).max(axis=0), out=self.peak_force)
        np.maximum(self.peak_torque, np.linalg.norm(u[..., 3:], axis=2).max(axis=0), out=self.peak_torque)

    def add_checked(
        self,
        t: np.ndarray,
        p: np.ndarray,
        R: np.ndarray,
        v: np.ndarray,
        u: np.ndarray,
        edges: EdgeSample,
        checked: CheckedSteps,
        violation: Violation | None,
    ) -> None:
        """T consecutive samples (arrays with a leading axis T) the run core checked itself (``checked``, ``violation``:
        :meth:`Judge.take_checked`); ``edges`` holds their e, ψ, ρ_e, ρ_ψ (T,K)."""
        start = self.judge.samples
        self.judge.take_checked(t, checked, violation)
        self.peak_force[:] = checked.peak_force
        self.peak_torque[:] = checked.peak_torque
        self._keep(start, t, p, R, v, u, edges)

    def _recorded_rows(self, start: int, n: int) -> np.ndarray:
        """Which of n samples from the run's sample ``start`` on the trajectory keeps: every ``record_every``-th."""
        return np.flatnonzero((start + np.arange(n)) % self.record_every == 0)

    def _keep(
        self,
        start: int,
        t: np.ndarray,
        p: np.ndarray,
        R: np.ndarray,
        v: np.ndarray,
        u: np.ndarray,
        edges: EdgeSample,
    ) -> None:
        """The decimated trajectory: every ``record_every``-th sample, counted from the run's first."""
        rows = self._recorded_rows(start, len(edges.e))
        for key, arr in (("t", t), ("p", p), ("R", R), ("v", v), ("u", u)):
            self._rows[key].extend(np.array(arr[rows], dtype=np.float64))
        for key, arr in (("e", edges.e), ("psi", edges.psi), ("rho_e", edges.rho_e), ("rho_psi", edges.rho_psi)):
            self._rows[key].extend(arr[rows])

    def add_link_ages(self, ages: np.ndarray, start: int) -> None:
        """Every link's held sample's age (T, n_links) [s] at samples start … start + T − 1 (a link model's
        runs), kept at the trajectory's samples as ``link_age``."""
        rows = self._recorded_rows(start, len(ages))
        self._rows.setdefault("link_age", []).extend(np.array(ages[rows], dtype=np.float64))

    def update_velocity(self, t: float, margin_v: np.ndarray) -> None:
        """Velocity margins (N,6) known at t between samples (:meth:`Judge.update_velocity`), after those queued."""
        self.flush()
        self.judge.update_velocity(t, margin_v)

    def fault(self, t: float, kind: str, agent: str, detail: str = "") -> bool:
        """Count a fault (not a funnel check); True if it is the agent's first of this kind."""
        return self.faults.add(t, agent, kind, detail)

    # -- results ------------------------------------------------------------------------------

    @property
    def samples(self) -> int:
        self.flush()
        return self.judge.samples

    @property
    def t_last(self) -> float:
        self.flush()
        return 0.0 if self.judge.t_last is None else self.judge.t_last

    @property
    def first_violation(self) -> Violation | None:
        self.flush()
        return self.judge.first_violation

    @property
    def min_margin_v(self) -> np.ndarray:
        self.flush()
        return self.judge.min_margin_v

    def worst_margin(self) -> float:
        self.flush()
        return self.judge.worst_margin()

    def arrays(self) -> dict[str, np.ndarray]:
        """The decimated trajectory (docs/outputs.md)."""
        self.flush()
        out = {k: np.array(v) for k, v in self._rows.items()}
        if "link_age" in out and len(out["link_age"]) != len(out["t"]):  # a run stopped between the two
            ages = np.full((len(out["t"]), out["link_age"].shape[1]), np.nan)
            n = min(len(ages), len(out["link_age"]))
            ages[:n] = out["link_age"][:n]
            out["link_age"] = ages
        return out

    def outcome(
        self, requested_duration: float | None, incomplete: Incomplete | None = None, untrusted: str | None = None
    ) -> Outcome:
        """The verdict: the funnels, the duration reached (to half a control period), ``incomplete``
        and ``untrusted`` (the reason the run's input cannot be trusted: an intruder)."""
        self.flush()
        if incomplete is None and requested_duration is not None:
            tol = 0.5 / self.control_rate if self.control_rate > 0 else 1e-9
            if self.judge.t_last is None or self.judge.t_last < requested_duration - tol:
                incomplete = Incomplete(
                    ExitCode.INCOMPLETE, f"duration not reached: t={self.t_last:g} s of {requested_duration:g} s"
                )
        return decide(self.first_violation is not None, incomplete, untrusted)

    def summary(
        self,
        *,
        wall_time: float | None,
        requested_duration: float | None = None,
        incomplete: Incomplete | None = None,
        extra: RunnerKeys | None = None,
    ) -> RunSummary:
        """summary.json (docs/outputs.md); ``requested_duration`` None: whatever was fed is the run.
        An ``extra["security"]`` that names an intruder makes the run INCOMPLETE (untrusted input)."""
        j = self.judge
        result = self.outcome(requested_duration, incomplete, untrusted_input((extra or {}).get("security")))
        duration = self.t_last
        out: RunSummary = {
            "formation": self.spec.name,
            "formation_file": Path(self.spec.source).name,
            "mode": self.mode,
            "control_rate": self.control_rate,
            "verdict": result.verdict.value,
            "incomplete_reason": result.reason if result.verdict != Verdict.PASS else None,
            "exit_status": int(result.exit_code),
            "requested_duration": requested_duration,
            "duration": duration,
            "samples": j.samples,
            "wall_time": wall_time,
            "real_time_factor": duration / wall_time if wall_time else None,  # None: wall time unknown
            # None (unknown) when the run is INCOMPLETE without a violation
            "funnels_held": {Verdict.PASS: True, Verdict.FAIL: False}.get(result.verdict),
            "first_violation": None if j.first_violation is None else j.first_violation.as_dict(),
            "worst_margin": j.worst_margin(),
            "faults": self.faults.as_dict(),
            "clearance": j.clearance(),
            "links": self.links,
            "edges": {
                name: {
                    "min_margin_e": j.min_margin_e[k],
                    "min_margin_psi": j.min_margin_psi[k],
                    "settle_time_e": j.settle_e[k],
                    "settle_time_psi": j.settle_psi[k],
                }
                for k, name in enumerate(j.edges.names)
            },
            "agents": {
                a.id: {
                    "peak_force": self.peak_force[i],
                    "peak_torque": self.peak_torque[i],
                    "min_margin_v": j.min_margin_v[i],
                }
                for i, a in enumerate(self.spec.agents)
            },
            **(extra or {}),
        }
        summary: RunSummary = strict_json(out)  # the same keys, NaN and numpy scalars made JSON
        return summary
