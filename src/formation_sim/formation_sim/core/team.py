"""Every agent's controller stepped together on one step's measurements (no ROS), and the fault policy.

:func:`team_step` is the one closed-loop control step: the run core (headless runs, campaigns)
calls it compiled on its measurement arrays; :class:`AgentTeam` calls it on the measurements the
simulator node published (its *shadow* of the agents: in lockstep these are what the agents
answer, so the velocity-funnel margins and faults it records are the agents' own) and on the
decoded messages of a synthesised bag. The fault policy is the same everywhere (:func:`step_faults`):
an agent missing a neighbour's pose answers a zero wrench at ERROR (:func:`fault_wrench`) and is a
``measurement`` fault (:func:`note_missing`); every other agent at ERROR (saturated: outside a
funnel) is a ``controller`` fault (:func:`note_errors`), counted per agent and step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from formation_agent.controller import (
    AGENT_COLUMNS,
    DELTA,
    END_COLUMNS,
    ERROR,
    GAMMA,
    LEVEL,
    MARGIN_V,
    REASON,
    REASON_MESSAGES,
    REASON_MISSING,
    T0,
    U,
    agent_step,
    fault_wrench,
    gains,
    new_funnel_start,
    new_outputs,
)
from formation_agent.roundoff import answer_bounds, tolerance
from formation_core.formation import FormationSpec, agent_view
from formation_core.numba_kernels import CODE_FORM, in_code_form, kernel
from formation_sim.core.measurement import Ends
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements


@kernel
def team_step(t, p_rel, R_rel, in_range, v_measured, first_end, agents, ends, start, out, edge_out):
    """Every agent's step at t [s] on end-indexed measurements; an agent missing a pose gets the fault wrench."""
    for i in range(v_measured.shape[0]):
        lo, hi = first_end[i], first_end[i + 1]
        measured = True
        for k in range(lo, hi):
            measured = measured and in_range[k]
        if measured:
            agent_step(t, i, lo, hi, p_rel, R_rel, v_measured[i], agents, ends, start, out, edge_out)
        else:
            fault_wrench(i, lo, hi, REASON_MISSING, out, edge_out, start)


def load_team_step() -> None:
    """Load (or compile into numba's cache) :func:`team_step` for the types every caller passes,
    on one agent without edges (what it computes is thrown away)."""
    first_end, agents, ends = np.zeros(2, dtype=np.int64), np.zeros((1, AGENT_COLUMNS)), np.zeros((0, END_COLUMNS))
    p_rel, R_rel, in_range = np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=np.bool_)
    outputs = (new_funnel_start(1), *new_outputs(1, 0))
    team_step(0.0, p_rel, R_rel, in_range, np.zeros((1, 6)), first_end, agents, ends, *outputs)


def step_faults(
    first_end: Sequence[int] | np.ndarray,
    neighbours: Sequence[str],
    in_range: Sequence[bool] | np.ndarray,
    level: Sequence[float] | np.ndarray,
    reason: Sequence[float] | np.ndarray,
) -> tuple[dict[int, list[str]], list[tuple[int, str]]]:
    """The fault policy of one step from the kernels' outputs: ({agent index: neighbours whose pose
    is missing}, [(agent index, reason) of every other agent at ERROR]); ``neighbours`` by end."""
    missing: dict[int, list[str]] = {}
    for i in range(len(first_end) - 1):
        gone = [neighbours[k] for k in range(first_end[i], first_end[i + 1]) if not in_range[k]]
        if gone:
            missing[i] = gone
    errors = [(i, REASON_MESSAGES[int(reason[i])]) for i in range(len(level)) if level[i] == ERROR and i not in missing]
    return missing, errors


def note_missing(
    recorder: RunRecorder, t: float, agent_ids: Sequence[str], missing: Mapping[int, Sequence[str]]
) -> None:
    """Agents missing a neighbour's pose ({agent index: neighbour ids}) are ``measurement`` faults.

    Recorded before the step's funnel check (``recorder.add``), so they come first at equal times.
    """
    for i, neighbours in missing.items():
        recorder.fault(t, "measurement", agent_ids[i], ",".join(neighbours))


def note_errors(recorder: RunRecorder, t: float, agent_ids: Sequence[str], errors: Sequence[tuple[int, str]]) -> None:
    """Every agent at ERROR for its controller (saturated: outside a funnel, or a non-finite wrench)
    is a ``controller`` fault: ``errors`` (agent index, reason) excludes agents missing a pose."""
    for i, message in errors:
        recorder.fault(t, "controller", agent_ids[i], message)


