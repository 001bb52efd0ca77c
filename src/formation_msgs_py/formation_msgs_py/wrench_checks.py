"""What the simulator accepts from the agents: the check of a wrench message (no ROS).

A wrench (body frame, [fx, fy, fz, tx, ty, tz] in N and N·m) stamped ``ns`` (integer ns of
sim time) from agent i is refused (the simulator counts it as the fault ``refused_wrench_<kind>``
of that agent, :mod:`formation_core.faults`) and never integrated when:

- a value is not finite (``non_finite``);
- its force or torque norm exceeds the agent's actuator limits, ``dynamics.max_force`` /
  ``max_torque``, by more than rounding (``over_limit``: a healthy controller scales its wrench
  to at most these limits);
- its bytes do not decode as a WrenchStamped (``malformed``);
- its stamp is no step of the run, i.e. not k / control_rate for an integer k (``unknown_step``),
  is later than the newest published step (``future_step``: once, a wrench stamped 2³¹−1 s was
  held for the rest of a run), or, in lockstep, is earlier than the current step (``past_step``:
  that step has been integrated already).

A refused value for a step not yet answered counts as that agent's answer with a zero wrench (a
lockstep run goes on; the fault is in the report); for a step already answered it changes
nothing; a refused stamp is no answer at all.

What the plant may go on with after an accepted wrench is the simulator's own check
(:mod:`formation_sim.core.state_checks`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from formation_msgs_py.codec import step_stamp_ns

NON_FINITE, OVER_LIMIT, UNKNOWN_STEP, FUTURE_STEP, PAST_STEP, MALFORMED = (
    "non_finite",
    "over_limit",
    "unknown_step",
    "future_step",
    "past_step",
    "malformed",
)
#: refusals of the stamp (or of bytes that are no message): the wrench answers no step
DROPPED_KINDS = frozenset({UNKNOWN_STEP, FUTURE_STEP, PAST_STEP, MALFORMED})
#: relative rounding allowed above a limit (a controller scaling to the limit lands within 1e-15)
LIMIT_ROUNDING = 1e-9
_NS = 1_000_000_000


@dataclass(frozen=True)
class WrenchRefusal:
    """Why a wrench was refused: ``kind`` (one of the constants above) and a readable reason."""

    kind: str
    reason: str


@dataclass
class WrenchCheck:
    """The wrench checks of one run: limits per agent in formation order [N, N·m], the step grid."""

    max_force: Sequence[float]
    max_torque: Sequence[float]
    control_rate: float
    lockstep: bool

    def step_of(self, ns: int) -> int | None:
        """The step k whose stamp is ``ns``, or None if ``ns`` is no step's stamp."""
        k = round(ns * self.control_rate / _NS)
        return k if step_stamp_ns(k, self.control_rate) == ns else None

    def check(self, i: int, ns: int, u: Sequence[float], current_ns: int) -> WrenchRefusal | None:
        """Why agent i's wrench ``u`` stamped ``ns`` is refused (None: accepted).

        ``current_ns`` is the stamp of the newest published step (lockstep: the step waited for).
        """
        reason = kind = None
        if self.step_of(ns) is None:
            kind, reason = UNKNOWN_STEP, f"stamp {ns / _NS:.9g} s is no step of the {self.control_rate:g} Hz grid"
        elif ns > current_ns:
            kind, reason = FUTURE_STEP, f"stamp {ns / _NS:.9g} s is after the newest step {current_ns / _NS:.9g} s"
        elif self.lockstep and ns < current_ns:
            kind, reason = PAST_STEP, f"stamp {ns / _NS:.9g} s is before the current step {current_ns / _NS:.9g} s"
        elif not all(math.isfinite(x) for x in u):
            kind, reason = NON_FINITE, "non-finite value"
        else:
            f = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
            t = math.sqrt(u[3] * u[3] + u[4] * u[4] + u[5] * u[5])
            if f > self.max_force[i] * (1 + LIMIT_ROUNDING) or t > self.max_torque[i] * (1 + LIMIT_ROUNDING):
                kind = OVER_LIMIT
                reason = (
                    f"force {f:.4g} N / torque {t:.4g} N·m beyond the limits "
                    f"{self.max_force[i]:g} N / {self.max_torque[i]:g} N·m"
                )
        return None if kind is None else WrenchRefusal(kind, reason or "")

    @staticmethod
    def malformed() -> WrenchRefusal:
        """Bytes on a wrench topic that do not decode as a WrenchStamped (raw CDR from anyone)."""
        return WrenchRefusal(MALFORMED, "bytes that are not a well-formed WrenchStamped")
