"""The simulator's rclpy node (:class:`SimNode`): its publishers (each step's measurements, ``/clock``,
the ground truth, the display topics), its subscriptions (every agent's wrench, ``/diagnostics``,
``/parameter_events``) and the agents' gains read from their parameters. What a wrench means for a
step is decided by :mod:`formation_sim.node.stepping`; the stepping loops are
:mod:`formation_sim.node.runner`'s; the process, :mod:`formation_sim.node.sim_node`'s.
"""

from __future__ import annotations

import functools
import struct
import time
from contextlib import nullcontext
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import ParameterEvent, ParameterType
from rclpy.node import Node
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import qos_profile_parameter_events
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock

from formation_agent.synchroniser import LIVE_GAINS
from formation_bag.contract import ros_type_name
from formation_bag.writer import offered_qos
from formation_core.faults import ANSWER_MISMATCH, FaultLog
from formation_core.formation import FormationSpec, simulator_view
from formation_deploy.graph_watch import GraphWatch
from formation_deploy.publisher_watch import PublisherWatch, describe, expected_publishers
from formation_msgs_py import topics, wrench_checks
from formation_msgs_py.ros import conversions, qos
from formation_sim.core.measurement import measurement_ends
from formation_sim.core.simulation import Measurements, Simulation
from formation_sim.node.display import DisplayPublisher
from formation_sim.node.run_bag import RunBag
from formation_sim.node.step_messages import StepMessages
from formation_sim.node.stepping import (
    APPLY,
    DUPLICATE,
    MISMATCH,
    NS,
    WrenchBook,
    admit,
)
from formation_sim.node.timing import Timing
from formation_sim.node.witness import FROM_LIVE_CHANGE, Witness


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
                bag.add_topic(name, ros_type_name(WrenchStamped), offered_qos(qos.CONTROL), published=False)
            diagnostics = ros_type_name(DiagnosticArray)
            bag.add_topic(topics.DIAGNOSTICS, diagnostics, offered_qos(qos.DIAGNOSTICS), published=False)
            self.diagnostics_sub = self.create_subscription(
                DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, qos.DIAGNOSTICS, raw=True
            )

    def create_publisher(self, msg_type: Any, topic: str, qos_profile: Any, **kwargs: Any) -> Any:
        """rclpy's publisher; with a bag, one that also writes what it sends (display topics included)."""
        publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        if self.bag is None:
            return publisher
        self.bag.add_topic(
            publisher.topic_name, ros_type_name(msg_type), offered_qos(publisher.qos_profile), published=True
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
        values = parameter_values(future, list(LIVE_GAINS))
        self._gains_changed(i, values, "parameters (read again after a refused answer)")

    def _on_parameter_event(self, event: ParameterEvent) -> None:
        """An agent's gains changed (its ``delta``/``gamma``, live): the shadow follows."""
        i = self.agent_nodes.get(event.node)
        if i is None:
            return
        values = {
            p.name: parameter_value(p.value)
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


def _fmt6(u: Any) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in u) + "]"


def parameter_value(value: Any) -> Any:
    """The Python value of an rcl_interfaces/ParameterValue (None: not set, or a type not used here)."""
    kind = value.type
    if kind == ParameterType.PARAMETER_DOUBLE:
        return float(value.double_value)
    if kind == ParameterType.PARAMETER_INTEGER:
        return float(value.integer_value)
    if kind == ParameterType.PARAMETER_STRING:
        return value.string_value
    return None


def parameter_values(future: Any, names: list[str]) -> dict[str, Any]:
    """{name: value} of a done GetParameters future (empty if the call failed)."""
    try:
        response = future.result()
    except Exception:
        return {}
    if response is None:
        return {}
    return {name: parameter_value(v) for name, v in zip(names, response.values)}


def text_value(value: Any) -> str | None:
    """A parameter's value if it is a non-empty string, else None."""
    return value if isinstance(value, str) and value else None


def number_value(value: Any) -> float | None:
    """A parameter's value if it is a float, else None."""
    return value if isinstance(value, float) else None
