"""The simulator's stepping policy without ROS: who answers a lockstep step, resend, timeout, hold, lag."""

from __future__ import annotations

import numpy as np
import pytest

from formation_sim.node.stepping import (
    APPLY,
    DUPLICATE,
    IGNORE,
    LAST_CALL,
    MISMATCH,
    NS,
    Admission,
    CommandHold,
    LagBudget,
    LockstepWait,
    ParticipantMissingError,
    WrenchBook,
    WrongAnswerError,
    admit,
)
from formation_sim.node.witness import AnswerWitness, Expectation

pytestmark = pytest.mark.numeric

IDS = ("1", "2", "3")
PERIOD_NS = 100_000  # 10 kHz


def wait() -> LockstepWait:
    return LockstepWait(IDS, step_timeout=2.0, resend=0.25)


def test_wrench_book_keeps_the_latest_stamp() -> None:
    """A wrench older than the one kept is a late duplicate (a re-sent step answered twice): ignored."""
    book = WrenchBook(2)
    assert book.accept(0, 200, (1.0,) * 6)
    assert not book.accept(0, 200, (2.0,) * 6)  # the same step again: kept, not a new answer
    assert book.value[0] == (2.0,) * 6
    assert not book.accept(0, 100, (3.0,) * 6)
    assert book.stamp == [200, -1] and book.value[0] == (2.0,) * 6


def test_wrench_book_tells_a_repeated_answer() -> None:
    """The same stamp and values again is a duplicate (an agent answering a re-sent step twice); a
    different value or another stamp is not, so it still goes through the simulator's checks."""
    book = WrenchBook(2)
    assert not book.repeats(0, 200, (1.0,) * 6)  # nothing kept yet
    book.accept(0, 200, (1.0,) * 6)
    assert book.repeats(0, 200, (1.0,) * 6)
    assert not book.repeats(0, 200, (1.0,) * 5 + (1.5,))
    assert not book.repeats(0, 300, (1.0,) * 6)
    assert not book.repeats(1, 200, (1.0,) * 6)


def test_lockstep_waits_for_every_agent() -> None:
    """The step is done once every agent answered it; a resend goes to the late agents only."""
    w, book = wait(), WrenchBook(3)
    w.begin(0, now=10.0)
    book.accept(0, 0, (0.0,) * 6)
    book.accept(2, 0, (0.0,) * 6)
    assert not w.done(book)
    assert w.poll(book, now=10.1) == []  # before the resend time
    assert w.wake_at() == 10.25
    assert w.poll(book, now=10.3) == [1]
    assert w.resends == [0, 1, 0]
    book.accept(1, 0, (0.0,) * 6)
    assert w.done(book)


def test_lockstep_names_who_stopped_answering() -> None:
    """At the step timeout the late agents get a last resend; LAST_CALL s later those still late are named."""
    w, book = wait(), WrenchBook(3)
    w.begin(5 * PERIOD_NS, now=0.0)
    book.accept(1, 5 * PERIOD_NS, (0.0,) * 6)
    assert w.poll(book, now=1.99) == [0, 2]  # a resend, not yet the timeout
    assert w.poll(book, now=2.0) == [0, 2]  # the timeout: the last resend
    assert w.wake_at() == 2.25  # resends go on meanwhile
    assert w.poll(book, now=2.0 + LAST_CALL - 0.01) == [0, 2]
    assert w.wake_at() == 2.0 + LAST_CALL
    with pytest.raises(ParticipantMissingError, match=r"agent 1, agent 3 .* t=0\.000500 s") as err:
        w.poll(book, now=2.0 + LAST_CALL)
    assert err.value.names == ["1", "3"]


