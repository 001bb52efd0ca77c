"""The simulator's stepping policy without ROS: who answers a lockstep step, resend, timeout, hold, lag."""

from __future__ import annotations

import numpy as np
import pytest

from formation_sim.node.stepping import (
    LAST_CALL,
    NS,
    CommandHold,
    LagBudget,
    LockstepWait,
    ParticipantMissingError,
    WrenchBook,
)

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
