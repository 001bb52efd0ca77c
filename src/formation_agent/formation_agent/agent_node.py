"""The agent node: one process per agent (docs/topics.md).

``formation-agent --ros-args -p formation_file:=FILE -p agent_id:=ID`` reads only
``agent_view(spec, ID)``, subscribes to exactly its own ``agent_<i>/velocity`` and the
``agent_<i>/relative_pose/agent_<j>`` of its tree neighbours j, and publishes
``agent_<i>/wrench`` stamped with the stamp of the measurements it answers, plus
``/diagnostics`` at most every ``diagnostics_period`` (wall s, ≥ 0.1 s).

The node checks every message first (:mod:`formation_msgs_py.measurement_checks`): a refused value
(non-finite, not a rotation, out of range) answers its step with a zero wrench and ERROR; a refused
stamp (too far from the agent's time) or malformed bytes name no step and are dropped. What it does
with the rest, and its time, is :class:`formation_agent.synchroniser.StepSynchroniser`'s (no ROS).
It reports its code form and numeric platform as read-only parameters: a lockstep simulator on the
same platform then checks its answers bit for bit (formation_sim.node.witness).
"""

from __future__ import annotations

import functools
import math
import struct
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import JumpThreshold, TimeJump
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

from formation_agent.controller import ERROR, LEVEL_NAMES, OK, AgentController
from formation_agent.kernel_cache import warm_up
from formation_agent.synchroniser import (
    CODE_FORM_PARAMETER,
    LIVE_GAINS,
    PLATFORM_PARAMETER,
    REFUSED_PAST_STAMP,
    StepSynchroniser,
    Window,
    live_gains,
)
from formation_core.errors import FormationSpecError
from formation_core.faults import fault_lines, write_json
from formation_core.formation import AgentView, agent_view
from formation_core.numba_kernels import CODE_FORM, numeric_platform
from formation_core.spec import load_formation
from formation_deploy.graph_watch import GraphWatch
from formation_deploy.publisher_watch import (
    POLICIES,
    PublisherWatch,
    expected_publishers,
    security_file,
)
from formation_deploy.transport_check import InsecureTransportError, check_secure_transport
from formation_msgs_py import topics
from formation_msgs_py.codec import NS_PER_S
from formation_msgs_py.measurement_checks import DROPPED_KINDS, PAST_STAMP, InputCheck, Refusal
from formation_msgs_py.ros import conversions, qos
from formation_ros import parameters, shutdown
from formation_ros.rclpy_internals import RCLError, now_ns_reader

_DIAG_LEVEL = {OK: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, ERROR: DiagnosticStatus.ERROR}
NODE_NAME = topics.AGENT_NODE_NAME
POSE_WAIT_DOC = (
    "wall seconds to wait for the neighbours' poses once the velocity is in; a neighbour still "
    "missing then is out of range: zero wrench and ERROR; live"
)
DIAG_DOC = "wall seconds between /diagnostics messages (>= 0.1; a message costs ~0.4 ms of CPU); live"
FAULTS_DOC = (
    "file to write this agent's fault counts to when it stops (per kind: count, first and last sim time; "
    "formation-launch merges them into summary.json faults); empty: none"
)
CODE_FORM_DOC = (
    "how this agent runs its controller: compiled (numba) or interpreted (NUMBA_DISABLE_JIT=1); reported, not settable"
)
PLATFORM_DOC = (
    "fingerprint of what decides the controller's last bits here (host, CPU, interpreter, numpy and numba, "
    "their environment); a simulator on the same one checks this agent's answers bit for bit; reported, not settable"
)
QOS_DOC = "QoS of the measurements: reliable or best-effort, as the simulator's --measurement-qos"
POLICY_DOC = (
    f"publishers other than the expected ones on this agent's topics: {' or '.join(POLICIES)} "
    "(also ignore that topic's messages while they are there; docs/security.md)"
)


def _root(name: str) -> str:
    """A topic name of docs/topics.md from the root: the node's own namespace /agent_<id> must not prefix it."""
    return "/" + name