def test_lockstep_takes_answers_sent_while_the_simulator_was_held_up() -> None:
    """The timeout counts wall time, also while the simulator was stopped: the first look after it
    resends to whoever is still late instead of naming them, and their answers complete the step."""
    w, book = wait(), WrenchBook(3)
    w.begin(0, now=0.0)
    book.accept(0, 0, (0.0,) * 6)
    assert w.poll(book, now=5.0) == [1, 2]  # held up 5 s: a last resend, nobody named
    book.accept(1, 0, (0.0,) * 6)
    book.accept(2, 0, (0.0,) * 6)
    assert w.done(book) and w.poll(book, now=9.0) == []
    assert w.resends == [0, 1, 1]
    w.begin(PERIOD_NS, now=10.0)  # the next step has a whole timeout and a last call of its own
    assert w.poll(book, now=12.0) == [0, 1, 2]
    with pytest.raises(ParticipantMissingError):
        w.poll(book, now=12.0 + LAST_CALL)


def test_answers_waiting_in_the_simulators_queue_are_taken_before_anyone_is_named() -> None:
    """Held up past the last call (a publish that blocked), the simulator first takes the answers waiting
    in its queue: only the agent that never answered is named, not those whose callbacks had not run."""
    w, book = wait(), WrenchBook(3)
    w.begin(0, now=0.0)
    assert w.poll(book, now=2.0) == [0, 1, 2]  # the timeout: the last resend
    queued = [(0, (1.0,) * 6), (2, (2.0,) * 6)]  # agents 1 and 3 answered; their callbacks have not run

    def collect() -> None:
        for i, u in queued:
            book.accept(i, 0, u)

    with pytest.raises(ParticipantMissingError, match=r"no answer from agent 2 for the step") as err:
        w.poll(book, now=2.0 + LAST_CALL, collect=collect)
    assert err.value.names == ["2"]
    assert book.value[0] == (1.0,) * 6 and book.value[2] == (2.0,) * 6


def test_nothing_is_collected_before_the_last_call_ends() -> None:
    """Before the last call's end a poll only resends (the loop's spin takes the answers): collect is not run."""
    w, book = wait(), WrenchBook(3)
    w.begin(0, now=0.0)
    calls = []
    assert w.poll(book, now=0.3, collect=lambda: calls.append(1)) == [0, 1, 2]
    assert w.poll(book, now=2.0, collect=lambda: calls.append(1)) == [0, 1, 2]  # the last resend
    assert calls == []


