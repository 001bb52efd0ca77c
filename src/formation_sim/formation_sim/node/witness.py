"""Lockstep's witness: what every agent must answer each step with, and whether an answer is it.

The simulator runs every agent's controller itself (its *shadow*:
:class:`formation_sim.core.team.AgentTeam`) on exactly what the agent received (the published
values, decoded by the agent's own decoder), at the agent's time (the step's stamp), in the
agent's code form and with the gains the agent uses. An agent reports its code form and numeric
platform (read-only parameters, :mod:`formation_core.numba_kernels`); where the simulator can run
the agent's form on the agent's platform, an answer must equal the shadow's **bit for bit**;
otherwise (another host, another CPU or libm, a form the simulator cannot run) it must lie within
the step's **round-off bound** (:mod:`formation_agent.roundoff`, docs/controller.md). An answer
beyond is not applied (fault ``answer_mismatch``); an agent that answers the step re-sent with the
same refused wrench is named (stepping.WrongAnswerError, exit status 5).

Gains: the simulator reads every agent's δ and γ before the first step (a parameters file or a
command line may have set them) and follows every live change (``/parameter_events``; on a refused
answer it reads them again). An agent applies a change from its next step, which the simulator
cannot see: until an answer with the new gains comes, either answer is right
(:meth:`Witness.gains_changed`). :meth:`Witness.report` says which gains each agent used from when.

No ROS here: the node translates messages, parameters and events into these calls.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from formation_core.formation import FormationSpec
from formation_core.numba_kernels import CODE_FORM, FORM_COMPILED, FORM_INTERPRETED, numeric_platform
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements
from formation_sim.core.team import AgentTeam, Trial


@dataclass(frozen=True)
class Expectation:
    """What an agent must answer a step with: ``u`` (6,) [N, N·m], and per component how far an
    answer may be from it (``tolerance``, from the step's round-off bound), or None: bit for bit."""

    u: tuple[float, ...]
    tolerance: tuple[float, ...] | None = None

    def difference(self, answer: Sequence[float]) -> tuple[float, float] | None:
        """None if ``answer`` agrees; else (largest component difference, that component's
        tolerance: 0 for bit for bit). NaN never agrees."""
        tol = self.tolerance
        if tol is None and tuple(answer) == self.u:  # the usual case, one comparison (NaN never equals)
            return None
        d = [abs(a - b) for a, b in zip(answer, self.u)]
        if tol is not None and all(x <= t for x, t in zip(d, tol)):
            return None
        c = max(range(6), key=lambda k: d[k] if d[k] == d[k] else math.inf)
        return (d[c] if d[c] == d[c] else math.inf), (0.0 if tol is None else tol[c])


#: how :meth:`AnswerWitness.judge` found an answer: agrees, agrees with an agent's new gains, differs
AGREES, AGREES_NEW_GAINS, DIFFERS = "agrees", "agrees_new_gains", "differs"


@dataclass
class AnswerWitness:
    """Lockstep: what every agent of ``ids`` must answer the current step with (docs/ros2.md, "Modes").

    :meth:`expect` takes the shadow controllers' answers to the step (computed on exactly what each
    agent received, at its time, in its code form: :class:`formation_sim.core.team.AgentTeam`), each
    with its tolerance (None: bit for bit), and, for an agent whose gains changed, the answer with the
    new gains (an agent applies a change from its next step, which the simulator cannot see: either
    answer is right until one with the new gains comes). :meth:`judge` tells whether an answer may
    be applied; the largest differences and ratios to the tolerance that agreed are kept for
    :meth:`report`.
    """

    ids: tuple[str, ...]
    ns: int = -1
    expected: list[Expectation] = field(default_factory=list)
    #: agent index -> the answer with its new gains, while it may still answer with its old ones
    alternative: dict[int, Expectation] = field(default_factory=dict)
    #: agent index -> (its last answer to the current step that differed, how often it came)
    mismatched: dict[int, tuple[tuple[float, ...], int]] = field(default_factory=dict)
    #: per agent: the largest difference [N or N·m] of an answer that agreed, and its ratio to the tolerance
    largest_agreed: list[float] = field(default_factory=list)
    largest_ratio: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.largest_agreed = [0.0] * len(self.ids)
        self.largest_ratio = [0.0] * len(self.ids)

    def expect(
        self, ns: int, expected: Sequence[Expectation], alternative: dict[int, Expectation] | None = None
    ) -> None:
        """The witness of step ``ns``: one :class:`Expectation` per agent, and the answers with new gains."""
        self.ns = ns
        self.expected = list(expected)
        self.alternative = dict(alternative or {})
        self.mismatched = {}

    def judge(self, i: int, ns: int, u: Sequence[float]) -> tuple[str, float, float]:
        """(AGREES, AGREES_NEW_GAINS or DIFFERS, the largest component difference [N or N·m], its
        tolerance) of agent i's answer ``u`` to step ``ns``; an answer to another step than the
        current one AGREES (the stamp checks decide those)."""
        if ns != self.ns:
            return AGREES, 0.0, 0.0
        for verdict, expected in ((AGREES, self.expected[i]), (AGREES_NEW_GAINS, self.alternative.get(i))):
            if expected is None:
                continue
            off = expected.difference(u)
            if off is None:
                self._agreed(i, u, expected)
                return verdict, 0.0, 0.0
        difference, tol = self.expected[i].difference(u) or (0.0, 0.0)
        previous = self.mismatched.get(i)
        answer = tuple(u)
        self.mismatched[i] = (answer, previous[1] + 1 if previous is not None and previous[0] == answer else 1)
        return DIFFERS, difference, tol

    def _agreed(self, i: int, u: Sequence[float], expected: Expectation) -> None:
        tol = expected.tolerance
        if tol is None:
            return
        for a, b, t in zip(u, expected.u, tol):
            d = abs(a - b)
            if d > self.largest_agreed[i]:
                self.largest_agreed[i] = d
            if t > 0 and d / t > self.largest_ratio[i]:
                self.largest_ratio[i] = d / t

    def repeated(self) -> list[int]:
        """Agents that gave the same refused answer to the current step more than once (to its resend)."""
        return [i for i, (_, count) in self.mismatched.items() if count > 1]

    def report(self) -> dict[str, Any]:
        """For summary.json ``witness``: per agent, the largest difference that agreed and its ratio
        to the tolerance (both 0 for an agent judged bit for bit)."""
        return {
            a: {"largest_agreed_difference": d, "largest_ratio_to_tolerance": r}
            for a, d, r in zip(self.ids, self.largest_agreed, self.largest_ratio)
        }


#: how an agent's answers are judged
BIT_FOR_BIT, WITHIN_BOUND = "bit for bit", "within the round-off bound"
#: where the gains of an agent came from (summary.json ``witness``)
FROM_FILE, FROM_PARAMETERS, FROM_LIVE_CHANGE = "formation file", "parameters", "live change"


@dataclass(frozen=True)
class AgentReport:
    """What an agent reports of itself (its parameters): code form, numeric platform, δ and γ.
    A value it did not report is None (an agent of another version)."""

    code_form: str | None
    platform: str | None
    delta: float | None
    gamma: float | None


class Witness:
    """The shadow of every agent and the judgement of their answers, one step at a time (lockstep),
    or the shadow alone (realtime: ``judging`` False, its margins and faults are the run's record)."""

    def __init__(self, spec: FormationSpec, *, judging: bool = True) -> None:
        self.ids = spec.agent_ids
        self.team = AgentTeam(spec)
        self.answers = AnswerWitness(self.ids)
        self.judging = judging
        n = len(self.ids)
        self.platform = numeric_platform()
        #: per agent: judged bit for bit (True) or within the round-off bound
        self.exact = [True] * n
        self.forms: list[str | None] = [None] * n
        #: per agent: [{from_t, delta, gamma, source}] in the order they were used
        self.gains: list[list[dict[str, Any]]] = [
            [{"from_t": 0.0, "delta": d, "gamma": g, "source": FROM_FILE}]
            for d, g in (self.team.gains_of(i) for i in range(n))
        ]
        #: agent index -> (δ, γ, source) it may be switching to
        self.pending: dict[int, tuple[float, float, str]] = {}
        self.trials: dict[int, Trial] = {}
        #: agents whose answer to the current step agreed with their new gains
        self.adopted: set[int] = set()
        self.received: Measurements | None = None

    # -- what the agents report -------------------------------------------------------------------

    def agent_reported(self, i: int, report: AgentReport) -> None:
        """Agent i's own report, before the first step: its code form and platform decide how its
        answers are judged, its gains are the ones it uses."""
        form = report.code_form if report.code_form in (FORM_COMPILED, FORM_INTERPRETED) else None
        self.forms[i] = form
        same_platform = report.platform == self.platform
        self.exact[i] = form is not None and same_platform and self.team.set_form(i, form)
        delta, gamma = self.team.gains_of(i)
        delta = delta if report.delta is None else float(report.delta)
        gamma = gamma if report.gamma is None else float(report.gamma)
        if (delta, gamma) != self.team.gains_of(i):
            self.team.set_gains(i, delta, gamma)
            self.gains[i] = [{"from_t": 0.0, "delta": delta, "gamma": gamma, "source": FROM_PARAMETERS}]

    # -- one step ---------------------------------------------------------------------------------

    def step(self, received: Measurements, recorder: RunRecorder | None) -> tuple[np.ndarray, list[tuple[int, str]]]:
        """The shadow's answers to ``received`` (what the agents decoded), and, judging, the
        expectations of the step; (margin_v (N,6), controller errors) for the record (a margin of
        an agent that then answers with new gains is replaced by :meth:`answered`)."""
        self.received = received
        self.adopted = set()
        u, margin_v, errors = self.team.evaluate(received, recorder)
        if not self.judging:
            return margin_v, errors
        expected = [Expectation(tuple(u[i].tolist()), self._tolerance(i, received)) for i in range(len(self.ids))]
        self.trials = {i: self.team.trial(i, received, d, g) for i, (d, g, _) in self.pending.items()}
        alternative = {i: self._expectation(t, received) for i, t in self.trials.items()}
        self.answers.expect(received.ns, expected, alternative)
        return margin_v, errors

    def _tolerance(self, i: int, received: Measurements, trial: Trial | None = None) -> tuple[float, ...] | None:
        if self.exact[i]:
            return None
        return tuple(self.team.bound(i, received, trial).tolist())

    def _expectation(self, trial: Trial, received: Measurements) -> Expectation:
        return Expectation(tuple(trial.u.tolist()), self._tolerance(trial.i, received, trial))

    def answered(self, margin_v: np.ndarray, t: float) -> list[tuple[int, str]]:
        """Every agent answered the step at sim time ``t`` [s]: the agents that answered with new gains
        use them from now on; their margins replace the shadow's in ``margin_v`` (N,6). Returns the
        controller errors of the step as answered."""
        for i in sorted(self.adopted):
            trial = self.trials.pop(i)
            delta, gamma, source = self.pending.pop(i)
            self.team.adopt(trial)
            margin_v[i] = trial.margin_v
            self.gains[i].append({"from_t": t, "delta": delta, "gamma": gamma, "source": source})
        return self.team.errors(self.received) if self.received is not None else []

    def gains_of(self, i: int) -> tuple[float, float]:
        """The gains (δ, γ) agent i uses, or is switching to."""
        pending = self.pending.get(i)
        return self.team.gains_of(i) if pending is None else pending[:2]

    def gains_changed(
        self, i: int, delta: float | None, gamma: float | None, t: float, source: str = FROM_LIVE_CHANGE
    ) -> tuple[float, ...] | None:
        """Agent i's δ and/or γ changed (None: unchanged) at sim time ``t`` [s]. Judging: its answers
        with the new gains agree from now on, its old ones until the first new one; returns its
        refused answer to the current step when that one agrees with the new gains (to apply now).
        Not judging: the shadow uses the new gains from the next step."""
        old_delta, old_gamma = self.gains_of(i)
        new = (old_delta if delta is None else float(delta), old_gamma if gamma is None else float(gamma))
        if new == (old_delta, old_gamma):
            return None
        if not self.judging:
            self.team.set_gains(i, *new)
            self.gains[i].append({"from_t": t, "delta": new[0], "gamma": new[1], "source": source})
            return None
        if new == self.team.gains_of(i):  # changed back before using the pending gains
            self.pending.pop(i, None)
            self.trials.pop(i, None)
            self.answers.alternative.pop(i, None)
            return None
        self.pending[i] = (*new, source)
        received = self.received
        if received is None or received.ns != self.answers.ns:
            return None  # before the first step: the next step tries them
        trial = self.team.trial(i, received, *new)
        self.trials[i] = trial
        self.answers.alternative[i] = self._expectation(trial, received)
        refused = self.answers.mismatched.get(i)
        if refused is not None and self.answers.alternative[i].difference(refused[0]) is None:
            self.answers.mismatched.pop(i)
            self.adopted.add(i)
            return refused[0]
        return None

    def report(self) -> dict[str, Any]:
        """summary.json ``witness``: per agent, how its answers were judged, its code form, the gains it
        used from when, and the largest difference that agreed (with its ratio to the tolerance)."""
        answers = self.answers.report()
        return {
            "platform": self.platform,
            "code_form": CODE_FORM,
            "agents": {
                a: {
                    "judged": BIT_FOR_BIT if self.exact[i] else WITHIN_BOUND,
                    "code_form": self.forms[i],
                    "gains": self.gains[i],
                    **answers[a],
                }
                for i, a in enumerate(self.ids)
            },
        }
