"""The verdict vocabulary (formation_core.verdict.decide): a death the run went on after and a
violation before or after it."""

from __future__ import annotations

import pytest

from formation_core.verdict import ExitCode, Incomplete, Outcome, Verdict, decide

#: a realtime agent died; every agent answered up to t = 3.12 s and the run went on
DIED = Incomplete(ExitCode.PROCESS_DIED, "agent_3 was killed by SIGKILL", whole_until=3.12)


@pytest.mark.parametrize(
    ("violation_t", "expected"),
    [
        (3.89, Outcome(Verdict.INCOMPLETE, ExitCode.PROCESS_DIED, DIED.reason)),  # after the death
        (3.12, Outcome(Verdict.FAIL, ExitCode.FAIL, DIED.reason)),  # at the last step every agent answered
        (2.0, Outcome(Verdict.FAIL, ExitCode.FAIL, DIED.reason)),  # while every agent was alive
        (None, Outcome(Verdict.FAIL, ExitCode.FAIL, DIED.reason)),  # when is unknown: not hidden
    ],
)
def test_a_death_the_run_went_on_after_hides_no_earlier_violation(violation_t, expected: Outcome) -> None:
    """A violation after the death is INCOMPLETE (exit 3); at or before it, or at an unknown time, FAIL."""
    assert decide(True, DIED, violation_t=violation_t) == expected


def test_a_death_the_run_went_on_after_without_a_violation_is_incomplete() -> None:
    """No violation: INCOMPLETE, exit 3, the death as the reason."""
    assert decide(False, DIED) == Outcome(Verdict.INCOMPLETE, ExitCode.PROCESS_DIED, DIED.reason)


def test_a_run_that_stopped_early_keeps_its_violation_as_fail() -> None:
    """A process death that stopped the run (no whole_until): a violation seen is FAIL, whenever it was."""
    stopped = Incomplete(ExitCode.PROCESS_DIED, "agent_3 was killed by SIGKILL")
    assert decide(True, stopped, violation_t=9.0) == Outcome(Verdict.FAIL, ExitCode.FAIL, stopped.reason)
    interrupted = Incomplete(ExitCode.INTERRUPTED, "interrupted (SIGINT)", whole_until=3.12)
    assert decide(True, interrupted, violation_t=1.0).exit_code == ExitCode.INTERRUPTED
    assert decide(True, interrupted, violation_t=4.0) == Outcome(
        Verdict.INCOMPLETE, ExitCode.INTERRUPTED, interrupted.reason
    )
