"""The simulator node: ``formation-sim FILE [--mode lockstep|realtime] [--out DIR] …``.

Plays the world with :class:`formation_sim.core.simulation.Simulation`, the code path of the
headless runner (docs/ros2.md). Per control step k it publishes what ``Simulation.sense()``
returns (relative poses of the tree pairs within sensing radius, noisy body twists), ``/clock``
and the ground truth, and collects every agent's wrench. When to advance is decided by the
ROS-free policy of :mod:`formation_sim.node.stepping`; this module is the thin node around it.

- **lockstep**: waits for every agent's WrenchStamped whose stamp equals step k's (integer ns),
  then ``Simulation.advance(u)``. Identical to ``run_headless`` sampled at the same rate. Steps not
  answered within ``--resend`` wall seconds are published again to the missing agents; an agent
  silent for ``simulation.step_timeout`` wall seconds gets a last resend and, still silent
  ``stepping.LAST_CALL`` s later, is named: INCOMPLETE, exit 3. Every answer must agree with the
  witness (:mod:`formation_sim.node.witness`: the agent's controller run here on the bytes it was
  sent, decoded as it decodes them, at its time, in its code form, with its gains, which the node
  reads from every agent's parameters before the first step and follows on ``/parameter_events``);
  one that differs is counted (``answer_mismatch``), not applied, and the step is re-sent; the same
  refused answer to the resend names the agent: INCOMPLETE, exit 5.
- **realtime**: ticks at the control rate on the wall clock; each tick integrates the previous
  period with the latest wrench of each agent held (zero-order hold), then publishes the new
  measurements. A wrench older than ``simulation.command_timeout`` (sim time) is replaced by
  zero; every tick without an agent's answer (stale or zeroed wrench) and every late tick is a
  counted fault (summary ``faults``, formation_msgs_py.faults). A run
  lagging more than ``--lag-budget`` wall seconds behind the wall clock stops INCOMPLETE (exit 4).

Funnels are checked on ground truth at every control step inside this node; ``/clock`` and
``formation/ground_truth`` are published at ``--clock-rate`` / ``--ground-truth-rate`` (default:
the record rate, at most the control rate; ``/clock`` at most 10 Hz in realtime). The run's
outputs (docs/outputs.md) go to ``--out``, also when the run is interrupted (SIGINT/SIGTERM:
summary and trajectory, no figures, so that the stop is fast). The node never needs its stdout
to finish.

``--bag DIR`` (what formation-launch gives a recorded run): the simulator is the run's recorder
(:mod:`formation_sim.node.run_bag`). Every publisher the node creates writes what it sends into the
bag, the wrench and /diagnostics subscriptions what they receive (log time: simulation time in
lockstep, the wall clock of sending or receipt in realtime); a bag I/O error ends the run
INCOMPLETE (exit 4). ``--wait-recorder``: wait before the first step until a recorder
(``formation-record --formation FILE``) subscribes to the ground truth.
"""

from __future__ import annotations

import functools
import math
import struct
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import ParameterEvent, ParameterType
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import qos_profile_parameter_events
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock

from formation_agent.kernel_cache import warm_up
from formation_agent.synchroniser import CODE_FORM_PARAMETER, LIVE_GAINS, PLATFORM_PARAMETER
from formation_msgs_py import topics
from formation_msgs_py.bag import KEY_FORMATION_FILE, KEY_FORMATION_YAML, ros_type_name
from formation_msgs_py.errors import BagError
from formation_msgs_py.faults import ANSWER_MISMATCH, FaultLog
from formation_msgs_py.options import RunOptions
from formation_msgs_py.outcome import ExitCode, Incomplete, guarded
from formation_msgs_py.publisher_watch import PublisherWatch, describe, expected_publishers
from formation_msgs_py.ros import conversions, qos, stopping
from formation_msgs_py.ros.graph_watch import GraphWatch
from formation_msgs_py.ros.rclpy_internals import RCLError
from formation_msgs_py.spec import FormationSpec, agent_view, simulator_view
from formation_msgs_py.transport_check import InsecureTransportError, check_secure_transport
from formation_msgs_py.wire import step_stamp_ns
from formation_sim.core import wrench_checks
from formation_sim.core.links import link_summary
from formation_sim.core.measurement import measurement_ends
from formation_sim.core.preflight import Prepared
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements, Simulation
from formation_sim.node.display import DEFAULT_MARKER_RATE, DisplayPublisher, declare_simulator_parameters
from formation_sim.node.run_bag import VIEW_FILE, RunBag
from formation_sim.node.sim_options import sim_preflight
from formation_sim.node.step_messages import StepMessages
from formation_sim.node.stepping import (
    APPLY,
    DUPLICATE,
    MISMATCH,
    NS,
    ZERO_WRENCH,
    CommandHold,
    LagBudget,
    LockstepWait,
    ParticipantMissingError,
    WrenchBook,
    WrongAnswerError,
    admit,
)
from formation_sim.node.timing import Timing
from formation_sim.node.witness import FROM_LIVE_CHANGE, AgentReport, Witness
from formation_sim.views.live_view import SUBPROTOCOL, LiveView, LiveViewError
from formation_sim.views.outputs import format_summary, write_outputs

#: default /clock rate in realtime [Hz]: the agents' measurement-age checks need no more
REALTIME_CLOCK_RATE = 10.0


class StopRequestedError(Exception):
    """The node was asked to stop (SIGINT/SIGTERM: context shut down)."""


class RunStoppedError(Exception):
    """The run cannot go on (plant blew up, lag budget exceeded): INCOMPLETE with this reason."""

    def __init__(self, incomplete: Incomplete) -> None:
        super().__init__(incomplete.reason)
        self.incomplete = incomplete


class RecordedPublisher:
    """An rclpy publisher that also writes every message it sends into the run's bag (the bytes sent)."""

    def __init__(self, publisher: Any, bag: RunBag) -> None:
        self.publisher = publisher
        self.bag = bag
        self.topic = publisher.topic_name

    def publish(self, msg: Any) -> None:
        self.publisher.publish(msg)
        self.record(msg)

    def record(self, msg: Any) -> None:
        """Write ``msg`` into the bag as :meth:`publish` does, without sending it (nobody to send it to)."""
        if isinstance(msg, bytes):
            self.bag.write_sent(self.topic, msg)
        else:  # a message object: serialised here, with its padding zeroed
            self.bag.write_sent(self.topic, self.bag.zero_padded(self.topic, serialize_message(msg)))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)


