"""The simulator's two stepping loops (:class:`Runner`): lockstep (each step waits for every agent's
answer, judged by the witness) and realtime (ticks on the wall clock with the latest wrenches held),
around :class:`formation_sim.core.simulation.Simulation` and the node of
:mod:`formation_sim.node.simulator_node`; what they mean: :mod:`formation_sim.node.sim_node`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import rclpy

from formation_agent.kernel_cache import warm_up
from formation_agent.synchroniser import CODE_FORM_PARAMETER, LIVE_GAINS, PLATFORM_PARAMETER
from formation_core.faults import ANSWER_MISMATCH
from formation_core.formation import FormationSpec, agent_view, simulator_view
from formation_core.options import RunOptions
from formation_core.verdict import ExitCode, Incomplete
from formation_msgs_py.codec import step_stamp_ns
from formation_sim.core import state_checks
from formation_sim.core.links import link_summary
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements, Simulation
from formation_sim.core.summary import RunnerKeys, RunSummary
from formation_sim.node.simulator_node import SimNode, number_value, parameter_values, text_value
from formation_sim.node.stepping import (
    NS,
    ZERO_WRENCH,
    CommandHold,
    LagBudget,
    LockstepWait,
    ParticipantMissingError,
    WrongAnswerError,
)
from formation_sim.node.witness import AgentReport

#: wall seconds after which an agent's unanswered parameter request is sent again
PARAMETER_ASK_AGAIN_S = 2.0
#: default /clock rate in realtime [Hz]: the agents' measurement-age checks need no more
REALTIME_CLOCK_RATE = 10.0


class StopRequestedError(Exception):
    """The node was asked to stop (SIGINT/SIGTERM: context shut down)."""


class RunStoppedError(Exception):
    """The run cannot go on (plant blew up, lag budget exceeded): INCOMPLETE with this reason."""

    def __init__(self, incomplete: Incomplete) -> None:
        super().__init__(incomplete.reason)
        self.incomplete = incomplete


class Runner:
    """The stepping loops of one run (lockstep or realtime)."""

    def __init__(self, node: SimNode, executor: Any, spec: FormationSpec, args: RunOptions) -> None:
        self.node = node
        self.executor = executor
        self.spec = spec
        self.args = args
        s = spec.simulation
        self.sim = Simulation(simulator_view(spec))
        self.shadow = node.shadow
        warm_up(agent_view(spec, spec.agent_ids[0]))  # the agents' kernel in numba's cache for the next run
        self.n_steps = round(s.duration * s.control_rate)
        self.period = 1.0 / s.control_rate
        record_every = max(1, round(s.control_rate / s.record_rate))
        # add(..., u=None) checks step k while the agents compute; set_inputs(u) when they answered
        self.recorder = RunRecorder(
            spec, record_every=record_every, mode=f"ros2-{args.mode}", control_rate=s.control_rate
        )
        node.faults = self.recorder.faults  # one count of every fault: the summary's
        gt_rate = args.ground_truth_rate or min(s.record_rate, s.control_rate)
        clock_rate = args.clock_rate or min(s.record_rate, s.control_rate)
        if args.mode == "realtime" and not args.clock_rate:
            # every agent takes each /clock (rclpy's time source, a message object): in realtime it
            # only dates their measurement-age check, for which REALTIME_CLOCK_RATE is plenty
            clock_rate = min(clock_rate, REALTIME_CLOCK_RATE)
        self.gt_every = max(1, round(s.control_rate / gt_rate))
        self.clock_every = max(1, round(s.control_rate / clock_rate))
        self.started = time.monotonic()
        self.last_progress = self.started
        self.step = 0

    def ok(self) -> bool:
        return rclpy.ok(context=self.node.context)

    def spin(self, timeout: float) -> None:
        """Run one callback (or wait ``timeout`` s), unless SIGINT/SIGTERM shut the context down:
        a callback run on a shut-down context fails."""
        if not self.ok():
            raise StopRequestedError
        self.executor.spin_once(timeout_sec=max(timeout, 0.0))

    def drain(self) -> None:
        """Run every callback that is ready now (the realtime loop may have no time left to wait):
        until a spin runs none, counting /diagnostics and the graph poll too (stopping at the first
        of those left a wrench that had come in time behind at one realtime tick in five)."""
        node = self.node
        for _ in range(6 * len(node.ids) + 4):
            before = node.taken()
            self.spin(0.0)
            if node.taken() == before:
                break

    def stamp_ns(self, k: int) -> int:
        return step_stamp_ns(k, self.spec.simulation.control_rate)

    def wait_for_agents(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        last_note = time.monotonic()
        while True:
            missing = self.node.unmatched_agents()
            if not missing:
                break
            now = time.monotonic()
            if now > deadline:
                raise ParticipantMissingError(
                    missing,
                    f"discovery: agent(s) {', '.join(missing)} not matched within {timeout:g} s "
                    "(not started, crashed, or another ROS_DOMAIN_ID / discovery range)",
                )
            if now - last_note > 5.0:
                print(f"formation-sim: waiting for agent(s) {', '.join(missing)}", flush=True)
                last_note = now
            self.spin(0.05)
        while self.args.wait_recorder and not self.node.recorder_matched():
            if time.monotonic() > deadline:
                raise ParticipantMissingError(["recorder"], f"discovery: no bag recorder matched within {timeout:g} s")
            self.spin(0.05)
        self.read_agents(deadline)
        settle = time.monotonic() + self.args.settle
        while time.monotonic() < settle:  # let the agents' side of discovery finish too
            self.spin(settle - time.monotonic())

    def read_agents(self, deadline: float) -> None:
        """Every agent's report of itself (code form, numeric platform, δ, γ: its parameters) into the
        shadow, before the first step; raises ParticipantMissingError naming the agents whose parameter
        services did not answer by ``deadline`` (monotonic s)."""
        node, names = self.node, [CODE_FORM_PARAMETER, PLATFORM_PARAMETER, *LIVE_GAINS]
        asked: dict[int, Any] = {}
        asked_at: dict[int, float] = {}
        while len(asked) < len(node.ids) or not all(f.done() for f in asked.values()):
            now = time.monotonic()
            for i, client in enumerate(node.parameter_clients):
                # a service is "ready" once its request topic matched; its response may still be lost
                # while the reply's own writer and reader match: a request unanswered is asked again
                stale = i in asked and not asked[i].done() and now - asked_at[i] > PARAMETER_ASK_AGAIN_S
                if (i not in asked or stale) and client.services_are_ready():
                    asked[i], asked_at[i] = client.get_parameters(names), now
            if time.monotonic() > deadline:
                missing = [a for i, a in enumerate(node.ids) if i not in asked or not asked[i].done()]
                raise ParticipantMissingError(
                    missing, f"discovery: the parameter services of agent(s) {', '.join(missing)} did not answer"
                )
            self.spin(0.05)
        for i, future in asked.items():
            values = parameter_values(future, names)
            report = AgentReport(
                code_form=text_value(values.get(CODE_FORM_PARAMETER)),
                platform=text_value(values.get(PLATFORM_PARAMETER)),
                delta=number_value(values.get("delta")),
                gamma=number_value(values.get("gamma")),
            )
            self.shadow.agent_reported(i, report)

    def progress(self, t: float, force: bool = False) -> None:
        now = time.monotonic()
        if self.args.quiet or (not force and now - self.last_progress < self.args.progress_period):
            return
        self.last_progress = now
        wall = now - self.started
        rtf = t / wall if wall > 0 else 0.0
        # wall seconds still to go at the real-time factor so far (none before the first step)
        eta = f" eta={(self.spec.simulation.duration - t) / rtf:.0f}" if rtf > 0 else ""
        print(
            f"progress t={t:.4f}/{self.spec.simulation.duration:g} rtf={rtf:.3f} "
            f"worst_margin={self.recorder.worst_margin():+.4f}{eta}",
            flush=True,
        )

    def _publish_aux(self, k: int, t: float, ns: int) -> None:
        if k % self.clock_every == 0:
            self.node.publish_clock(ns)
        if k % self.gt_every == 0:
            self.node.publish_ground_truth(ns, self.sim)
        if self.node.display is not None:  # markers at the display rate, with the latest wrenches
            display = self.node.display
            if display.due(t) and self.sim.links is not None:
                display.publish_link_ages(t, self.sim.link_ages())
            display.publish(t, self.sim.state.p, self.sim.state.R, np.array(self.node.wrenches.value))

    def advance(self, u: np.ndarray) -> None:
        """Integrate one control period (raises RunStoppedError, agents named, if the state blew up,
        or if the run's bag could not be written)."""
        if self.node.bag is not None and self.node.bag.failed:
            raise RunStoppedError(Incomplete(ExitCode.INCOMPLETE, self.node.bag.failed))
        reason = state_checks.advance_checked(self.sim, u)
        if reason:
            raise RunStoppedError(Incomplete(ExitCode.INCOMPLETE, reason))

    # lockstep --------------------------------------------------------------------------------
    def run_lockstep(self) -> None:
        node, sim, rec, timing = self.node, self.sim, self.recorder, self.node.timing
        mono = time.monotonic
        wait = LockstepWait(
            node.ids,
            step_timeout=self.spec.simulation.step_timeout,
            resend=self.args.resend,
            first_step_timeout=self.args.discovery_timeout or 30.0 + len(self.spec.agents),
        )
        self.started = mono()
        for k in range(self.n_steps + 1):
            self.step = k
            final = k == self.n_steps
            meas = sim.sense()
            ns = meas.ns
            node.current_ns = ns
            sent = mono()
            node.pub_wall = {ns: sent}
            wait.begin(ns, sent)
            node.publish_step(meas)
            # while the agents compute: /clock, ground truth, display, the witness (the shadow
            # controllers on what the agents decode) and the funnel check of step k (an agent's stamp
            # checks allow /clock to come a little later)
            self._publish_aux(k, meas.t, ns)
            margin_v, _ = self.shadow.step(node.messages.decoded(meas), rec)
            s = sim.state
            rec.add(meas.t, s.p, s.R, s.v, None)
            witness = self.shadow.answers
            while True:
                if wait.done(node.wrenches):
                    break
                now = mono()
                # answers waiting in our own queue count: held up, we may not have run their callbacks yet
                late = wait.poll(node.wrenches, now, witness.mismatched, self.drain)
                wrong = [i for i in witness.repeated() if i not in node.reading]
                if wrong:
                    raise WrongAnswerError([node.ids[i] for i in wrong], self._wrong_answers(wrong, ns))
                if late:
                    node.publish_step(meas, only=late)
                    timing.resends += 1
                    for i in late:
                        rec.fault(meas.t, "resent_step", node.ids[i])
                self.spin(wait.wake_at() - now)
            for i in range(len(node.ids)):
                timing.answered[i] += 1
            timing.expected += 1
            errors = self.shadow.answered(margin_v, meas.t)
            self.shadow.team.note_errors(meas.t, errors, rec)
            u = np.array(node.wrenches.value)
            rec.set_inputs(u, margin_v)
            if final:
                if sim.links is not None:  # the last answers go onto the links too (the run core's count)
                    sim.deliver(u)
                    rec.add_link_ages(sim.link_ages()[None], k)
                break
            self.advance(u)
            if sim.links is not None:
                rec.add_link_ages(sim.closed_step_link_ages[None], k)
            if k & 63 == 0:
                self.progress(sim.t)

    def _wrong_answers(self, agents: list[int], ns: int) -> str:
        """Why agents that answered step ``ns`` re-sent with the same refused wrench are named."""
        node = self.node
        parts = []
        for i in agents:
            answer = node.shadow.answers.mismatched[i][0]
            off = node.shadow.answers.expected[i].difference(answer) or (math.inf, 0.0)
            allowed = "bit for bit" if off[1] == 0 else f"within {off[1]:.3g} (round-off bound)"
            parts.append(f"agent {node.ids[i]} (max |u - witness| {off[0]:.3g}, allowed {allowed})")
        return (
            f"lockstep: wrong answer: {', '.join(parts)} answered the step at t={ns / NS:.6f} s, re-sent, "
            f"again with the wrench the witness refused ({ANSWER_MISMATCH}); its answers were not applied"
        )

    # realtime --------------------------------------------------------------------------------
    def run_realtime(self) -> None:
        node, sim, rec, timing = self.node, self.sim, self.recorder, self.node.timing
        hold = CommandHold(round(self.spec.simulation.command_timeout * NS))
        budget = LagBudget(self.args.lag_budget, self.period)
        mono = time.monotonic
        u = np.zeros((len(node.ids), 6))
        self.started = t0 = mono()
        prev: tuple[Measurements, Any, np.ndarray, list] | None = None
        for k in range(self.n_steps + 1):
            self.step = k
            target = t0 + k * self.period
            while (now := mono()) < target:
                self.spin(target - now)
            self.drain()
            lag = mono() - target
            timing.lags.append(lag)
            done, prev = prev, None  # step k-1: its wrenches apply now; its bookkeeping waits until step k is out
            late_tick = budget.late(lag)
            if done is not None:
                u, faults = hold.applied(node.wrenches, self.stamp_ns(k - 1))
                try:
                    self.advance(u)
                except RunStoppedError:
                    self._close_step(done, u, faults, late_tick)
                    raise
                if sim.links is not None:
                    rec.add_link_ages(sim.closed_step_link_ages[None], k - 1)
            if late_tick:
                rec.fault(sim.t, "late_tick", "simulator", f"{lag * 1e3:.1f} ms late")
            if budget.exceeded(lag):
                if done is not None:
                    self._close_step(done, u, faults, late_tick)
                raise RunStoppedError(
                    Incomplete(
                        ExitCode.INCOMPLETE,
                        f"realtime lag budget exceeded: {lag:.3f} s behind the wall clock at t={sim.t:.4f} s "
                        f"(--lag-budget {budget.budget:g} s)",
                    )
                )
            meas = sim.sense()
            ns = self.stamp_ns(k)
            node.current_ns = ns
            node.pub_wall[ns] = mono()
            if len(node.pub_wall) > 64:
                del node.pub_wall[next(iter(node.pub_wall))]
            node.publish_step(meas)  # first: the agents' time to answer runs from here
            if done is not None:
                self._close_step(done, u, faults, late_tick)
            self._publish_aux(k, meas.t, ns)
            margin_v, errors = self.shadow.step(node.messages.decoded(meas), rec)
            prev = (meas, sim.state, margin_v, errors)
            self.progress(meas.t)
        if prev is not None:  # the last sample, with the wrenches held at the end
            pmeas, pstate, pmargin, _ = prev
            rec.add(pmeas.t, pstate.p, pstate.R, pstate.v, None, pmargin)
            rec.set_inputs(u)
            if sim.links is not None:
                sim.deliver(u)
                rec.add_link_ages(sim.link_ages()[None], pmeas.step)

    def _close_step(
        self, step: tuple[Measurements, Any, np.ndarray, list], u: np.ndarray, faults: list, late_tick: bool
    ) -> None:
        """Realtime: count and record step k-1 (measurements, state, margins, shadow outputs) once
        its wrenches ``u`` were applied; ``faults`` (agent index, kind, detail) lists who had not answered.
        ``step`` is (measurements, state, margin_v, errors) of its shadow evaluation.

        An agent's step is *answered* if its wrench was in when the next tick applied it, and *on
        time* if, besides, that tick came within half a period of its wall-clock time: a simulator
        running late gives the agents more time, and a step closed late is not a real-time step.
        """
        node, rec, timing = self.node, self.recorder, self.node.timing
        meas, state, margin_v, errors = step
        late = {i for i, _, _ in faults}
        for i in range(len(node.ids)):
            answered = i not in late
            timing.answered[i] += answered
            timing.on_time[i] += answered and not late_tick
        for i, kind, why in faults:
            first = rec.fault(meas.t, kind, node.ids[i], why)
            if first and kind == ZERO_WRENCH:
                print(f"formation-sim: agent {node.ids[i]}: t={meas.t:.4f}: {why}: zero wrench", flush=True)
        timing.expected += 1
        rec.add(meas.t, state.p, state.R, state.v, None, margin_v)
        rec.set_inputs(u)
        self.shadow.team.note_errors(meas.t, errors, rec)

    def summary(self, wall: float, incomplete: Incomplete | None, extra: RunnerKeys) -> RunSummary:
        """summary.json: the recorder's, with the simulator's rates, timing, security and witness, and ``extra``."""
        s = self.spec.simulation
        timing = self.node.timing.summary(self.spec.agent_ids, self.period)
        stamps = self.node.wrenches.stamp
        info: RunnerKeys = {
            "physics_rate": s.physics_rate,
            "steps": self.step,
            "clock_rate": s.control_rate / self.clock_every,
            "ground_truth_rate": s.control_rate / self.gt_every,
            "velocity_margins": "shadow controllers on the published measurements",
            **timing,
            "security": self.node.watch.watch.report(),
            "witness": self.shadow.report(),
            # the step each agent last answered (None: never): the launcher dates an agent's death by it
            "last_answer_t": {a: stamps[i] / NS if stamps[i] >= 0 else None for i, a in enumerate(self.node.ids)},
            **extra,
        }
        if self.sim.links is not None:
            links = link_summary(self.sim.links, self.sim.view)
            if self.args.mode == "realtime":  # what the real network added, under the emulated links
                links["real_latency_ms"] = timing.get("latency_ms")
            self.recorder.links = links
        return self.recorder.summary(wall_time=wall, requested_duration=s.duration, incomplete=incomplete, extra=info)