def test_command_hold_counts_stale_and_zeroed_wrenches() -> None:
    """Realtime: the latest wrench is held (a stale command) until older than the command timeout,
    then zero (a zeroed wrench); an agent that answered the step is no fault."""
    hold = CommandHold(timeout_ns=50 * NS // 1000)  # 50 ms
    book = WrenchBook(4)
    book.accept(0, 0, (1.0,) * 6)
    book.accept(1, 10 * NS // 1000, (2.0,) * 6)
    book.accept(3, 55 * NS // 1000, (3.0,) * 6)
    u, faults = hold.applied(book, 55 * NS // 1000)
    np.testing.assert_array_equal(u, [[0.0] * 6, [2.0] * 6, [0.0] * 6, [3.0] * 6])
    assert faults == [
        (0, "zero_wrench", "last wrench 0.055 s old"),
        (1, "stale_command", "held the wrench of t=0.0100 s"),
        (2, "zero_wrench", "no wrench yet"),
    ]
    # 40 ms: agent 0's wrench is 40 ms old (held), and a run younger than the timeout needs none yet
    u, faults = hold.applied(book, 40 * NS // 1000)
    assert u[0, 0] == 1.0 and u[2, 0] == 0.0
    assert faults == [
        (0, "stale_command", "held the wrench of t=0.0000 s"),
        (1, "stale_command", "held the wrench of t=0.0100 s"),
        (2, "stale_command", "no wrench yet"),
    ]


def test_lag_budget() -> None:
    """A tick late by more than half a period is a late tick; beyond the budget the run stops."""
    b = LagBudget(budget=1.0, period=0.01)
    assert not b.late(0.004) and b.late(0.006)
    assert not b.exceeded(1.0) and b.exceeded(1.0001)


def _witness(u: np.ndarray, ns: int = 0, tolerance: float | None = None) -> AnswerWitness:
    """A witness expecting ``u`` (N,6) at step ``ns``: bit for bit, or within ``tolerance`` per component."""
    w = AnswerWitness(IDS)
    tol = None if tolerance is None else (tolerance,) * 6
    w.expect(ns, [Expectation(tuple(row), tol) for row in u.tolist()])
    return w


def test_an_answer_not_bit_for_bit_is_not_applied_and_the_step_waits() -> None:
    """Lockstep, an agent judged bit for bit: the witness's own answer is applied; one a unit in the last
    place off is a mismatch with its size (allowed 0), the step stays unanswered, and the agent's later,
    equal answer is applied."""
    rng = np.random.default_rng(25)
    u = rng.uniform(-100.0, 100.0, (3, 6))
    book, witness = WrenchBook(3), _witness(u, ns=PERIOD_NS)
    assert admit(0, PERIOD_NS, tuple(u[0]), None, book, witness) == Admission(APPLY, tuple(u[0]))
    ulp = tuple(np.nextafter(u[1], np.inf))
    a = admit(1, PERIOD_NS, ulp, None, book, witness)
    assert a.action == MISMATCH and a.tolerance == 0.0
    assert a.difference == np.max(np.abs(np.array(ulp) - u[1])) > 0
    assert witness.mismatched == {1: (ulp, 1)}
    w = LockstepWait(IDS, step_timeout=2.0, resend=0.25)
    w.begin(PERIOD_NS, now=0.0)
    book.accept(0, PERIOD_NS, tuple(u[0]))
    assert w.poll(book, now=0.3, mismatched=witness.mismatched) == [1, 2]  # resent to agent 2 (no apply)
    assert admit(1, PERIOD_NS, tuple(u[1]), None, book, witness) == Admission(APPLY, tuple(u[1]))


def test_an_answer_within_its_tolerance_is_applied_and_one_beyond_is_not() -> None:
    """An agent judged by the round-off bound: within the tolerance applies (the largest difference and its
    ratio to the tolerance are reported); beyond it, by any component, is a mismatch naming that tolerance."""
    u = np.ones((3, 6))
    # 1 + 4e-10 rounds within ulp(1)/2 = 1.1e-16 of it, inside pytest.approx's relative 1e-6 of 4e-10
    book, witness = WrenchBook(3), _witness(u, tolerance=1e-9)
    close = tuple(u[0] + 4e-10)
    assert admit(0, 0, close, None, book, witness) == Admission(APPLY, close)
    off = tuple(u[1] + np.array([0, 0, 0, 0, 0, 2e-9]))
    a = admit(1, 0, off, None, book, witness)
    assert (a.action, a.tolerance) == (MISMATCH, 1e-9) and a.difference == pytest.approx(2e-9)
    report = witness.report()
    assert report["1"]["largest_agreed_difference"] == pytest.approx(4e-10)
    assert report["1"]["largest_ratio_to_tolerance"] == pytest.approx(0.4)
    assert report["2"] == {"largest_agreed_difference": 0.0, "largest_ratio_to_tolerance": 0.0}


def test_a_step_answered_keeps_its_answer_and_refused_values_wait_for_the_agent() -> None:
    """Lockstep: a second, equal answer is a duplicate (never replaces the first); a second, other one
    is a mismatch; a refused value does not answer the step with zero (the witness waits for the agent)."""
    u = np.arange(18.0).reshape(3, 6)
    book, witness = WrenchBook(3), _witness(u)
    book.accept(0, 0, tuple(u[0]))
    assert admit(0, 0, tuple(u[0]), None, book, witness) == Admission(DUPLICATE)
    assert admit(0, 0, tuple(u[0] + 1.0), None, book, witness).action == MISMATCH
    assert admit(1, 0, (1e9,) * 6, "over_limit", book, witness) == Admission(IGNORE)
    assert admit(1, 0, tuple(u[1]), "past_step", book, witness) == Admission(IGNORE)
    # realtime (no witness): a refused value answers with zero, a later answer replaces an earlier one
    assert admit(1, 0, (1e9,) * 6, "over_limit", book, None) == Admission(APPLY, (0.0,) * 6)
    assert admit(0, 0, tuple(u[0] + 1.0), None, book, None) == Admission(APPLY, tuple(u[0] + 1.0))


def test_an_answer_with_an_agents_new_gains_agrees_until_it_comes() -> None:
    """During a gain change both answers agree: the old one (the agent has not applied the change yet) and
    the new one, which the admission marks; a third is a mismatch."""
    u = np.zeros((3, 6))
    book, witness = WrenchBook(3), _witness(u, ns=PERIOD_NS)
    new = (1.0, 2.0, 3.0, 0.0, 0.0, 0.0)
    witness.alternative[2] = Expectation(new)
    assert admit(2, PERIOD_NS, new, None, book, witness) == Admission(APPLY, new, new_gains=True)
    assert admit(1, PERIOD_NS, new, None, book, witness).action == MISMATCH
    assert admit(0, PERIOD_NS, (0.0,) * 6, None, book, witness) == Admission(APPLY, (0.0,) * 6)


def test_the_same_refused_answer_again_is_a_repeat() -> None:
    """An agent that answers the re-sent step with the answer refused before is listed as repeating it;
    another answer starts the count again."""
    u = np.zeros((3, 6))
    book, witness = WrenchBook(3), _witness(u)
    wrong = (1.0,) * 6
    admit(1, 0, wrong, None, book, witness)
    assert witness.repeated() == []
    admit(1, 0, wrong, None, book, witness)
    assert witness.repeated() == [1]
    admit(1, 0, (2.0,) * 6, None, book, witness)
    assert witness.repeated() == []


def test_an_agent_that_never_agrees_is_named_as_such() -> None:
    """The last call names a silent agent (exit 3) and, with it, one whose answers all differed; an agent
    whose answers all differed, alone, is a wrong answer (its own error: exit 5)."""
    w, book = wait(), WrenchBook(3)
    w.begin(0, now=0.0)
    book.accept(1, 0, (0.0,) * 6)
    w.poll(book, now=2.0, mismatched={2: ((1.0,) * 6, 1)})
    with pytest.raises(ParticipantMissingError) as err:
        w.poll(book, now=2.0 + LAST_CALL, mismatched={2: ((1.0,) * 6, 1)})
    assert err.value.names == ["1", "3"]
    assert "no answer from agent 1; only answers the witness refused (answer_mismatch) from agent 3" in str(err.value)
    w.begin(PERIOD_NS, now=10.0)
    book.accept(0, PERIOD_NS, (0.0,) * 6)
    book.accept(1, PERIOD_NS, (0.0,) * 6)
    w.poll(book, now=12.0, mismatched={2: ((1.0,) * 6, 1)})
    with pytest.raises(WrongAnswerError) as wrong:
        w.poll(book, now=12.0 + LAST_CALL, mismatched={2: ((1.0,) * 6, 1)})
    assert wrong.value.names == ["3"]
    assert "only answers the witness refused (answer_mismatch) from agent 3 for the step at t=0.000100 s" in str(
        wrong.value
    )


def test_a_non_finite_answer_never_agrees() -> None:
    """A NaN anywhere in an answer is a mismatch of infinite size, whatever the other components."""
    u = np.ones((3, 6))
    for tolerance in (None, 1e-9):
        witness = _witness(u, tolerance=tolerance)
        for k in range(6):
            answer = [1.0] * 6
            answer[k] = float("nan")
            assert witness.judge(0, 0, tuple(answer))[:2] == ("differs", float("inf"))


def test_the_first_step_waits_as_long_as_discovery() -> None:
    """Step 0 may wait first_step_timeout (an agent's reader can match the simulator's writer late); the
    steps after it wait step_timeout."""
    w = LockstepWait(IDS, step_timeout=2.0, resend=0.25, first_step_timeout=40.0)
    book = WrenchBook(3)
    w.begin(0, now=0.0)
    assert w.poll(book, now=30.0) == [0, 1, 2]  # past step_timeout: resent, not named
    assert not w.last_call
    for i in range(3):
        book.accept(i, 0, (0.0,) * 6)
    w.begin(PERIOD_NS, now=31.0)
    w.poll(book, now=33.5)  # step 1: step_timeout again, the last resend
    assert w.last_call
