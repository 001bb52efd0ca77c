"""The simulator's check of a wrench message (offline): every class of bad wrench is refused with its kind and a reason
naming the value (the simulator counts refusals as faults: tests/ros/test_bad_messages.py)."""

from __future__ import annotations

import math

import pytest

from formation_msgs_py import wrench_checks

NS = 1_000_000_000
RATE = 1000.0  # Hz: steps every 1 ms
GOOD = (1.0, 2.0, 3.0, 0.1, 0.2, 0.3)


def check(lockstep: bool = True) -> wrench_checks.WrenchCheck:
    return wrench_checks.WrenchCheck((100.0, 100.0), (50.0, 50.0), RATE, lockstep=lockstep)


@pytest.mark.parametrize(
    ("u", "kind"),
    [
        ((math.nan, 0, 0, 0, 0, 0), wrench_checks.NON_FINITE),
        ((0, 0, 0, 0, math.inf, 0), wrench_checks.NON_FINITE),
        ((1e308, 0, 0, 0, 0, 0), wrench_checks.OVER_LIMIT),
        ((1e8, 0, 0, 0, 0, 0), wrench_checks.OVER_LIMIT),
        ((60.0, 60.0, 60.0, 0, 0, 0), wrench_checks.OVER_LIMIT),  # 104 N > 100 N
        ((0, 0, 0, 0, 0, 50.001), wrench_checks.OVER_LIMIT),
    ],
)
def test_bad_wrench_value_is_refused(u, kind) -> None:
    """Non-finite or beyond the actuator limits: refused with that kind."""
    c = check()
    refusal = c.check(1, 5 * NS // 1000, u, current_ns=5 * NS // 1000)
    assert refusal is not None and refusal.kind == kind


def test_wrench_at_the_limit_is_accepted() -> None:
    """A controller scaling to exactly its limit (rounding 1e-15) passes; so does a plain wrench."""
    c = check()
    at_limit = (100.0 * (1 + 1e-15), 0, 0, 0, 0, 50.0)
    assert c.check(0, 0, at_limit, current_ns=0) is None
    assert c.check(0, 0, GOOD, current_ns=0) is None


@pytest.mark.parametrize(
    ("ns", "current_ns", "lockstep", "kind"),
    [
        ((2**31 - 1) * NS, 5 * NS, False, wrench_checks.FUTURE_STEP),  # once held for the rest of a realtime run
        ((2**31 - 1) * NS, 5 * NS, True, wrench_checks.FUTURE_STEP),  # once stalled a lockstep run
        (5 * NS + 1_000_000, 5 * NS, True, wrench_checks.FUTURE_STEP),
        (5 * NS - 1_000_000, 5 * NS, True, wrench_checks.PAST_STEP),
        (5 * NS + 1, 6 * NS, False, wrench_checks.UNKNOWN_STEP),
    ],
)
def test_wrench_for_a_step_that_does_not_exist_is_refused(ns, current_ns, lockstep, kind) -> None:
    c = check(lockstep)
    refusal = c.check(0, ns, GOOD, current_ns)
    assert refusal is not None and refusal.kind == kind
    assert kind in wrench_checks.DROPPED_KINDS


def test_realtime_accepts_a_late_answer_lockstep_does_not() -> None:
    """Realtime holds the newest wrench, so an answer to an earlier step is valid; lockstep refuses it."""
    assert check(lockstep=False).check(0, 4 * NS, GOOD, current_ns=5 * NS) is None
    assert check(lockstep=True).check(0, 4 * NS, GOOD, current_ns=5 * NS) == wrench_checks.WrenchRefusal(
        wrench_checks.PAST_STEP, "stamp 4 s is before the current step 5 s"
    )


def test_refusal_reasons_name_the_value() -> None:
    """The reason is what the simulator logs and counts (first and last) for the agent."""
    c = check()
    assert c.check(0, 0, (math.nan,) * 6, current_ns=0) == wrench_checks.WrenchRefusal(
        wrench_checks.NON_FINITE, "non-finite value"
    )
    over = c.check(1, 0, (1e9, 0, 0, 0, 0, 0), current_ns=0)
    assert (
        over is not None
        and over.kind == wrench_checks.OVER_LIMIT
        and "1e+09 N" in over.reason
        and "100 N" in over.reason
    )
    unknown = c.check(0, 5 * NS + 1, GOOD, current_ns=6 * NS)
    assert unknown is not None and "no step of the 1000 Hz grid" in unknown.reason


def test_bytes_that_are_no_wrench_are_refused() -> None:
    """Raw bytes on a wrench topic that do not decode: counted as malformed for that agent."""
    import struct

    from formation_msgs_py import codec

    c = check()
    with pytest.raises(struct.error):
        codec.wrench_codec("b").decode(b"\x00\x01\x00\x00garbage")
    assert c.malformed().kind == wrench_checks.MALFORMED and wrench_checks.MALFORMED in wrench_checks.DROPPED_KINDS