class AgentNode(Node):
    """Thin ROS wrapper around :class:`StepSynchroniser` for one agent."""

    def __init__(self, agent_id: str, context: Context | None = None) -> None:
        super().__init__(NODE_NAME, namespace="/" + topics.agent_frame(agent_id), context=context)
        declare = parameters.declare
        declare(self, "agent_id", agent_id, "the agent's id in the formation file", read_only=True, any_type=True)
        path = declare(self, "formation_file", "", "formation file (YAML); the agent reads its view", read_only=True)
        if not path:
            raise FormationSpecError("formation_file", "parameter formation_file is required")
        view: AgentView = agent_view(load_formation(path), agent_id)
        self.view = view
        self.agent_id = view.agent_id
        pose_wait = declare(self, "pose_wait", 0.005, POSE_WAIT_DOC, low=0.0, high=1.0)
        self.diag_period = declare(self, "diagnostics_period", 0.5, DIAG_DOC, low=0.1, high=3600.0)
        self.measurement_qos = declare(self, "measurement_qos", "reliable", QOS_DOC, read_only=True)
        policy = declare(self, "intruder_policy", "report", POLICY_DOC, read_only=True)
        self.faults_file = declare(self, "faults_file", "", FAULTS_DOC, read_only=True)
        gains = {n: declare(self, n, float(getattr(view.controller, n)), doc) for n, doc in LIVE_GAINS.items()}
        # what a lockstep simulator's witness needs to compute this agent's answers as it does
        declare(self, CODE_FORM_PARAMETER, CODE_FORM, CODE_FORM_DOC, read_only=True, fixed=True)
        declare(self, PLATFORM_PARAMETER, numeric_platform(), PLATFORM_DOC, read_only=True, fixed=True)
        self.sync = StepSynchroniser(
            AgentController(view),
            self._publish_wrench,
            pose_wait=float(pose_wait),
        )
        warm_up(view)  # the controller's kernels before subscribing (compiled: numba's cache, ~1 s), not at step 0
        self.inputs = InputCheck(view.sensing_radius, round(view.controller.measurement_timeout * NS_PER_S))
        self.sync.set_gains(**live_gains(self.agent_id, gains))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._log_parameters)
        # hot path: CDR bytes in and out (formation_msgs_py.ros.conversions), no message objects
        self._wrench_codec = conversions.wrench_codec(view.agent_id)
        self._twist_codec = conversions.twist_codec(view.agent_id)
        self._pub = self.create_publisher(WrenchStamped, _root(topics.wrench(view.agent_id)), qos.CONTROL)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos.DIAGNOSTICS)
        meas_qos = qos.measurements(self.measurement_qos)
        # the publishers of what this agent hears (and of its own wrench topic) are watched
        expected = expected_publishers([view.agent_id], [(view.agent_id, j) for j in view.neighbours])
        self._watch = GraphWatch(self, PublisherWatch(expected, policy))
        self._velocity = _root(topics.velocity(view.agent_id))
        self._subs = {
            self._velocity: self.create_subscription(
                TwistStamped, self._velocity, self._on_velocity, meas_qos, raw=True
            )
        }
        for j in view.neighbours:
            codec = conversions.relative_pose_codec(view.agent_id)
            topic = _root(topics.relative_pose(view.agent_id, j))
            self._subs[topic] = self.create_subscription(
                PoseStamped,
                topic,
                functools.partial(self._on_pose, j, codec, topic),
                meas_qos,
                raw=True,
            )
        # not Node's own _clock (the same object, but ours to name)
        self._ros_clock = self.get_clock()
        self._jump_handle = self._ros_clock.create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=False),
            post_callback=self._on_jump,
        )
        self._use_sim_time = bool(self.get_parameter("use_sim_time").value)
        # sim time for the input check of every message (through the clock's handle: rclpy_internals).
        # Without sim time stamps are not judged (0).
        self._clock_ns = now_ns_reader(self._ros_clock) if self._use_sim_time else (lambda: 0)
        self._next_diag = time.monotonic() + self.diag_period
        self.get_logger().info(
            f"agent {view.agent_id}: neighbours {', '.join(view.neighbours)}; "
            f"use_sim_time={self._use_sim_time}; pose_wait={self.sync.pose_wait * 1e3:.1f} ms"
        )

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """Apply live parameters; refuse the whole set, with the reason, if one value is invalid."""
        values = {p.name: p.value for p in params}
        try:
            gains = live_gains(self.agent_id, {k: v for k, v in values.items() if k in LIVE_GAINS})
        except FormationSpecError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.sync.set_gains(**gains)
        if "pose_wait" in values:
            self.sync.pose_wait = float(values["pose_wait"])
        if "diagnostics_period" in values:
            self.diag_period = float(values["diagnostics_period"])
        return SetParametersResult(successful=True)

    def _log_parameters(self, params: list) -> None:
        """Log every accepted change (called once the whole set is applied)."""
        for p in params:
            self.get_logger().info(f"parameter {p.name} set to {p.value!r}")

    # callbacks: messages -> synchroniser
    def _on_velocity(self, data: bytes) -> None:
        if not self._watch.accept(self._velocity, self._subs[self._velocity]):
            return
        try:
            ns, v = self._twist_codec.decode(data)
        except struct.error:
            self._refuse(0, self.inputs.malformed("velocity"))
            return
        refusal = self.inputs.velocity(ns, v, self._clock_ns(), self.sync.confirmed_ns)
        if refusal is not None:
            self._refuse(ns, refusal)
            return
        self.sync.on_velocity(ns, v, time.monotonic())

    def _on_pose(self, j: str, codec: conversions.StampedCodec, topic: str, data: bytes) -> None:
        if not self._watch.accept(topic, self._subs[topic]):
            return
        try:
            ns, values = codec.decode(data)
        except struct.error:
            self._refuse(0, self.inputs.malformed(f"relative pose of {j}"))
            return
        refusal = self.inputs.pose(j, ns, values, self._clock_ns(), self.sync.confirmed_ns)
        if refusal is not None:
            self._refuse(ns, refusal, j)
            return
        p, R = conversions.relative_pose_from_values(values)
        self.sync.on_pose(j, ns, p, R, time.monotonic())

    def _refuse(self, ns: int, refusal: Refusal, neighbour: str | None = None) -> None:
        """A refused measurement (formation_msgs_py.measurement_checks): ERROR, counted; a bad value answers zero."""
        n = self.inputs.counts[refusal.kind]
        t = (ns or self._ros_clock.now().nanoseconds) / NS_PER_S
        self.sync.fault(t, f"refused_{refusal.kind}", refusal.reason)
        if n & (n - 1) == 0:  # the 1st, 2nd, 4th, 8th, … of each kind: every kind shows, the log stays small
            self.get_logger().error(f"refused ({refusal.kind}, {n} so far): {refusal.reason}")
        if refusal.kind in DROPPED_KINDS:  # names no step to answer: dropped
            w = self.sync.window
            w.level, w.message, w.faults = ERROR, f"refused: {refusal.reason}", w.faults + 1
            return
        self.sync.refuse(ns, refusal.reason, time.monotonic(), neighbour)

    def report_faults(self) -> None:
        """Print every fault kind (count, first and last) and write ``faults_file`` (at the stop)."""
        faults = self.sync.faults.as_dict()
        for line in fault_lines(faults):
            print(f"formation-agent {self.agent_id}:{line}", flush=True)
        if self.faults_file:
            try:
                write_json(Path(self.faults_file), faults)
                # intruders on this agent's own topics: the launcher names them in the verdict
                # (the simulator's graph may never see one that reached only this agent)
                write_json(security_file(self.faults_file), self._watch.watch.report())
            except OSError as exc:
                print(f"formation-agent {self.agent_id}: could not write {self.faults_file}: {exc}", flush=True)

    def _publish_wrench(self, ns: int, u: Sequence[float]) -> None:
        try:
            self._pub.publish(self._wrench_codec.encode(ns, u))
        except RCLError:
            if self.context.ok():
                raise
            # SIGINT/SIGTERM shut the context down (rclpy's handler) since this step began: a stop

    def _on_jump(self, info: TimeJump) -> None:
        """/clock went back: counted, and nothing reset (any process may publish /clock in plain mode;
        the synchroniser restarts time only when the measurements go back with it)."""
        if info.delta.nanoseconds < 0:
            clock_ns = self._ros_clock.now().nanoseconds
            self.get_logger().warning(
                f"/clock jumped back by {-info.delta.nanoseconds / NS_PER_S:.6f} s to {clock_ns / NS_PER_S:.6f} s: "
                "counted, nothing reset (time restarts only if the measurements go back too)"
            )
            self.sync.clock_jumped_back(clock_ns, info.delta.nanoseconds)

    # the loop: spin, then deadlines (pose wait, diagnostics) on the wall clock
    def spin(self) -> None:
        sync = self.sync
        mono = time.monotonic
        executor = EventsExecutor(context=self.context)  # one callback per spin_once (BENCHMARKS.md)
        executor.add_node(self)
        ok = self.context.ok
        try:
            while ok():
                dl = sync.deadline()
                now = mono()
                timeout = min(self._next_diag - now, 0.1 if dl is None else dl - now)
                executor.spin_once(timeout_sec=max(timeout, 0.0))
                now = mono()
                if sync.pending is not None and now >= sync.pending[2]:
                    sync.try_compute(now, final=True)
                if now >= self._next_diag:
                    self._publish_diagnostics(now)
                    self._next_diag = now + self.diag_period
        finally:
            # the executor holds the node's entities, and node and executor refer to each other: not
            # shut down, it keeps the node's DDS participant (and /dev/shm segment) past destroy_node
            executor.shutdown()

    def _publish_diagnostics(self, now: float) -> None:
        sync = self.sync
        w = sync.window
        status = DiagnosticStatus()
        status.name = f"formation_agent/{self.agent_id}"
        status.hardware_id = topics.agent_frame(self.agent_id)
        level, message = w.level, w.message
        age = None if sync.last_measurement_wall is None else now - sync.last_measurement_wall
        stale_s = None
        if self._use_sim_time and sync.confirmed_ns is not None:
            clock_ns = self._ros_clock.now().nanoseconds
            stale_s = (clock_ns - sync.confirmed_ns) / NS_PER_S
            timeout = self.view.controller.measurement_timeout
            # stale when /clock has moved on AND no measurement came for as long in wall time: /clock
            # alone (any process may publish it) cannot raise the alarm while the measurements flow
            if stale_s > timeout and age is not None and age > timeout:
                level, message = ERROR, f"no measurements for {stale_s:.3f} s (sim time)"
        if w.steps == 0 and level == OK:
            message = "waiting for measurements" if sync.last_ns is None else "no new measurements"
        status.level = _DIAG_LEVEL[level]
        status.message = message or LEVEL_NAMES[level]
        values = [KeyValue(key="steps", value=str(w.steps)), KeyValue(key="faults", value=str(w.faults))]
        refused = dict(self.inputs.counts)
        past = sync.faults.counts.get((self.agent_id, REFUSED_PAST_STAMP))
        if past is not None:
            refused[PAST_STAMP] = past.count
        values += [KeyValue(key=f"refused/{k}", value=str(n)) for k, n in sorted(refused.items())]
        last = "" if sync.last_ns is None else f"{sync.last_ns / NS_PER_S:.9f}"
        values.append(KeyValue(key="last_stamp", value=last))
        values.append(KeyValue(key="measurement_age_wall", value="" if age is None else f"{age:.6f}"))
        values.append(KeyValue(key="measurement_age_sim", value="" if stale_s is None else f"{stale_s:.6f}"))
        for k, ie in enumerate(self.view.edges):
            name = ie.edge.name
            values.append(KeyValue(key=f"margin_e/{name}", value=_fmt(w.margin_e[k])))
            values.append(KeyValue(key=f"margin_psi/{name}", value=_fmt(w.margin_psi[k])))
        for c, ch in enumerate(("vx", "vy", "vz", "wx", "wy", "wz")):
            values.append(KeyValue(key=f"margin_v/{ch}", value=_fmt(w.margin_v[c])))
        status.values = values
        arr = DiagnosticArray()
        arr.header.stamp = self._ros_clock.now().to_msg()
        arr.status = [status]
        self._diag_pub.publish(arr)
        sync.window = Window.empty(len(sync.neighbours))