class SimNode(Node):
    """Publishers and subscriptions of the simulator; the stepping loops are :class:`Runner`'s."""

    display: DisplayPublisher | None = None
    bag: RunBag | None = None  # a class attribute: Node.__init__ creates a publisher already

    def __init__(
        self,
        spec: FormationSpec,
        measurement_qos: str = "reliable",
        intruder_policy: str = "report",
        bag: RunBag | None = None,
    ) -> None:
        super().__init__(topics.SIM_NODE_NAME)
        self.bag = bag
        meas_qos = qos.measurements(measurement_qos)
        self.spec = spec
        self.ids = spec.agent_ids
        n = len(self.ids)
        self.clock_pub = self.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
        self.gt_pub = self.create_publisher(PoseArray, topics.GROUND_TRUTH, qos.GROUND_TRUTH)
        self.vel_pubs = [self.create_publisher(TwistStamped, topics.velocity(a), meas_qos) for a in self.ids]
        # one publisher per directed tree link; each agent's by edge end (Measurements' order)
        self.links: dict[tuple[str, str], Any] = {}
        for e in spec.edges:
            for obs, tgt in ((e.tail, e.head), (e.head, e.tail)):
                self.links[(obs, tgt)] = self.create_publisher(PoseStamped, topics.relative_pose(obs, tgt), meas_qos)
        ends = measurement_ends(simulator_view(spec))
        self.agent_ends: list[list[tuple[int, Any]]] = [[] for _ in self.ids]
        for k, (obs, tgt) in enumerate(zip(ends.observer, ends.target)):
            self.agent_ends[self.ids.index(obs)].append((k, self.links[(obs, tgt)]))
        # hot path: messages are published and taken as CDR bytes (formation_msgs_py.ros.conversions)
        self.wrench_codecs = [conversions.wrench_codec(a) for a in self.ids]
        #: the bytes of the current step's messages, and what the agents decode from them
        self.messages = StepMessages(spec)
        self.wrenches = WrenchBook(n)
        # the shadow of every agent; in lockstep also the witness every answer must agree with
        self.shadow = Witness(spec, judging=spec.simulation.mode == "lockstep")
        self.witness = self.shadow.answers if self.shadow.judging else None
        #: agents whose gains are being read (AsyncParameterClient futures)
        self.reading: dict[int, Any] = {}
        self.parameter_clients = [AsyncParameterClient(self, topics.agent_node(a)) for a in self.ids]
        self.wrench_check = wrench_checks.WrenchCheck(
            [a.dynamics.max_force for a in spec.agents],
            [a.dynamics.max_torque for a in spec.agents],
            spec.simulation.control_rate,
            lockstep=spec.simulation.mode == "lockstep",
        )
        self.faults = FaultLog()  # refused wrenches; the Runner's RunRecorder shares it
        self.current_ns = -1  # the lockstep step being answered (the wrench check's reference)
        self.received = 0  # messages its subscriptions took (wrenches, /diagnostics)
        self.pub_wall: dict[int, float] = {}
        self.timing = Timing(n)
        self.wrench_subs = [
            self.create_subscription(
                WrenchStamped, topics.wrench(a), functools.partial(self.accept_wrench, i), qos.CONTROL, raw=True
            )
            for i, a in enumerate(self.ids)
        ]
        # the agents' live gains: the shadow follows them
        self.agent_nodes = {topics.agent_node(a): i for i, a in enumerate(self.ids)}
        self.parameter_events_sub = self.create_subscription(
            ParameterEvent, "/parameter_events", self._on_parameter_event, qos_profile_parameter_events
        )
        # every topic of the formation: intruders are reported (and counted in summary.json) here
        self.wrench_topics = ["/" + topics.wrench(a) for a in self.ids]
        self.watch = GraphWatch(
            self,
            PublisherWatch(expected_publishers(self.ids, self.links), intruder_policy),  # type: ignore[arg-type]
            on_intruder=lambda intruder: print(f"formation-sim: {describe(intruder)}", flush=True),
        )
        if bag is not None:  # what the simulator receives goes into the bag as received
            for name in self.wrench_topics:
                bag.add_topic(name, ros_type_name(WrenchStamped), qos.bag_qos(qos.CONTROL), published=False)
            diagnostics = ros_type_name(DiagnosticArray)
            bag.add_topic(topics.DIAGNOSTICS, diagnostics, qos.bag_qos(qos.DIAGNOSTICS), published=False)
            self.diagnostics_sub = self.create_subscription(
                DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, qos.DIAGNOSTICS, raw=True
            )

    def create_publisher(self, msg_type: Any, topic: str, qos_profile: Any, **kwargs: Any) -> Any:
        """rclpy's publisher; with a bag, one that also writes what it sends (display topics included)."""
        publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        if self.bag is None:
            return publisher
        self.bag.add_topic(
            publisher.topic_name, ros_type_name(msg_type), qos.bag_qos(publisher.qos_profile), published=True
        )
        return RecordedPublisher(publisher, self.bag)

    def taken(self) -> int:
        """How many messages and graph polls this node's callbacks have run (Runner.drain's progress)."""
        return self.received + self.watch.polls

    def _on_diagnostics(self, data: bytes) -> None:
        self.received += 1
        self.bag.write(topics.DIAGNOSTICS, data)  # type: ignore[union-attr]  # subscribed only with a bag

    def accept_wrench(self, i: int, data: bytes) -> None:
        """Every wrench agent i publishes comes here (the one place wrenches are accepted).

        In lockstep an answer is applied only if it agrees with the witness (:class:`AnswerWitness`);
        one that differs is the fault ``answer_mismatch`` and leaves the step unanswered (resent)."""
        self.received += 1
        if self.bag is not None:
            self.bag.write(self.wrench_topics[i], data)
        if not self.watch.accept(self.wrench_topics[i], self.wrench_subs[i]):
            return
        refused: wrench_checks.WrenchRefusal | None
        try:
            ns, u = self.wrench_codecs[i].decode(data)
        except struct.error:
            refused = self.wrench_check.malformed()
        else:
            if self.wrenches.repeats(i, ns, u):
                # the agent answered a resent step twice: the same answer again, not a bad input
                self.timing.duplicates += 1
                return
            refused = self.wrench_check.check(i, ns, u, self.current_ns)
        kind = None
        if refused is not None:
            kind, reason = refused.kind, refused.reason
            if self.faults.add(self.current_ns / NS, self.ids[i], f"refused_wrench_{kind}", reason):
                print(f"formation-sim: agent {self.ids[i]}: wrench refused ({kind}): {reason}", flush=True)
            if kind == wrench_checks.MALFORMED:
                return  # no stamp, no values
        admission = admit(i, ns, u, kind, self.wrenches, self.witness)
        if admission.action == APPLY:
            if admission.new_gains:
                self.shadow.adopted.add(i)
            self._answer(i, ns, admission.u)
        elif admission.action == MISMATCH:
            self._mismatch(i, ns, admission)
        elif admission.action == DUPLICATE:
            self.timing.duplicates += 1

    def _answer(self, i: int, ns: int, u: tuple[float, ...]) -> None:
        if self.wrenches.accept(i, ns, u):
            sent = self.pub_wall.get(ns)
            if sent is not None:
                self.timing.latencies.append(time.monotonic() - sent)

    def _mismatch(self, i: int, ns: int, admission: Any) -> None:
        """Agent i's answer to step ``ns`` differs from the witness beyond its tolerance: counted, not
        applied; its gains are read again (a change the events have not brought yet)."""
        u, difference, tol = admission.u, admission.difference, admission.tolerance
        w = self.witness.expected[i].u  # type: ignore[union-attr]  # only called with a witness
        zero = " (a zero wrench: the agent lacked a measurement?)" if not any(u) else ""
        allowed = "0 (bit for bit)" if tol == 0 else f"{tol:.3g} (round-off bound)"
        detail = f"step t={ns / NS:.6f} s: max |u - witness| {difference:.3g}, allowed {allowed}{zero}"
        if self.faults.add(ns / NS, self.ids[i], ANSWER_MISMATCH, detail):
            print(
                f"formation-sim: agent {self.ids[i]}: answer not applied ({ANSWER_MISMATCH}): {detail}; "
                f"answer {_fmt6(u)}, witness {_fmt6(w)}",
                flush=True,
            )
        self.read_gains(i)

    def read_gains(self, i: int) -> None:
        """Ask agent i for its gains (its parameter services), unless a request is out already."""
        if i in self.reading:
            return
        client = self.parameter_clients[i]
        if client.services_are_ready():
            self.reading[i] = client.get_parameters(list(LIVE_GAINS))
            self.reading[i].add_done_callback(functools.partial(self._gains_read, i))

    def _gains_read(self, i: int, future: Any) -> None:
        self.reading.pop(i, None)
        values = _parameter_values(future, list(LIVE_GAINS))
        self._gains_changed(i, values, "parameters (read again after a refused answer)")

    def _on_parameter_event(self, event: ParameterEvent) -> None:
        """An agent's gains changed (its ``delta``/``gamma``, live): the shadow follows."""
        i = self.agent_nodes.get(event.node)
        if i is None:
            return
        values = {
            p.name: _parameter_value(p.value)
            for p in [*event.new_parameters, *event.changed_parameters]
            if p.name in LIVE_GAINS
        }
        if values:
            self._gains_changed(i, values, FROM_LIVE_CHANGE)

    def _gains_changed(self, i: int, values: dict[str, Any], source: str) -> None:
        """Agent i reported δ and/or γ (``values``): the shadow follows, and an answer it refused
        that agrees with the new gains is applied now."""
        delta, gamma = (v if isinstance(v, float) else None for v in (values.get("delta"), values.get("gamma")))
        t = max(self.current_ns, 0) / NS
        before = self.shadow.gains_of(i)
        held = self.shadow.gains_changed(i, delta, gamma, t, source)
        after = self.shadow.gains_of(i)
        if after != before:
            print(f"formation-sim: agent {self.ids[i]}: δ={after[0]:g}, γ={after[1]:g} from t={t:.6f} s ({source})")
        if held is not None:
            self._answer(i, self.witness.ns, held)  # type: ignore[union-attr]  # judging: there is one

    # publishing ------------------------------------------------------------------------------
    def publish_step(self, meas: Measurements, only: list[int] | None = None) -> None:
        """Relative poses (pairs in range) and velocities of one step, stamped ``meas.ns`` (``only``: the
        step's bytes again to those agents); the bag gets them once all are out (RunBag.held: the last
        agent's leave ~50 µs sooner)."""
        if only is None:
            self.messages.encode(meas)
        in_range = meas.in_range.tolist()
        poses, velocities = self.messages.poses, self.messages.velocities
        with nullcontext() if self.bag is None else self.bag.held():
            for i, ends in enumerate(self.agent_ends):
                if only is not None and i not in only:
                    continue
                for k, pub in ends:
                    if in_range[k]:
                        pub.publish(poses[k])
                # its velocity after its poses: an agent computes when its velocity is in, and the
                # first agents compute while the simulator publishes for the others
                self.vel_pubs[i].publish(velocities[i])

    def publish_clock(self, ns: int) -> None:
        self.clock_pub.publish(conversions.clock_bytes(ns))

    def publish_ground_truth(self, ns: int, sim: Simulation) -> None:
        """The ground truth at ``ns``: into the bag always, over DDS only while a reader is matched (with
        none it reaches nobody, and cost a lockstep step 0.14-0.24 ms of CPU in all: BENCHMARKS.md)."""
        subscribed = self.gt_pub.get_subscription_count() > 0
        if not subscribed and self.bag is None:
            return
        data = conversions.ground_truth_bytes(ns, sim.state.p.tolist(), sim.state.R.tolist())
        if subscribed:
            self.gt_pub.publish(data)  # and into the bag (RecordedPublisher)
        else:
            self.gt_pub.record(data)  # a RecordedPublisher: there is a bag

    # discovery -------------------------------------------------------------------------------
    def unmatched_agents(self) -> list[str]:
        """Agents whose velocity or pose readers, or wrench writer, the simulator has not matched."""
        out = []
        for i, a in enumerate(self.ids):
            ok = self.vel_pubs[i].get_subscription_count() > 0 and self.wrench_subs[i].get_publisher_count() > 0
            ok = ok and all(pub.get_subscription_count() > 0 for (obs, _), pub in self.links.items() if obs == a)
            if not ok:
                out.append(a)
        return out

    def recorder_matched(self) -> bool:
        """A recorder subscribes to the ground truth (formation-record subscribes to it last)."""
        return self.gt_pub.get_subscription_count() > 0


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
        while len(asked) < len(node.ids) or not all(f.done() for f in asked.values()):
            for i, client in enumerate(node.parameter_clients):
                if i not in asked and client.services_are_ready():
                    asked[i] = client.get_parameters(names)
            if time.monotonic() > deadline:
                missing = [a for i, a in enumerate(node.ids) if i not in asked or not asked[i].done()]
                raise ParticipantMissingError(
                    missing, f"discovery: the parameter services of agent(s) {', '.join(missing)} did not answer"
                )
            self.spin(0.05)
        for i, future in asked.items():
            values = _parameter_values(future, names)
            report = AgentReport(
                code_form=_text(values.get(CODE_FORM_PARAMETER)),
                platform=_text(values.get(PLATFORM_PARAMETER)),
                delta=_number(values.get("delta")),
                gamma=_number(values.get("gamma")),
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
        reason = wrench_checks.advance_checked(self.sim, u)
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

    def summary(self, wall: float, incomplete: Incomplete | None, extra: dict[str, Any]) -> dict[str, Any]:
        s = self.spec.simulation
        info = {
            "physics_rate": s.physics_rate,
            "steps": self.step,
            "clock_rate": s.control_rate / self.clock_every,
            "ground_truth_rate": s.control_rate / self.gt_every,
            "velocity_margins": "shadow controllers on the published measurements",
        }
        info.update(self.node.timing.summary(self.spec.agent_ids, self.period))
        info["security"] = self.node.watch.watch.report()
        info["witness"] = self.shadow.report()
        # the step each agent last answered (None: never): the launcher dates an agent's death by it
        stamps = self.node.wrenches.stamp
        info["last_answer_t"] = {a: stamps[i] / NS if stamps[i] >= 0 else None for i, a in enumerate(self.node.ids)}
        if self.sim.links is not None:
            links = link_summary(self.sim.links, self.sim.view)
            if self.args.mode == "realtime":  # what the real network added, under the emulated links
                links["real_latency_ms"] = info.get("latency_ms")
            self.recorder.links = links
        info.update(extra)
        return self.recorder.summary(wall_time=wall, requested_duration=s.duration, incomplete=incomplete, extra=info)


def _fmt6(u: Any) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in u) + "]"


