"""The verdict of a run and the exit status of every runner and analysis: one vocabulary.

| verdict      | meaning                                                                  | exit |
|--------------|--------------------------------------------------------------------------|------|
| ``PASS``       | every funnel held over the whole requested duration, with complete data  | 0    |
| ``FAIL``       | a funnel was violated (edge or agent, channel, time)                     | 1    |
| (no verdict) | invalid input (formation file, option): nothing was started              | 2    |
| ``INCOMPLETE`` | a process died or an agent stopped answering                             | 3    |
| ``INCOMPLETE`` | any other reason: I/O error, disk full, lag budget, data missing, internal, untrusted input | 4    |
| ``INCOMPLETE`` | wrong answer: an agent answered a lockstep step only with wrenches the witness refused | 5    |
| ``INCOMPLETE`` | interrupted (SIGINT/SIGTERM)                                             | 130  |

A crash never exits 1: 1 means a funnel was violated and nothing else. A violation seen before a
run stopped early is still FAIL (exit 1, or 130 when interrupted): the data shows it. A run that
went on after a process died (realtime: the simulator zeroes a dead agent's wrench) is FAIL only
for a violation while every agent was still answering; a violation after the death is no
evidence about the controller: INCOMPLETE, exit 3, the violation kept as information. Missing
data is never a violation. A run with untrusted input (a publisher the formation does not expect
on its topics) is INCOMPLETE whatever its funnels did: its evidence says nothing about the
controller (a violation may be the intruder's doing, a pass its luck).
"""

from __future__ import annotations

import enum
import functools
import os
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


class Verdict(str, enum.Enum):  # noqa: UP042  (StrEnum would change str() of a member: not here)
    """What a run (or the analysis of its bag) concludes."""

    PASS = "PASS"
    FAIL = "FAIL"
    INCOMPLETE = "INCOMPLETE"


class ExitCode(enum.IntEnum):
    """Process exit status of formation-headless, formation-sim, formation-launch, run.sh, formation-analyze, …"""

    PASS = 0
    FAIL = 1
    INVALID = 2
    PROCESS_DIED = 3
    INCOMPLETE = 4
    WRONG_ANSWER = 5
    INTERRUPTED = 130


EXIT_STATUS_HELP = (
    "exit status: 0 PASS (every funnel held, complete data), 1 FAIL (a funnel was violated), "
    "2 invalid input (nothing started), 3 a process died or an agent stopped answering, "
    "4 incomplete for another reason (I/O error, disk full, lag budget, data missing, internal error, "
    "untrusted input), "
    "5 wrong answer (lockstep: an agent answered a step, also when it was re-sent, with a wrench the simulator's "
    "witness refuses), "
    "130 interrupted"
)


@dataclass(frozen=True)
class Incomplete:
    """Why a run has no PASS/FAIL verdict over its whole requested duration."""

    code: ExitCode
    reason: str
    #: the run went on after this cause (an agent died in realtime): its data is whole up to this
    #: simulated time [s] only. None: the run stopped for it (its data is whole up to its end)
    whole_until: float | None = None


@dataclass(frozen=True)
class Outcome:
    """A verdict, its exit status and (INCOMPLETE) the reason."""

    verdict: Verdict
    exit_code: ExitCode
    reason: str | None = None


def decide(
    violated: bool, incomplete: Incomplete | None, untrusted: str | None = None, violation_t: float | None = None
) -> Outcome:
    """The verdict of a run: a violation seen is FAIL even if the run stopped early; missing data
    or an early stop without a violation is INCOMPLETE. An interrupted run exits 130 either way.

    ``untrusted`` (the reason, e.g. :func:`formation_deploy.publisher_watch.untrusted_input`):
    INCOMPLETE, exit 4, whatever the funnels did; an early stop keeps its own exit status (a
    process died: 3, interrupted: 130) and both reasons are given.

    ``violation_t`` [s]: when the first violation was seen. A violation after ``incomplete.whole_until``
    (the run went on without a dead process) is INCOMPLETE with ``incomplete``'s exit status; one at or
    before it, or at an unknown time, is FAIL: a death never hides a violation of the whole formation."""
    if untrusted is not None:
        if incomplete is None:
            return Outcome(Verdict.INCOMPLETE, ExitCode.INCOMPLETE, untrusted)
        return Outcome(Verdict.INCOMPLETE, incomplete.code, f"{incomplete.reason}; {untrusted}")
    if violated and incomplete is not None and _after(violation_t, incomplete.whole_until):
        return Outcome(Verdict.INCOMPLETE, incomplete.code, incomplete.reason)
    if violated:
        interrupted = incomplete is not None and incomplete.code == ExitCode.INTERRUPTED
        code = ExitCode.INTERRUPTED if interrupted else ExitCode.FAIL
        return Outcome(Verdict.FAIL, code, None if incomplete is None else incomplete.reason)
    if incomplete is not None:
        return Outcome(Verdict.INCOMPLETE, incomplete.code, incomplete.reason)
    return Outcome(Verdict.PASS, ExitCode.PASS)


def _after(t: float | None, whole_until: float | None) -> bool:
    """True if a violation at ``t`` is known to follow the time its run's data stopped being whole."""
    return t is not None and whole_until is not None and t > whole_until


class _PipeGuard:
    """Standard output that a closed pipe (``formation-analyze BAG | head -1``) cannot break: the
    first write or flush that meets it sends the rest of the output to /dev/null, and the command
    goes on to its own end and exit status (a verdict, outputs on disk) instead of a traceback."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return int(self._stream.write(text))
        except BrokenPipeError:
            self._to_devnull()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._to_devnull()

    def _to_devnull(self) -> None:
        # the file descriptor itself: also the interpreter's last flush of sys.__stdout__ lands there
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())
        os.close(devnull)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def guarded(prog: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """Decorate a command's ``main``: a crash exits 4 (internal error, traceback on stderr), never 1;
    Ctrl-C outside the command's own handling exits 130; a closed standard output ends nothing (the
    rest of the output is dropped, the exit status is the command's own)."""

    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def guarded_main(*args: Any, **kwargs: Any) -> int:
            stdout = sys.stdout
            if not isinstance(stdout, _PipeGuard) and hasattr(stdout, "fileno"):
                sys.stdout = _PipeGuard(stdout)
            try:
                return int(main(*args, **kwargs))
            except KeyboardInterrupt:
                print(f"{prog}: INCOMPLETE: interrupted", file=sys.stderr, flush=True)
                return ExitCode.INTERRUPTED
            except Exception as exc:  # a crash: exit 4, never 1 (FAIL)
                traceback.print_exc()
                print(f"{prog}: INCOMPLETE: internal error: {exc!r}", file=sys.stderr, flush=True)
                return ExitCode.INCOMPLETE
            finally:
                if isinstance(sys.stdout, _PipeGuard):
                    sys.stdout.flush()
                sys.stdout = stdout

        return guarded_main

    return wrap
