"""Plausibility of what an agent receives, checked before anything is computed from it (no ROS).

A relative pose (translation xyz [m], quaternion xyzw, frame agent_i) or a body twist is refused
when it cannot be a measurement:

- a value is not finite;
- the quaternion's norm is zero or differs from 1 by more than :data:`QUATERNION_NORM_TOLERANCE`
  (we publish unit quaternions to rounding; a float32-normalised one is off by ~1e-7: anything
  further is not a rotation someone meant, and silently normalising (0, 0, 0, 2) turned it into
  a command of 1e8 N·m);
- the translation is longer than the agent's sensing radius by more than
  :data:`SENSING_SLACK` (relative): the neighbour could not have been sensed there;
- its bytes do not decode as the message type (``malformed``: anyone may publish raw bytes);
- its stamp leads the agent's /clock by more than :data:`MAX_LEAD_NS` (a stamp from the future
  would be taken as the newest step, and every real step after it as a clock jump back), or
  trails it by more than the measurement timeout. The lead allowed is generous because /clock
  and the measurements travel on different topics: on a loaded two-core machine a realtime
  agent heard measurements 0.21 s of sim time before the /clock of their step. Without a /clock
  (clock_ns == 0) stamps are not judged.

:class:`InputCheck` returns the reason of a refusal (or None) and counts refusals per kind.
The node answers a refused value with a zero wrench and ERROR for that step; a refused stamp is
dropped (it names no step the agent should answer).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

#: |‖q‖ − 1| above this refuses a relative pose.
QUATERNION_NORM_TOLERANCE = 1e-6
#: a translation longer than (1 + slack)·sensing_radius refuses a relative pose (room for noise).
SENSING_SLACK = 0.1
#: a stamp more than this ahead of /clock (ns of sim time) is from the future.
MAX_LEAD_NS = 1_000_000_000

NON_FINITE, BAD_QUATERNION, OUT_OF_RANGE, FUTURE_STAMP, OLD_STAMP, MALFORMED = (
    "non_finite",
    "bad_quaternion",
    "out_of_range",
    "future_stamp",
    "old_stamp",
    "malformed",
)
#: kinds that name no step to answer: the message is dropped
DROPPED_KINDS = frozenset({FUTURE_STAMP, OLD_STAMP, MALFORMED})


@dataclass(frozen=True)
class Refusal:
    """Why a message was refused: ``kind`` (one of the constants above) and a readable reason."""

    kind: str
    reason: str


@dataclass
class InputCheck:
    """The checks of one agent: its sensing radius [m] and allowed measurement age [ns]."""

    sensing_radius: float
    max_age_ns: int
    counts: Counter = field(default_factory=Counter)

    def _stamp(self, neighbour: str | None, ns: int, clock_ns: int) -> Refusal | None:
        """The stamp of the velocity (``neighbour`` None) or of a neighbour's pose against /clock."""
        lead_ns = ns - clock_ns
        if clock_ns <= 0 or -self.max_age_ns <= lead_ns <= MAX_LEAD_NS:
            return None
        what = "velocity" if neighbour is None else f"relative pose of {neighbour}"
        lead = lead_ns / 1e9
        if lead_ns > 0:
            return self._count(Refusal(FUTURE_STAMP, f"{what} stamped {ns / 1e9:.9g} s, {lead:.3g} s ahead of /clock"))
        return self._count(Refusal(OLD_STAMP, f"{what} stamped {ns / 1e9:.9g} s, {-lead:.3g} s behind /clock"))

    def _count(self, refusal: Refusal) -> Refusal:
        self.counts[refusal.kind] += 1
        return refusal

    def pose(self, neighbour: str, ns: int, values: Sequence[float], clock_ns: int = 0) -> Refusal | None:
        """Check the 7 doubles of a relative pose of ``neighbour`` (translation, quaternion xyzw)."""
        # every message of every step comes here: the accepted path builds no string
        px, py, pz, qx, qy, qz, qw = values
        # a finite sum means finite values; an infinite one may be an overflow: look at each value
        if not math.isfinite(px + py + pz + qx + qy + qz + qw) and not all(map(math.isfinite, values)):
            return self._count(Refusal(NON_FINITE, f"relative pose of {neighbour}: non-finite value"))
        qn = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if not abs(qn - 1.0) <= QUATERNION_NORM_TOLERANCE:
            reason = f"relative pose of {neighbour}: quaternion norm {qn:.6g} is not 1"
            return self._count(Refusal(BAD_QUATERNION, reason))
        dist = math.sqrt(px * px + py * py + pz * pz)
        if dist > (1.0 + SENSING_SLACK) * self.sensing_radius:
            radius = self.sensing_radius
            reason = f"relative pose of {neighbour}: {dist:.4g} m is beyond the sensing radius {radius:g} m"
            return self._count(Refusal(OUT_OF_RANGE, reason))
        return self._stamp(neighbour, ns, clock_ns)

    def malformed(self, what: str) -> Refusal:
        """Bytes that do not decode as the topic's message type (raw CDR published by anyone)."""
        refusal = Refusal(MALFORMED, f"{what}: bytes that are not a well-formed message")
        self.counts[MALFORMED] += 1
        return refusal

    def velocity(self, ns: int, values: Sequence[float], clock_ns: int = 0) -> Refusal | None:
        """Check the 6 doubles of the agent's own body twist."""
        if not math.isfinite(sum(values)) and not all(map(math.isfinite, values)):
            return self._count(Refusal(NON_FINITE, "velocity: non-finite value"))
        return self._stamp(None, ns, clock_ns)
