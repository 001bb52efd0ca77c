"""The simulator's stepping policy, without ROS (docs/ros2.md, "Modes").

- :class:`LockstepWait`: who must answer step k before the world advances: every agent (its
  wrench stamped k). Resends an unanswered step to the agents that have not answered after
  ``resend`` wall seconds; after ``step_timeout`` sends it a last time, and names who has still not
  answered :data:`LAST_CALL` s later.
- :class:`CommandHold`: realtime zero-order hold of each agent's latest wrench, replaced by zero
  once older than ``command_timeout`` (sim time); every tick without the agent's answer to the
  previous step is a counted fault (a held, stale command or a zeroed wrench).
- :class:`LagBudget`: realtime lag behind the wall clock; a run further behind than its budget
  stops INCOMPLETE.
- :class:`WrenchBook`: the latest wrench of each agent, kept by stamp (what the node's
  subscriptions accept).
- :class:`AnswerWitness`: lockstep: the wrench each agent must answer the current step with (the
  shadow controllers' on what the agent received: :class:`formation_sim.core.team.AgentTeam`), bit
  for bit where the shadow runs the agent's own code on the agent's platform, else within the
  round-off bound of the step (:mod:`formation_agent.roundoff`); an answer beyond it is not applied
  (fault ``answer_mismatch``) and the step stays unanswered; the same answer again to the step
  re-sent names the agent (:class:`WrongAnswerError`).

Times: ``ns`` are simulation stamps in integer nanoseconds, ``now`` wall seconds (monotonic).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field

import numpy as np

from formation_core.faults import ANSWER_MISMATCH
from formation_msgs_py.wrench_checks import DROPPED_KINDS
from formation_sim.node.witness import AGREES_NEW_GAINS, DIFFERS, AnswerWitness

NS = 1_000_000_000
#: wall s between a lockstep step's last resend, at its timeout, and naming the agents still silent.
#: The timeout counts wall time, also while the simulator itself was held up (stopped, a stalled
#: disk, a busy machine): answers sent meanwhile wait in its queues, and a lost one is sent again.
#: After a 2.5 s SIGSTOP of the simulator, answers to the resend took up to ~1.75 s (0.5 s named an
#: agent in about a quarter of the runs).
LAST_CALL = 3.0


class ParticipantMissingError(RuntimeError):
    """An agent was not matched, or did not answer a lockstep step within the step timeout."""

    def __init__(self, names: list[str], message: str) -> None:
        super().__init__(message)
        self.names = names


class WrongAnswerError(RuntimeError):
    """Lockstep: an agent answered a step only with wrenches the witness refuses (the same one again
    to the step re-sent, or none agreeing before the step timeout)."""

    def __init__(self, names: list[str], message: str) -> None:
        super().__init__(message)
        self.names = names


@dataclass
class WrenchBook:
    """The latest wrench (stamp ns, 6 values) of each of ``n`` agents."""

    n: int
    stamp: list[int] = field(default_factory=list)
    value: list[tuple[float, ...]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.stamp = [-1] * self.n
        self.value = [(0.0,) * 6] * self.n

    def repeats(self, i: int, ns: int, u: tuple[float, ...]) -> bool:
        """True if agent i's wrench stamped ns is exactly the answer already kept (a duplicate)."""
        return ns == self.stamp[i] and u == self.value[i]

    def accept(self, i: int, ns: int, u: tuple[float, ...]) -> bool:
        """Keep agent i's wrench stamped ns; False if older than what it has (a late duplicate)."""
        if ns < self.stamp[i]:
            return False
        first = ns != self.stamp[i]
        self.stamp[i] = ns
        self.value[i] = u
        return first


@dataclass
class LockstepWait:
    """Who still owes an answer to the current step, and what to do about it."""

    ids: tuple[str, ...]
    step_timeout: float
    resend: float
    #: wall s the first step may wait (at least step_timeout): the simulator starts once it has matched
    #: every agent's endpoints on its own side, but an agent's reader may match the simulator's writer
    #: later; with 40 agents on two busy cores one took longer than step_timeout (step 0 resent 31 times)
    first_step_timeout: float = 0.0
    resends: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.resends = [0] * len(self.ids)
        self.ns = -1
        self.next_resend = 0.0
        self.deadline = 0.0
        self.last_call = False

    def begin(self, ns: int, now: float) -> None:
        """Step ``ns`` was published at wall time ``now``."""
        first = self.ns == -1
        self.ns = ns
        self.next_resend = now + self.resend
        self.deadline = now + (max(self.step_timeout, self.first_step_timeout) if first else self.step_timeout)
        self.last_call = False

    def late_agents(self, wrenches: WrenchBook) -> list[int]:
        return [i for i, s in enumerate(wrenches.stamp) if s != self.ns]

    def done(self, wrenches: WrenchBook) -> bool:
        return all(s == self.ns for s in wrenches.stamp)

    def poll(
        self,
        wrenches: WrenchBook,
        now: float,
        mismatched: Collection[int] = (),
        collect: Callable[[], object] | None = None,
    ) -> list[int]:
        """Agents to send the step again now (empty: keep waiting until :meth:`wake_at`).

        At the step timeout the late agents get a last resend; raises ParticipantMissingError
        naming those still late :data:`LAST_CALL` s after it (those in ``mismatched``, whose
        answers to the step all differed from the witness, as such). Before naming anyone,
        ``collect`` takes the answers already received into ``wrenches``: a simulator held up in its
        own thread (beside two busy loops, ~1.9 s between publishing the step in which an agent was
        SIGKILLed and its first look at the answers) may not have run their callbacks yet, and an
        answer waiting in its queue is no silence.
        """
        late = self.late_agents(wrenches)
        if late and collect is not None and self.last_call and now >= self.deadline:
            collect()
            late = self.late_agents(wrenches)
        if not late:
            return []
        if now >= self.deadline:
            if self.last_call:
                silent = [self.ids[i] for i in late if i not in mismatched]
                wrong = [self.ids[i] for i in late if i in mismatched]
                within = (
                    f"for the step at t={self.ns / NS:.6f} s within step_timeout={self.step_timeout:g} s "
                    f"and {LAST_CALL:g} s after a last resend"
                )
                refused = f"only answers the witness refused ({ANSWER_MISMATCH}) from {_agents(wrong)}"
                if silent:
                    what = f"no answer from {_agents(silent)}" + (f"; {refused}" if wrong else "")
                    raise ParticipantMissingError(silent + wrong, f"lockstep: {what} {within}")
                raise WrongAnswerError(wrong, f"lockstep: {refused} {within}")
            self.last_call = True
            self.deadline = now + LAST_CALL
        elif now < self.next_resend:
            return []
        self.next_resend = now + self.resend
        for i in late:
            self.resends[i] += 1
        return late

    def wake_at(self) -> float:
        """Wall time of the next resend or timeout."""
        return min(self.deadline, self.next_resend)


