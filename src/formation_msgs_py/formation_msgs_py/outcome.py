"""The verdict of a run and the exit status of every runner and analysis: one vocabulary.

| verdict      | meaning                                                                  | exit |
|--------------|--------------------------------------------------------------------------|------|
| ``PASS``       | every funnel held over the whole requested duration, with complete data  | 0    |
| ``FAIL``       | a funnel was violated (edge or agent, channel, time)                     | 1    |
| (no verdict) | invalid input (formation file, option): nothing was started              | 2    |
| ``INCOMPLETE`` | a process died or an agent stopped answering                             | 3    |
| ``INCOMPLETE`` | any other reason: I/O error, disk full, lag budget, data missing, internal | 4    |
| ``INCOMPLETE`` | interrupted (SIGINT/SIGTERM)                                             | 130  |

A crash never exits 1: 1 means a funnel was violated and nothing else.
"""

from __future__ import annotations

import enum


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
    INTERRUPTED = 130


EXIT_STATUS_HELP = (
    "exit status: 0 PASS (every funnel held, complete data), 1 FAIL (a funnel was violated), "
    "2 invalid input (nothing started), 3 a process died or an agent stopped answering, "
    "4 incomplete for another reason (I/O error, disk full, lag budget, data missing, internal error), "
    "130 interrupted"
)