def _parameter_value(value: Any) -> Any:
    """The Python value of an rcl_interfaces/ParameterValue (None: not set, or a type not used here)."""
    kind = value.type
    if kind == ParameterType.PARAMETER_DOUBLE:
        return float(value.double_value)
    if kind == ParameterType.PARAMETER_INTEGER:
        return float(value.integer_value)
    if kind == ParameterType.PARAMETER_STRING:
        return value.string_value
    return None


def _parameter_values(future: Any, names: list[str]) -> dict[str, Any]:
    """{name: value} of a done GetParameters future (empty if the call failed)."""
    try:
        response = future.result()
    except Exception:
        return {}
    if response is None:
        return {}
    return {name: _parameter_value(v) for name, v in zip(names, response.values)}


def _text(value: Any) -> str | None:
    return value if isinstance(value, str) and value else None


def _number(value: Any) -> float | None:
    return value if isinstance(value, float) else None


def bag_custom_data(spec: FormationSpec, args: RunOptions) -> dict[str, str]:
    """custom_data of the run's bag: the formation file and the run's effective settings, as
    formation-record --formation FILE --meta mode=… control_rate=… duration=… stores them."""
    s = spec.simulation
    assert args.file is not None  # preflight loaded it
    return {
        "mode": args.mode or s.mode,
        "control_rate": repr(s.control_rate),
        "duration": repr(s.duration),
        KEY_FORMATION_YAML: args.file.read_text(encoding="utf-8"),
        KEY_FORMATION_FILE: args.file.name,
    }