class AgentTeam:
    """Every agent's controller of ``spec``, in formation-file order, stepped as each agent's own
    process steps it: :func:`formation_agent.controller.agent_step` in the agent's code form
    (compiled or interpreted: :meth:`set_form`), with the gains the agent uses (:meth:`set_gains`),
    at the agent's time (the step's stamp) on the values the agent decodes.

    With the same inputs, form and numeric platform as the agent, its answer is the agent's to the
    bit; for an agent on another platform :meth:`bound` gives how far a correct answer may be off
    (:mod:`formation_agent.roundoff`).
    """

    def __init__(self, spec: FormationSpec) -> None:
        self.ids = spec.agent_ids
        views = [agent_view(spec, a) for a in self.ids]
        self.first_end, self.agents, self.ends = gains(views)
        self.end_neighbours = [ie.neighbour for v in views for ie in v.edges]
        self._pairs = [(v.agent_id, ie.neighbour) for v in views for ie in v.edges]
        self._checked: Ends | None = None
        n_agents, n = len(self.ids), len(self.end_neighbours)
        self.start = new_funnel_start(n_agents)
        self.out, self.edge_out = new_outputs(n_agents, n)
        self._ends_of = [(int(self.first_end[i]), int(self.first_end[i + 1])) for i in range(n_agents)]
        self.forms = [CODE_FORM] * n_agents
        self._step = [agent_step] * n_agents
        #: whether each agent's velocity funnel started at the step evaluated last
        self.started_now = [False] * n_agents
        #: the round-off state of every agent (formation_agent.roundoff)
        self.rho_v0_bound = np.full((n_agents, 6), np.nan)
        self._work = np.zeros((4, 6))
        self._bound_out, self._bound_edge = new_outputs(n_agents, n)
        # load (or compile) the kernels now, on scratch outputs: not at a realtime run's first step
        p, R, v = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n_agents, 6))
        everyone = np.ones(n, dtype=np.bool_)  # every agent steps (a missing pose would skip agent_step)
        scratch = (new_funnel_start(n_agents), *new_outputs(n_agents, n))
        team_step(0.0, p, R, everyone, v, self.first_end, self.agents, self.ends, *scratch)
        lo, hi = int(self.first_end[0]), int(self.first_end[1])
        agent_step(0.0, 0, lo, hi, p, R, v[0], self.agents, self.ends, *scratch)
        answer_bounds(0.0, 0, lo, hi, p, R, v[0], self.agents, self.ends, scratch[0], scratch[1],
                      np.full((n_agents, 6), np.nan), self._work, *new_outputs(n_agents, n))  # fmt: skip

    def set_form(self, i: int, form: str) -> bool:
        """Step agent i in code ``form`` from now on; False (nothing changes) where this process
        cannot run it (compiled code in an interpreted process)."""
        step = in_code_form(agent_step, form)
        if step is None:
            return False
        self.forms[i], self._step[i] = form, step
        return True

    def gains_of(self, i: int) -> tuple[float, float]:
        """Agent i's gains (δ_i, γ_i) as the team steps it."""
        return float(self.agents[i, DELTA]), float(self.agents[i, GAMMA])

    def set_gains(self, i: int, delta: float, gamma: float) -> None:
        """Step agent i with gains δ_i, γ_i from the next evaluation on (its funnel start is kept, as
        an agent keeps it)."""
        self.agents[i, DELTA], self.agents[i, GAMMA] = delta, gamma

    def _check_order(self, meas: Measurements) -> None:
        if meas.ends is not self._checked:  # the measurements' end order must be the kernels'
            if list(zip(meas.ends.observer, meas.ends.target)) != self._pairs:
                raise ValueError("measurements by edge end in another order than the team's controllers")
            self._checked = meas.ends

    def step(self, i: int, meas: Measurements, agents: np.ndarray | None = None) -> None:
        """Agent i's step on ``meas`` (at its time ``meas.t``, the stamp's) into row i of :attr:`out`
        and its ends of :attr:`edge_out`: the fault wrench when one of its poses is missing.
        ``agents`` replaces the gains of every agent (a trial of other gains)."""
        lo, hi = self._ends_of[i]
        if not all(meas.in_range[lo:hi]):
            fault_wrench(i, lo, hi, REASON_MISSING, self.out, self.edge_out, self.start)
            return
        self._step[i](
            meas.t, i, lo, hi, meas.p_rel, meas.R_rel, meas.velocities[i],
            self.agents if agents is None else agents, self.ends, self.start, self.out, self.edge_out,
        )  # fmt: skip

    def evaluate(
        self, meas: Measurements, recorder: RunRecorder | None
    ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, str]]]:
        """(u (N,6), margin_v (N,6), errors) at ``meas.t``; ``errors`` lists (agent index, reason) of
        the agents at ERROR for their controller (:meth:`note_errors` records them). With a recorder,
        the agents missing a pose are recorded now (``measurement`` faults)."""
        self._check_order(meas)
        out, in_range = self.out, meas.in_range
        unstarted = np.isnan(self.start[:, T0]).tolist()
        for i in range(len(self.ids)):
            self.step(i, meas)
        if any(unstarted):  # an agent's funnel starts at its first step with every pose
            started = np.isnan(self.start[:, T0]).tolist()
            self.started_now = [before and not after for before, after in zip(unstarted, started)]
        elif any(self.started_now):
            self.started_now = [False] * len(self.ids)
        errors: list[tuple[int, str]] = []
        if not in_range.all() or out[:, LEVEL].max() == ERROR:
            missing, errors = step_faults(self.first_end, self.end_neighbours, in_range, out[:, LEVEL], out[:, REASON])
            if recorder is not None:
                note_missing(recorder, meas.t, self.ids, missing)
        return out[:, U : U + 6].copy(), out[:, MARGIN_V : MARGIN_V + 6].copy(), errors

    def errors(self, meas: Measurements) -> list[tuple[int, str]]:
        """(agent index, reason) of every agent at ERROR for its controller at ``meas``, the step
        evaluated last (the agents missing a pose are :meth:`evaluate`'s ``measurement`` faults)."""
        out = self.out
        if out[:, LEVEL].max() != ERROR:
            return []
        return step_faults(self.first_end, self.end_neighbours, meas.in_range, out[:, LEVEL], out[:, REASON])[1]

    def bound(self, i: int, meas: Measurements, trial: Trial | None = None) -> np.ndarray:
        """How far a correct answer of agent i to ``meas`` may be from the team's, per wrench component
        [N, N·m] (after :meth:`evaluate`; of a :meth:`trial`'s answer if given):
        :func:`formation_agent.roundoff.tolerance` of the step's round-off bound; zeros for the fault
        wrench (exact on every platform)."""
        lo, hi = int(self.first_end[i]), int(self.first_end[i + 1])
        if not meas.in_range[lo:hi].all():
            return np.zeros(6)
        agents, out, start = self.agents, self.out, self.start
        if trial is not None:
            agents, out, start = self.agents.copy(), self.out.copy(), self.start.copy()
            agents[i, DELTA], agents[i, GAMMA] = trial.delta, trial.gamma
            out[i], start[i] = trial.out, trial.start
        answer_bounds(
            meas.t, i, lo, hi, meas.p_rel, meas.R_rel, meas.velocities[i], agents, self.ends,
            start, out, self.rho_v0_bound, self._work, self._bound_out, self._bound_edge,
        )  # fmt: skip
        return np.asarray(tolerance(self._bound_out[i, U : U + 6]))

    def trial(self, i: int, meas: Measurements, delta: float, gamma: float) -> Trial:
        """Agent i's answer to ``meas`` with gains δ, γ instead of its own (after :meth:`evaluate`),
        leaving the team as it was; :meth:`adopt` makes it the agent's."""
        agents = self.agents.copy()
        agents[i, DELTA], agents[i, GAMMA] = delta, gamma
        keep = (self.out[i].copy(), self.edge_out.copy(), self.start[i].copy())
        if self.started_now[i]:
            self.start[i] = np.nan  # the funnel starts at this step: from the trial's own e_v(0)
        self.step(i, meas, agents)
        trial = Trial(i, delta, gamma, self.out[i].copy(), self.edge_out.copy(), self.start[i].copy())
        self.out[i], self.edge_out[:], self.start[i] = keep
        return trial

    def adopt(self, trial: Trial) -> None:
        """Agent ``trial.i`` uses the trial's gains: from its step on, its outputs and funnel start are the trial's."""
        i = trial.i
        lo, hi = int(self.first_end[i]), int(self.first_end[i + 1])
        self.set_gains(i, trial.delta, trial.gamma)
        self.out[i] = trial.out
        self.edge_out[lo:hi] = trial.edge_out[lo:hi]
        self.start[i] = trial.start

    def note_errors(self, t: float, errors: Sequence[tuple[int, str]], recorder: RunRecorder) -> None:
        """Record :meth:`evaluate`'s ``errors`` (``controller`` faults)."""
        note_errors(recorder, t, self.ids, errors)


@dataclass(frozen=True)
class Trial:
    """Agent i's outputs at one step with gains δ, γ (:meth:`AgentTeam.trial`)."""

    i: int
    delta: float
    gamma: float
    out: np.ndarray
    edge_out: np.ndarray
    start: np.ndarray

    @property
    def u(self) -> np.ndarray:
        """The wrench (6,) [N, N·m], body frame."""
        return self.out[U : U + 6]

    @property
    def margin_v(self) -> np.ndarray:
        """The velocity-funnel margins (6,)."""
        return self.out[MARGIN_V : MARGIN_V + 6]