def _fmt(x: float) -> str:
    return "" if math.isinf(x) else f"{x:.6f}"


def _cli_sets(args: Sequence[str], name: str) -> bool:
    return any(a.startswith(f"{name}:=") for a in args)


def resolve_agent_id(argv: Sequence[str], context: Context | None) -> str:
    """The agent id: ``-p agent_id:=ID`` on the command line, else the ``agent_id`` parameter a
    parameters file gives the node (``/**`` or its own section; a ``-r __ns:=/agent_<ID>`` remap
    selects the per-agent section), else the ``<ID>`` of such a namespace remap."""
    for a in argv:
        if a.startswith("agent_id:="):
            return a.split(":=", 1)[1].strip("'\"")
    probe = Node(NODE_NAME, context=context, start_parameter_services=False)
    try:
        value = parameters.declare(probe, "agent_id", "", "the agent's id in the formation file", any_type=True)
        namespace = probe.get_namespace()
    finally:
        probe.destroy_node()
    if value not in (None, ""):
        return str(value)
    prefix = "/" + topics.agent_frame("")
    if namespace.startswith(prefix) and namespace.count("/") == 1:
        return namespace[len(prefix) :]
    raise FormationSpecError("agent_id", "is required: -p agent_id:=ID, a parameters file or -r __ns:=/agent_ID")