def _interrupted(runner: Runner | None) -> Incomplete:
    t = runner.sim.t if runner is not None else 0.0
    return Incomplete(ExitCode.INTERRUPTED, f"interrupted (SIGINT/SIGTERM) at t={t:.4f} s")


class SimProcess:
    """The parts of one simulator process, made in order by :meth:`start` and released by :meth:`release`
    whatever got made (a stop can come at any point)."""

    def __init__(
        self, spec: FormationSpec, args: RunOptions, raw: list[str], bag: RunBag | None, live: LiveView | None
    ) -> None:
        self.spec, self.args, self.raw, self.bag, self.live = spec, args, raw, bag, live
        self.node: SimNode | None = None
        self.executor: Any = None
        self.runner: Runner | None = None
        self.extra: dict[str, Any] = {}

    def start(self) -> Runner:
        """rclpy, the node (secure transport checked), the executor, the runner; every agent matched."""
        spec, args = self.spec, self.args
        stopping.init(self.raw)
        self.node = node = SimNode(spec, args.measurement_qos, args.intruder_policy, self.bag)
        check_secure_transport()
        node.display = declare_simulator_parameters(node, spec, args, self.live)
        self.executor = EventsExecutor(context=node.context)
        self.executor.add_node(node)
        self.runner = runner = Runner(node, self.executor, spec, args)
        timeout = args.discovery_timeout or 30.0 + len(spec.agents)
        t_disc = time.monotonic()
        runner.wait_for_agents(timeout)
        self.extra["discovery_s"] = time.monotonic() - t_disc
        print(f"formation-sim: all {len(spec.agents)} agents matched in {self.extra['discovery_s']:.2f} s", flush=True)
        return runner

    def stopped_by(self, exc: BaseException) -> Incomplete | None:
        """How a run stopped by ``exc`` (out of :meth:`start` or the stepping) ends; None: no stop but a bug.

        A missing agent: exit 3 naming it; a run that cannot go on: its reason; an insecure transport:
        invalid input; SIGINT/SIGTERM (also a publish or wait it cut short): interrupted."""
        if isinstance(exc, (ParticipantMissingError, WrongAnswerError, RunStoppedError, InsecureTransportError)):
            print(f"formation-sim: ERROR: {exc}", file=sys.stderr, flush=True)
        if isinstance(exc, ParticipantMissingError):
            self.extra["missing"] = exc.names
            return Incomplete(ExitCode.PROCESS_DIED, str(exc))
        if isinstance(exc, WrongAnswerError):
            self.extra["wrong_answers"] = exc.names
            return Incomplete(ExitCode.WRONG_ANSWER, str(exc))
        if isinstance(exc, RunStoppedError):
            return exc.incomplete
        if isinstance(exc, InsecureTransportError):
            return Incomplete(ExitCode.INVALID, str(exc))  # before any runner: the exit status alone
        if isinstance(exc, (KeyboardInterrupt, ExternalShutdownException, StopRequestedError)):
            return _interrupted(self.runner)
        if self.node is not None and not rclpy.ok(context=self.node.context):
            return _interrupted(self.runner)  # a publish or wait cut short by SIGINT/SIGTERM
        return None

    def release(self, incomplete: Incomplete | None) -> tuple[float, Incomplete | None]:
        """Shut executor, node and rclpy down and close the bag; (stepping wall time [s], the run's
        Incomplete: a bag that failed to write makes a finished run INCOMPLETE)."""
        wall = time.monotonic() - self.runner.started if self.runner is not None else 0.0
        if self.executor is not None:
            self.executor.shutdown()  # else it keeps the node's DDS participant past destroy_node (agent_node.spin)
        if self.node is not None:
            self.node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:
            pass  # rclpy's signal handler shut the context down at the same moment (SIGINT/SIGTERM)
        if self.live is not None:
            self.live.close()
        bag = self.bag
        if bag is not None:
            stopped = None if incomplete is None else (int(incomplete.code), incomplete.reason)
            sim = None if self.runner is None else self.runner.sim
            links = None if sim is None or sim.links is None else link_summary(sim.links, sim.view)
            self.extra["recorder"] = bag.close(stopped, links)
            if bag.failed is not None and incomplete is None:
                print(f"formation-sim: ERROR: {bag.failed}", file=sys.stderr, flush=True)
                incomplete = Incomplete(ExitCode.INCOMPLETE, bag.failed)
        return wall, incomplete