def _agents(ids: Sequence[str]) -> str:
    return ", ".join(f"agent {a}" for a in ids)


#: what :func:`admit` decides about an answer
APPLY, DUPLICATE, IGNORE, MISMATCH = "apply", "duplicate", "ignore", "mismatch"


@dataclass(frozen=True)
class Admission:
    """:func:`admit`'s decision: ``action`` (APPLY ``u``; DUPLICATE, IGNORE: nothing changes;
    MISMATCH: counted, not applied, ``difference`` [N or N·m] from the witness, beyond ``tolerance``).
    ``new_gains``: the answer agreed with the agent's new gains (AnswerWitness.alternative)."""

    action: str
    u: tuple[float, ...] = ()
    difference: float = 0.0
    tolerance: float = 0.0
    new_gains: bool = False


def admit(
    i: int,
    ns: int,
    u: tuple[float, ...],
    refusal_kind: str | None,
    wrenches: WrenchBook,
    witness: AnswerWitness | None,
) -> Admission:
    """What to do with agent i's wrench ``u`` stamped ``ns`` that the wrench checks refused as
    ``refusal_kind`` (formation_msgs_py.wrench_checks; None: passed), given the answers kept and,
    in lockstep, the witness.

    A refused stamp answers no step; a refused value answers an unanswered step with zero, except
    in lockstep (the witness waits for the agent's answer). In lockstep a step once answered keeps
    its answer, and an answer the witness disagrees with is never applied.
    """
    if refusal_kind is not None:
        if refusal_kind in DROPPED_KINDS or ns == wrenches.stamp[i] or witness is not None:
            return Admission(IGNORE)
        return Admission(APPLY, (0.0,) * 6)
    if witness is not None:
        verdict, difference, tol = witness.judge(i, ns, u)
        if verdict == DIFFERS:
            return Admission(MISMATCH, tuple(u), difference, tol)
        if ns == wrenches.stamp[i]:
            return Admission(DUPLICATE)
        return Admission(APPLY, tuple(u), new_gains=verdict == AGREES_NEW_GAINS)
    return Admission(APPLY, tuple(u))


#: realtime fault kinds (formation_core.faults): an older wrench held, or zero applied instead
STALE_COMMAND, ZERO_WRENCH = "stale_command", "zero_wrench"


@dataclass
class CommandHold:
    """Realtime zero-order hold: agent i's latest wrench until it is older than ``timeout_ns``."""

    timeout_ns: int

    def applied(self, wrenches: WrenchBook, ns: int) -> tuple[np.ndarray, list[tuple[int, str, str]]]:
        """(u (N,6), [(agent index, fault kind, detail)]) for the tick after step ``ns``.

        Every agent whose answer to step ``ns`` is not in is a fault: ``stale_command`` while its
        latest wrench (or none, in a run younger than the timeout) is held, ``zero_wrench`` once
        that wrench is older than the timeout and zero is applied instead.
        """
        u = np.zeros((wrenches.n, 6))
        faults = []
        for i, (s, val) in enumerate(zip(wrenches.stamp, wrenches.value)):
            if s >= ns:
                u[i] = val
            elif s >= 0 and ns - s <= self.timeout_ns:
                u[i] = val
                faults.append((i, STALE_COMMAND, f"held the wrench of t={s / NS:.4f} s"))
            elif s < 0 and ns <= self.timeout_ns:
                faults.append((i, STALE_COMMAND, "no wrench yet"))
            else:
                why = "no wrench yet" if s < 0 else f"last wrench {(ns - s) / NS:.3f} s old"
                faults.append((i, ZERO_WRENCH, why))
        return u, faults


@dataclass(frozen=True)
class LagBudget:
    """Realtime: how far [wall s] a tick may lag behind its wall-clock target."""

    budget: float
    period: float

    def exceeded(self, lag: float) -> bool:
        return lag > self.budget

    def late(self, lag: float) -> bool:
        """A tick more than half a period late (a counted fault)."""
        return lag > 0.5 * self.period
