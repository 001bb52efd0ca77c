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
- its stamp is too far from the agent's time (``future_stamp``, ``old_stamp``). The agent's time
  is the newest *confirmed* step of its measurement stream (a step answered from its velocity and
  at least one neighbour's pose: two topics, which one forged message cannot give), not /clock:
  any process may publish /clock in plain mode, and a /clock jumped back 1 s by an outsider once
  made every genuine measurement look 1 s ahead. /clock (``clock_ns``) only widens the window: a
  stamp is from the future when it leads both the confirmed step and /clock by more than
  :data:`MAX_LEAD_NS` (a stamp from the future would be taken as the newest step), and old when it
  trails both by more than the measurement timeout. A forged /clock can therefore let a stamp
  through that the stream alone would refuse, never refuse a genuine one; /clock is still needed
  for that widening (after a stall the genuine stream may lead the last confirmed step by more
  than the lead allowed, and the simulator's /clock catches up with it). The lead allowed is
  generous because /clock and the measurements travel on different topics (in realtime /clock is
  published at 10 Hz; on a loaded two-core machine a realtime agent heard measurements 0.21 s of
  sim time before the /clock of their step). With neither a confirmed step nor a /clock stamps are
  not judged. Stamps earlier than the agent's confirmed step are the synchroniser's
  to judge (``past_stamp``, :class:`formation_agent.synchroniser.StepSynchroniser`).

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
#: a stamp more than this ahead of the agent's time and of /clock (ns of sim time) is from the future.
MAX_LEAD_NS = 1_000_000_000

NON_FINITE, BAD_QUATERNION, OUT_OF_RANGE, FUTURE_STAMP, OLD_STAMP, MALFORMED = (
    "non_finite",
    "bad_quaternion",
    "out_of_range",
    "future_stamp",
    "old_stamp",
    "malformed",
)
#: a velocity stamped before the agent's confirmed step that is no resend (the synchroniser refuses it)
PAST_STAMP = "past_stamp"
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

    def _stamp(self, neighbour: str | None, ns: int, clock_ns: int, ref_ns: int | None) -> Refusal | None:
        """The stamp of the velocity (``neighbour`` None) or of a neighbour's pose against the agent's
        confirmed step ``ref_ns`` (None: none yet) and /clock ``clock_ns`` (0: none yet); ns of sim time."""
        if ref_ns is None:
            if clock_ns <= 0:
                return None
            ahead = behind = clock_ns
        elif clock_ns <= 0:
            ahead = behind = ref_ns
        else:  # /clock only widens the window: an outsider's /clock cannot refuse a genuine stamp
            ahead, behind = max(ref_ns, clock_ns), min(ref_ns, clock_ns)
        if ns - ahead > MAX_LEAD_NS:
            kind, lead_ns = FUTURE_STAMP, ns - ahead
        elif behind - ns > self.max_age_ns:
            kind, lead_ns = OLD_STAMP, ns - behind
        else:
            return None
        what = "velocity" if neighbour is None else f"relative pose of {neighbour}"
        lead = lead_ns / 1e9
        if kind == FUTURE_STAMP:
            return self._count(
                Refusal(kind, f"{what} stamped {ns / 1e9:.9g} s, {lead:.3g} s ahead of the agent's time")
            )
        return self._count(Refusal(kind, f"{what} stamped {ns / 1e9:.9g} s, {-lead:.3g} s behind the agent's time"))

    def _count(self, refusal: Refusal) -> Refusal:
        self.counts[refusal.kind] += 1
        return refusal

    def pose(
        self, neighbour: str, ns: int, values: Sequence[float], clock_ns: int = 0, ref_ns: int | None = None
    ) -> Refusal | None:
        """Check the 7 doubles of a relative pose of ``neighbour`` (translation, quaternion xyzw);
        ``clock_ns`` /clock, ``ref_ns`` the agent's confirmed step (None: none yet)."""
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
        return self._stamp(neighbour, ns, clock_ns, ref_ns)

    def malformed(self, what: str) -> Refusal:
        """Bytes that do not decode as the topic's message type (raw CDR published by anyone)."""
        refusal = Refusal(MALFORMED, f"{what}: bytes that are not a well-formed message")
        self.counts[MALFORMED] += 1
        return refusal

    def velocity(
        self, ns: int, values: Sequence[float], clock_ns: int = 0, ref_ns: int | None = None
    ) -> Refusal | None:
        """Check the 6 doubles of the agent's own body twist (``clock_ns``, ``ref_ns`` as :meth:`pose`)."""
        if not math.isfinite(sum(values)) and not all(map(math.isfinite, values)):
            return self._count(Refusal(NON_FINITE, "velocity: non-finite value"))
        return self._stamp(None, ns, clock_ns, ref_ns)