@guarded("formation-sim")
def main(argv: list[str] | None = None, *, prepared: Prepared | None = None) -> int:
    """The simulator process (``formation_sim.cli.sim.sim`` pre-flights ``argv`` first)."""
    raw = list(sys.argv if argv is None else [sys.argv[0], *argv])
    run = prepared or sim_preflight(raw)
    spec, out, args = run.spec, run.out, run.options
    assert out is not None  # sim_preflight names OUT (formation-sim --out, or its default)
    for msg in run.warnings:
        print(f"formation-sim: warning: {msg}", file=sys.stderr)
    s = spec.simulation
    print(
        f"formation-sim: {spec.name}, {len(spec.agents)} agents, {args.mode} at {s.control_rate:g} Hz "
        f"(physics {s.physics_rate:g} Hz), {s.duration:g} s; outputs in {out}/",
        flush=True,
    )
    live = None
    if args.foxglove is not None:  # before anything is written: a port in use is an invalid input
        try:
            live = LiveView(args.foxglove, name="formation-sim")
        except LiveViewError as exc:
            print(f"formation-sim: {exc}", file=sys.stderr, flush=True)
            return ExitCode.INVALID
        print(f"formation-sim: live view on {live.url} (Foxglove WebSocket, {SUBPROTOCOL})", flush=True)
    bag = None
    if args.bag is not None:
        try:
            realtime = args.mode == "realtime"
            bag = RunBag(
                args.bag,
                bag_custom_data(spec, args),
                wall_log_time=realtime,
                max_bytes=args.max_bag_size,
                view=out / VIEW_FILE,  # what a viewer shows, at the display rate (docs/bags.md)
                view_rate=args.marker_rate or DEFAULT_MARKER_RATE,
            )
        except (BagError, OSError) as exc:
            print(f"formation-sim: {exc}", file=sys.stderr, flush=True)
            return ExitCode.INVALID
    proc = SimProcess(spec, args, raw, bag, live)
    incomplete: Incomplete | None = None
    try:
        runner = proc.start()
        if args.mode == "lockstep":
            runner.run_lockstep()
        else:
            runner.run_realtime()
    except (Exception, KeyboardInterrupt) as exc:
        incomplete = proc.stopped_by(exc)
        if incomplete is None:
            raise
    finally:
        wall, incomplete = proc.release(incomplete)
    code: int
    if proc.runner is None:
        code = ExitCode.INCOMPLETE if incomplete is None else incomplete.code
    else:
        code = _write_outputs(proc.runner, out, args, wall, incomplete, proc.extra)
    if proc.node is None:
        return code  # stopped while starting: a node half made is released by the interpreter's finalization
    stopping.exit_now(code, proc.node.context)


