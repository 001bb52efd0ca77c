"""What an agent does with the messages it takes, without ROS: :class:`StepSynchroniser`.

A step is the set of measurements with one stamp. The agent computes as soon as it has its velocity
and every neighbour's pose with that stamp; a neighbour out of sensing range sends nothing, so after
``pose_wait`` wall seconds it answers anyway with a zero wrench and ERROR (as the headless runner
does), and a lockstep simulator never waits for it. A repeated stamp (the simulator re-sends a step it
has no answer for) is answered with the same wrench, or, if that answer lacked a neighbour's pose,
computed again from the resend's poses. A refused value (:mod:`formation_msgs_py.measurement_checks`)
answers its step with a zero wrench and ERROR.

Time only from the simulator's measurements. The controller's time is the stamp of the step it
answers (:func:`formation_msgs_py.codec.control_time`). The agent's own time, against which stamps are
judged, is its newest *confirmed* step: one answered from its velocity and at least one neighbour's
pose (two topics agree; one forged message cannot confirm a step). /clock, which any process may
publish in plain mode, moves nothing: it only widens the window of acceptable stamps
(measurement_checks), stamps /diagnostics and reports staleness there. So:

- a velocity stamped before the confirmed step that is no resend of a step still remembered is
  refused and counted (``refused_past_stamp``), without an answer and without a reset;
- a step ahead of the next genuine one (a forged velocity) is answered alone (zero and ERROR after
  ``pose_wait``, its poses never come) and confirms nothing: the genuine steps before its stamp are
  still answered, in their order;
- /clock jumping back (an outsider, or a bag replayed in a loop) is counted (``clock_jump``) and
  resets nothing by itself. Simulation time restarts (``reset``: controller and watchdogs) only when
  /clock has jumped back *and* a step earlier than the confirmed one arrives with its velocity and a
  neighbour's pose, close to that /clock: three topics agreeing, as a replay that loops gives.

Also here, for the node and for tools that read an agent's parameters without ROS: the live gains
(:data:`LIVE_GAINS`, :func:`live_gains`) and the names of the parameters an agent reports.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from formation_agent.controller import ERROR, OK, AgentController, ControlOutput
from formation_core.faults import FaultLog
from formation_core.schema import AGENT_FIELDS, parse_mapping
from formation_msgs_py.codec import NS_PER_S, control_time
from formation_msgs_py.measurement_checks import MAX_LEAD_NS, PAST_STAMP

#: Bounded memory of stamps with poses (and of refusals); more only happens when the agent lags.
_POSE_MEMORY = 8

PoseTuple = tuple[list[float], list[list[float]]]
#: fault kinds of the synchroniser (formation_core.faults)
REFUSED_PAST_STAMP = f"refused_{PAST_STAMP}"
CLOCK_JUMP = "clock_jump"


@dataclass
class Window:
    """What /diagnostics reports: the worst of every step since the last report."""

    margin_e: list[float]
    margin_psi: list[float]
    margin_v: list[float]
    level: int = OK
    message: str = ""
    steps: int = 0
    faults: int = 0

    @classmethod
    def empty(cls, n_edges: int) -> Window:
        inf = math.inf
        return cls([inf] * n_edges, [inf] * n_edges, [inf] * 6)

    def add(self, out: ControlOutput) -> None:
        self.steps += 1
        pairs = ((self.margin_e, out.margin_e), (self.margin_psi, out.margin_psi), (self.margin_v, out.margin_v))
        for dst, src in pairs:
            for k, m in enumerate(src):
                if m < dst[k]:
                    dst[k] = m
        if out.level == ERROR:
            self.faults += 1
        if out.level >= self.level:
            self.level = out.level
            self.message = out.message


@dataclass
class StepSynchroniser:
    """Matches an agent's velocity with its neighbours' poses by stamp and runs the controller.

    ``publish(stamp_ns, wrench)`` is called once per answered stamp (and again for a re-sent
    stamp). Times: stamps in integer ns of sim time; ``now`` in wall seconds (monotonic). What
    comes in has passed the node's input check (:mod:`formation_msgs_py.measurement_checks`); a refused
    measurement comes through :meth:`refuse` and its step is answered with zero and ERROR.
    """

    controller: AgentController
    publish: Callable[[int, Sequence[float]], None]
    pose_wait: float = 0.005
    #: poses by stamp, then neighbour (refused ones as (None, None)); bounded, see _POSE_MEMORY
    steps: dict[int, dict[str, PoseTuple]] = field(default_factory=dict)
    pending: tuple[int, Sequence[float], float] | None = None
    #: whether the pending step is earlier than the confirmed one after /clock jumped back (a restart?)
    pending_restart: bool = False
    #: the newest answered step [ns]
    last_ns: int | None = None
    #: the agent's time: the newest step answered from its velocity and at least one pose [ns]
    confirmed_ns: int | None = None
    #: /clock after its last backward jump [ns], until a step confirms or restarts the time
    rewind_ns: int | None = None
    #: the last answers by stamp: wrench and whether every neighbour's pose was in (else a resend
    #: of that step is answered anew); bounded, see _POSE_MEMORY
    answers: dict[int, tuple[tuple[float, ...], bool]] = field(default_factory=dict)
    last_wrench: tuple[float, ...] = (0.0,) * 6
    last_output: ControlOutput | None = None
    window: Window = None  # type: ignore[assignment]
    #: every fault of this agent by kind (formation_core.faults): resets, refusals, zero answers
    faults: FaultLog = field(default_factory=FaultLog)
    last_measurement_wall: float | None = None
    #: reasons of refused measurements (formation_msgs_py.measurement_checks) by stamp: that step answers zero
    refused: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.neighbours = tuple(e.neighbour for e in self.controller.view.edges)
        self.window = Window.empty(len(self.neighbours))

    def reset(self, t: float, why: str) -> None:
        """Forget everything that depends on time (simulation time restarted at t [s]): a ``reset`` fault."""
        self.controller.reset()
        self.steps = {}
        self.pending = None
        self.pending_restart = False
        self.last_ns = None
        self.confirmed_ns = None
        self.rewind_ns = None
        self.answers = {}
        self.refused = {}
        self.fault(t, "reset", why)

    def clock_jumped_back(self, clock_ns: int, delta_ns: int) -> None:
        """/clock went back by ``-delta_ns`` to ``clock_ns``: counted (``clock_jump``); nothing is reset
        until a step of that earlier time arrives with its velocity and a pose (:meth:`on_velocity`)."""
        self.rewind_ns = clock_ns
        self.fault(clock_ns / NS_PER_S, CLOCK_JUMP, f"/clock jumped by {delta_ns / NS_PER_S:.6f} s")

    def fault(self, t: float, kind: str, detail: str) -> None:
        self.faults.add(t, self.controller.view.agent_id, kind, detail)

    @property
    def resets(self) -> int:
        c = self.faults.counts.get((self.controller.view.agent_id, "reset"))
        return 0 if c is None else c.count

    def set_gains(self, **gains: float) -> None:
        """Controller gains (``agents[].controller`` names) from the next step on; ρ_v0 and t0 are kept."""
        old = self.controller
        if not gains:
            return
        changes: dict[str, Any] = dict(gains)  # floats only: the checker cannot tell them from velocity_funnel
        new = AgentController(replace(old.view, controller=replace(old.view.controller, **changes)))
        new.rho_v0, new.t0 = old.rho_v0, old.t0
        self.controller = new

    def on_pose(self, j: str, ns: int, p: list[float], R: list[list[float]], now: float) -> None:
        steps = self.steps
        poses = steps.get(ns)
        if poses is None:
            poses = steps[ns] = {}
            if len(steps) > _POSE_MEMORY:  # more only happens when the agent lags
                del steps[next(iter(steps))]
        poses[j] = (p, R)
        self.last_measurement_wall = now
        pending = self.pending
        if pending is not None and pending[0] == ns and len(poses) == len(self.neighbours):
            self.try_compute(now, final=False)

    def on_velocity(self, ns: int, v: Sequence[float], now: float) -> None:
        self.last_measurement_wall = now
        restart = False
        answered = self.answers.get(ns)
        if answered is not None:
            if answered[1]:  # the simulator re-sent a step: same answer
                self.publish(ns, answered[0])
                return
            # a step re-sent after an answer without a neighbour's pose (lost, or later than
            # pose_wait) is answered again from the resend's poses below, as if it were new: the
            # controller's only state, the velocity funnel's start, is set once, so the answer is
            # the one the headless run gives
        elif self.confirmed_ns is not None and ns <= self.confirmed_ns:
            rewind = self.rewind_ns
            if rewind is None or ns - rewind > MAX_LEAD_NS:
                # an outsider's, or a step long forgotten: the agent's time does not go back for one message
                before = self.confirmed_ns / NS_PER_S
                detail = f"velocity stamped {ns / NS_PER_S:.9g} s, before the agent's time {before:.9g} s"
                self.fault(ns / NS_PER_S, REFUSED_PAST_STAMP, detail)
                return
            restart = True  # /clock went back too: a restart if a neighbour's pose confirms the step
        self.pending = (ns, v, now + self.pose_wait)
        self.pending_restart = restart
        self.try_compute(now, final=False)

    def refuse(self, ns: int, reason: str, now: float, neighbour: str | None = None) -> None:
        """A measurement of step ``ns`` was refused (the velocity if ``neighbour`` is None): the step
        is answered with a zero wrench and ERROR naming ``reason``."""
        if self.confirmed_ns is not None and ns < self.confirmed_ns and ns not in self.answers:
            return  # a step behind the agent's time: nothing to answer, and no reset
        self.refused[ns] = reason
        if len(self.refused) > _POSE_MEMORY:
            del self.refused[next(iter(self.refused))]
        if neighbour is None:
            self.on_velocity(ns, (), now)
        else:
            self.on_pose(neighbour, ns, None, None, now)  # type: ignore[arg-type]

    def deadline(self) -> float | None:
        return None if self.pending is None else self.pending[2]

    def try_compute(self, now: float, *, final: bool) -> None:
        """Answer the pending step if complete, or (``final``) with what has arrived."""
        if self.pending is None:
            return
        ns, v, _ = self.pending
        steps = self.steps
        poses = steps.get(ns, {})
        complete = len(poses) == len(self.neighbours)
        if not (complete or final):
            return
        self.pending = None
        t = control_time(ns)
        refused = self.refused.pop(ns, None) if self.refused else None
        # two topics agree on this step: the velocity (not refused) and at least one pose
        confirms = refused is None and any(p is not None for p, _ in poses.values())
        if self.pending_restart:
            self.pending_restart = False
            if not confirms:
                detail = f"velocity stamped {t:.9g} s, before the agent's time and without a pose"
                self.fault(t, REFUSED_PAST_STAMP, detail)
                return
            assert self.confirmed_ns is not None and self.rewind_ns is not None
            before = self.confirmed_ns / NS_PER_S
            why = f"/clock back to {self.rewind_ns / NS_PER_S:.6f} s, measurements at {t:.6f} s after {before:.6f} s"
            self.reset(t, why)
            steps = self.steps = {ns: poses}
        ctrl = self.controller
        if refused is not None:
            out = ctrl.fault_output(t, f"refused at t={t:.6f}: {refused}")
        elif not complete:
            missing = ", ".join(j for j in self.neighbours if j not in poses)
            self.fault(t, "missing_pose", missing)
            out = ctrl.fault_output(t, f"no relative pose of neighbour(s) {missing} at t={t:.6f}")
        else:
            out = ctrl.compute(t, poses, v)
        if self.last_ns is None or ns > self.last_ns:
            self.last_ns = ns
        answers = self.answers
        answers[ns] = (out.wrench, complete)
        if len(answers) > _POSE_MEMORY:
            del answers[next(iter(answers))]
        self.last_wrench = out.wrench
        self.last_output = out
        self.window.add(out)
        self.publish(ns, out.wrench)
        steps.pop(ns, None)
        if confirms and (self.confirmed_ns is None or ns > self.confirmed_ns):
            self.confirmed_ns = ns
            self.rewind_ns = None  # the simulator's time went on: a later restart needs a new jump
            if steps:  # the poses of earlier steps are obsolete (not after an unconfirmed step: a
                # forged velocity ahead of the genuine steps must not throw their poses away)
                for old in [s for s in steps if s < ns]:
                    del steps[old]


#: read-only parameters an agent reports: its code form and numeric platform (formation_core.numba_kernels)
CODE_FORM_PARAMETER, PLATFORM_PARAMETER = "code_form", "numeric_platform"

#: Gains that a running agent applies from its next step: {parameter name: description}.
LIVE_GAINS = {
    "delta": "gain δ_i of the desired velocity (> 0); live: applies from the next step",
    "gamma": "gain γ_i of the wrench (> 0); live: applies from the next step",
}


def live_gains(agent_id: str, values: Mapping[str, Any]) -> dict[str, float]:
    """``values`` checked as the formation file's ``agents[].controller`` section is checked.

    Raises FormationSpecError naming the field and the value (e.g. ``gamma: -1.0 must be > 0``).
    """
    controller = next(f for f in AGENT_FIELDS if f.name == "controller")
    fields = tuple(f for f in controller.children if f.name in LIVE_GAINS and f.name in values)
    return parse_mapping(dict(values), fields, f"agents[{agent_id}].controller")