def main(args: list[str] | None = None) -> int:
    """Entry point of ``formation-agent``; exit 2 on a bad file or parameter. SIGINT and SIGTERM
    stop the agent (formation_ros.shutdown): it writes its faults, destroys its node and ends
    the process at once."""
    argv = list(sys.argv if args is None else args)
    if not _cli_sets(argv, "use_sim_time"):
        argv += ["--ros-args", "-p", "use_sim_time:=true"]
    node = None
    try:
        shutdown.init(argv)
        try:
            node = AgentNode(resolve_agent_id(argv, None))
            check_secure_transport()
        except (FormationSpecError, ParameterException, ValueError, InsecureTransportError) as exc:
            print(f"formation-agent: {exc}", file=sys.stderr)
            return 2
        node.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # stopped before rclpy's handler was in place, or while spinning
    except RCLError:
        if rclpy.ok():
            raise
        # a call cut short by SIGINT/SIGTERM (rclpy's handler shut the context down): a stop
    finally:
        if node is not None:
            node.report_faults()
            node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:
            pass  # rclpy's signal handler shut the context down at the same moment (SIGINT/SIGTERM)
    if node is None:
        return 0  # stopped while starting: a node half made is released by the interpreter's finalization
    shutdown.exit_now(0, node.context)


if __name__ == "__main__":
    sys.exit(main())