def _write_outputs(
    runner: Runner, out: Path, args: RunOptions, wall: float, incomplete: Incomplete | None, extra: dict[str, Any]
) -> int:
    """Write OUT (summary, trajectory, figures unless stopped early or --no-plots), print the summary;
    the exit status."""
    summary = runner.summary(wall, incomplete, extra)
    plots = not args.no_plots and incomplete is None
    what = "summary, trajectory" + (", figures" if plots else "")
    early = "" if plots or args.no_plots else "; stopped early: no figures"
    done = f"formation-sim: stepping done: {runner.step} steps in {wall:.2f} s"
    print(f"{done}; writing {out}/ ({what}{early})", flush=True)
    t_out = time.monotonic()
    try:
        figures = write_outputs(out, runner.recorder, summary, plots=plots)
    except OSError as exc:
        print(f"formation-sim: INCOMPLETE: could not write {out}: {exc}", file=sys.stderr, flush=True)
        return ExitCode.INCOMPLETE
    figures_note = f" (figures {figures:.2f} s)" if plots else ""
    print(f"formation-sim: {out}/ written in {time.monotonic() - t_out:.2f} s{figures_note}", flush=True)
    print(format_summary(summary), flush=True)
    return summary["exit_status"]


if __name__ == "__main__":
    sys.exit(main())
