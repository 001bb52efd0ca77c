"""``formation-record``: record the docs/topics.md topics of a running formation into a bag.

A thin rclpy node: raw subscriptions (the CDR bytes, nothing is deserialized) drained by one
wait-set loop straight into a :class:`formation_bag.writer.SegmentedBagWriter`
(a segment closes in a few ms; every subscription queues up to 1000 messages meanwhile).
Counts: received and written per topic, and the publishers' sequence numbers (what they
published in total and while we listened), stored in metadata.yaml custom_data ``recorder_counts``
(and in ``--stats FILE``). SIGINT/SIGTERM (our own handlers) stop the loop, take and write what
the subscriptions already hold (no waiting for silence: agents publish /diagnostics until they
are stopped), close the last segment and write metadata.yaml (exit status 0). A SIGKILL loses at
most the open chunk of the open segment (the writer flushes a chunk every 1 MiB or second of log
time; ``formation-bag repair`` salvages the rest). A full disk stops the recording with one line
and exit status 4.

An observer of any run: nothing waits for it while stepping (formation-launch has the simulator
write the run's bag itself, ``formation-sim --bag``). ``formation-sim --wait-recorder`` waits for
it to subscribe before the first step, and ``formation-replay`` until its subscriptions have matched
and settled; a recorder started after the simulator reports the steps it missed.

Topics: every docs/topics.md topic of ``--formation FILE`` (exact, known before anything runs),
plus whatever the graph shows that matches (checked every ``--discovery-period`` s); or only
``--topics``. Log time (``--log-time``): ``sim``, each message's own stamp (simulation time, as
``ros2 bag record --use-sim-time`` gives; the default for lockstep runs, so a player shows the run
at its true speed), or ``receive``, the receive time on the system clock (the default in realtime,
where the analysis needs the order in which wrenches arrived).

Over 500 lines: the recorder node's one wait-set loop with the plan of what to record, the counts
it keeps per topic and the clean stop that writes them; they share the writer and the subscriptions.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib
import json
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from formation_bag import messages as m
from formation_bag.contract import KEY_FORMATION_FILE, KEY_FORMATION_YAML, STAMPED_TYPES, ros_type_name
from formation_bag.dataset import stated_settings
from formation_bag.parsers import record_parser
from formation_bag.writer import SegmentedBagWriter, offered_qos
from formation_core.errors import BagError, BagTopicError, FormationSpecError
from formation_core.faults import write_json
from formation_core.spec import load_formation
from formation_core.verdict import ExitCode, guarded
from formation_deploy.transport_check import InsecureTransportError, check_secure_transport
from formation_msgs_py import codec, topics
from formation_msgs_py.ros import qos as fqos
from formation_ros.rclpy_internals import RCLError, SubscriptionWaitSet, pointer, raw_taker

#: depth of the recorder's own subscription queues (it must never be the one that drops)
SUB_DEPTH = 1000
#: with --formation, the ground-truth subscription waits until every other subscription has matched
#: a publisher, then this many seconds (the publishers' side of discovery), at most DEFER_TIMEOUT s
DEFER_SETTLE = 0.5
DEFER_TIMEOUT = 60.0


def msg_class(msgtype: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name``."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def offered_profile(topic: str) -> QoSProfile:
    """The project's QoS profile of a topic (formation_msgs_py.ros.qos)."""
    if topic == topics.CLOCK:
        return fqos.CLOCK
    if topic.endswith(topics.GROUND_TRUTH):
        return fqos.GROUND_TRUTH
    if topic == topics.DIAGNOSTICS:
        return fqos.DIAGNOSTICS
    return fqos.CONTROL


def parse_decimation(items: Sequence[str]) -> list[tuple[str, int]]:
    """``TOPIC=N`` (TOPIC may be a glob such as ``/agent_*/relative_pose/*``) -> [(pattern, N)]."""
    out = []
    for item in items:
        pattern, sep, n = item.rpartition("=")
        try:
            every = int(n)
        except ValueError:
            every = 0
        if not sep or not pattern or every < 1:
            raise BagTopicError(f"--decimate {item!r}: expected TOPIC=N with N a positive integer")
        out.append((pattern, every))
    return out


def parse_meta(items: Sequence[str]) -> dict[str, str]:
    """``KEY=VALUE`` -> {KEY: VALUE}; the run settings among them (``mode``, ``control_rate``,
    ``duration``: what formation-analyze takes over the formation file's) must be valid."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise BagTopicError(f"--meta {item!r}: expected KEY=VALUE")
        out[key] = value
    stated_settings(out, "--meta ")
    return out


class Recorder(Node):
    """Raw subscriptions to the selected topics, drained by :meth:`spin` straight into the bag.

    No executor: one wait set over every subscription, then *all* queued messages of each ready
    subscription are taken (``take_message(raw=True)``) and written. rclpy's executor costs tens
    of µs per callback, too much for a lockstep run on a small machine; this loop does not.
    Log time = the rmw receive timestamp (system clock), as ``ros2 bag record``.
    """

    def __init__(
        self,
        writer: SegmentedBagWriter,
        *,
        known: dict[str, str],
        only: list[str] | None,
        namespace: str,
        decimate: list[tuple[str, int]],
        sim_log_time: bool = False,
        step_topics: list[str] | None = None,
    ) -> None:
        super().__init__("formation_record")
        self.sim_log_time = sim_log_time
        self.step_topics = step_topics or []  # velocities and wrenches: the first one dates the recording
        self.first_step_stamp: int | None = None
        self.sim_now = 0  # the latest stamp taken [ns]
        #: monotonic wall clock [s] when the first and the latest messages were taken: the run's wall time
        self.first_wall: float | None = None
        self.last_wall = 0.0
        self.writer = writer
        self.namespace = namespace
        self.only = only
        self.decimate = decimate
        self.received: dict[str, int] = {}
        self.written: dict[str, int] = {}
        self.seq: dict[str, list[int]] = {}  # topic -> [first, last] publication sequence number
        self.subs: dict[str, Any] = {}
        self.reliable: set[str] = set()
        self.active_version = 0
        self._active: list[tuple[str, Any, Any, int]] = []
        self.stopping = False
        # Ground truth last, and only once every other subscription has matched a publisher (then
        # DEFER_SETTLE s more): formation-sim --wait-recorder starts stepping when it sees a
        # ground-truth subscriber, and DDS delivers nothing published before both sides matched.
        gt = m.absolute(topics.GROUND_TRUTH, namespace)
        self._deferred: tuple[str, str] | None = None
        self._defer_until = time.monotonic() + DEFER_TIMEOUT
        self._matched_at: float | None = None
        for name, msgtype in known.items():
            if only is not None and name not in only:
                continue
            if name == gt:
                self._deferred = (name, msgtype)
            else:
                self._subscribe(name, msgtype)
        if self._deferred is not None and not self._active:
            self._subscribe(*self._deferred)
            self._deferred = None
        self.discover()

    # -- topics ----------------------------------------------------------------------------------

    def _wanted(self, name: str) -> bool:
        if self.only is not None:
            return name in self.only
        return m.classify(name, self.namespace) is not None

    def _in_loop(self, name: str) -> bool:
        kind = m.classify(name, self.namespace)
        return kind is not None and kind.kind in ("clock", "velocity", "relative_pose", "wrench")

    def check_deferred(self) -> None:
        """Subscribe to the ground truth once every other subscription has matched (or after a timeout)."""
        if self._deferred is None:
            return
        now = time.monotonic()
        # only the topics of the closed loop are waited for: /diagnostics (≤ 10 Hz) and the display
        # topics (markers, funnels: off with --marker-rate 0) are optional
        if all(sub.get_publisher_count() > 0 for name, sub, _, _ in self._active if self._in_loop(name)):
            if self._matched_at is None:
                self._matched_at = now
        else:
            self._matched_at = None
        ready = self._matched_at is not None and now - self._matched_at >= DEFER_SETTLE
        if ready or now > self._defer_until:
            name, msgtype = self._deferred
            self._deferred = None
            self._subscribe(name, msgtype)
            why = "every publisher matched" if ready else f"not every publisher matched in {DEFER_TIMEOUT:g} s"
            print(f"formation-record: {why}; subscribed to {name}", flush=True)

    def discover(self) -> None:
        """Subscribe to new wanted topics; re-subscribe best effort where only such publishers appear."""
        for name, types in self.get_topic_names_and_types():
            if not self._wanted(name) or not types:
                continue
            if self._deferred is not None and name == self._deferred[0]:
                continue
            if name not in self.subs:
                self._subscribe(name, types[0])
            elif name in self.reliable and self.subs[name] is not None and self.subs[name].get_publisher_count() == 0:
                # subscribed (reliable) before the publisher existed; a best-effort publisher
                # (e.g. --measurement-qos best-effort) never matches a reliable subscription
                pubs = self.get_publishers_info_by_topic(name)
                if pubs and any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in pubs):
                    self._resubscribe(name, best_effort=True)

    def _every(self, name: str) -> int:
        for pattern, n in self.decimate:
            if fnmatch.fnmatchcase(name, pattern):
                return n
        return 1

    def _subscribe(self, name: str, msgtype: str) -> None:
        try:
            cls = msg_class(msgtype)
        except (ImportError, AttributeError, ValueError):
            self.get_logger().warning(f"{name}: type {msgtype} not available, not recorded")
            self.subs[name] = None
            return
        pubs = self.get_publishers_info_by_topic(name)
        offered = [p.qos_profile for p in pubs] or [offered_profile(name)]
        best_effort = any(p.reliability == ReliabilityPolicy.BEST_EFFORT for p in offered)
        try:
            self.writer.add_topic(name, msgtype, tuple(offered_qos(p) for p in offered[:1]))
        except BagError as exc:
            self.get_logger().warning(f"{name}: {exc}; not recorded")
            self.subs[name] = None
            return
        self.received[name] = 0
        self.written[name] = 0
        self._create(name, cls, best_effort)

    def _create(self, name: str, cls: Any, best_effort: bool) -> None:
        sub_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=SUB_DEPTH,
            reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        )
        sub = self.create_subscription(cls, name, _unused, sub_qos, raw=True)
        self.subs[name] = sub
        if best_effort:
            self.reliable.discard(name)
        else:
            self.reliable.add(name)
        self._active.append((name, sub, cls, self._every(name)))
        self.active_version += 1

    def _resubscribe(self, name: str, *, best_effort: bool) -> None:
        entry = next(e for e in self._active if e[0] == name)
        self._take_all(*entry)
        self._active.remove(entry)
        self.destroy_subscription(entry[1])
        self.get_logger().info(f"{name}: best-effort publisher, subscribing best effort")
        self._create(name, entry[2], best_effort)

    @property
    def topic_count(self) -> int:
        return len(self._active)

    # -- the loop ----------------------------------------------------------------------------------

    def request_stop(self, *_args: object) -> None:
        """Signal handler (SIGINT/SIGTERM): finish the current wait, drain, then stop."""
        self.stopping = True

    def spin(self, *, discovery_period: float, status_period: float | None) -> None:
        """Record until :meth:`request_stop` (SIGINT/SIGTERM) or the context shuts down.

        On stop, every message the subscriptions have already received is still taken and written
        (a publisher that got its acknowledgements has handed them to us), then the loop ends.
        """
        context = self.context
        next_discovery = time.monotonic() + discovery_period
        next_status = None if status_period is None else time.monotonic() + status_period
        last_total, last_t = 0, time.monotonic()
        wait_set = None
        n_active = -1
        version = -1
        while context.ok() and not self.stopping:
            if self.active_version != version:
                version = self.active_version
                n_active = len(self._active)
                if n_active:
                    wait_set = SubscriptionWaitSet(n_active, context)
                by_pointer = {pointer(entry[1]): entry for entry in self._active}
            if n_active and wait_set is not None:
                try:
                    ready = wait_set.wait((sub for _, sub, _, _ in self._active), 100_000_000)
                except RCLError:
                    if not context.ok():
                        break  # interrupted while waiting
                    raise
                for ptr in ready:
                    self._take_all(*by_pointer[ptr])
            else:
                time.sleep(0.1)  # nothing to record yet: discovery below
            now = time.monotonic()
            self.check_deferred()
            if now >= next_discovery:
                self.discover()
                next_discovery = now + discovery_period
            if next_status is not None and now >= next_status:
                total = sum(self.received.values())
                print(
                    f"formation-record: {self.topic_count} topics, {total} messages "
                    f"({(total - last_total) / (now - last_t):.0f}/s), {len(self.writer.segments)} segments closed",
                    flush=True,
                )
                last_total, last_t, next_status = total, now, now + (status_period or 0)
        if context.ok():
            self.drain()

    def drain(self, limit: float = 1.0) -> None:
        """Take what the subscriptions hold now, until a pass finds nothing (at most ``limit`` s).

        Does not wait for silence: the agents publish /diagnostics until they are stopped."""
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline and sum(self._take_all(*entry) for entry in self._active) > 0:
            pass

    def _take_all(self, name: str, sub: Any, cls: Any, every: int) -> int:
        """Take and write every queued message of one subscription; returns how many."""
        take = raw_taker(sub)
        received, seq, write = self.received, self.seq, self.writer.write
        sim_time = self.sim_log_time
        step_topic = name in self.step_topics and self.first_step_stamp is None
        # messages that start with a stamp (header or Clock); others (markers, funnels, /tf) are
        # logged at the latest simulation time seen
        stamped = ros_type_name(cls) in STAMPED_TYPES
        count = 0
        while (got := take(cls, True)) is not None:
            data, info = got
            if stamped:
                stamp = codec.stamp_of(data)
                self.sim_now = max(self.sim_now, stamp)
            else:
                stamp = self.sim_now
            if step_topic and self.first_step_stamp is None:
                self.first_step_stamp = stamp
            count += 1
            n = received[name]
            received[name] = n + 1
            s = info.get("publication_sequence_number")
            if s is not None:
                first_last = seq.get(name)
                if first_last is None:
                    seq[name] = [s, s]
                elif s > first_last[1]:
                    first_last[1] = s
            if n % every == 0:
                write(name, stamp if sim_time else info.get("received_timestamp") or time.time_ns(), data)
                self.written[name] += 1
        if count:
            self.last_wall = time.monotonic()
            if self.first_wall is None:
                self.first_wall = self.last_wall
        return count

    def missed_start(self) -> str | None:
        """What a recorder started after the simulator missed (None if it has the first step)."""
        if self.first_step_stamp is None or self.first_step_stamp == 0:
            return None
        return f"started after the run: steps before t={self.first_step_stamp / 1e9:.6f} s not recorded"

    def finish(self) -> dict[str, Any]:
        """Close the bag with the counts in custom_data; returns the counts."""
        published: dict[str, int | None] = {}
        total: dict[str, int | None] = {}
        for name, (first, last) in self.seq.items():
            # one publisher per topic of docs/topics.md: its sequence numbers (from 1) count what it
            # published in total and while we listened; with several publishers (/diagnostics)
            # they interleave: unknown
            span = last - first + 1
            single = span >= self.received[name]
            published[name] = span if single else None
            total[name] = last if single else None
        stats = {
            "received": dict(self.received),
            "written": dict(self.written),
            "published_seen": published,
            "published_total": total,
            "decimate": {p: n for p, n in self.decimate},
            "log_time": "sim" if self.sim_log_time else "receive",
            "missed_start": self.missed_start(),
        }
        self.writer.custom_data["recorder_counts"] = json.dumps(stats, sort_keys=True)
        if self.first_wall is not None:
            # the wall time from the first to the last message taken: formation-analyze's real-time factor
            self.writer.custom_data["wall_time"] = repr(self.last_wall - self.first_wall)
        self.writer.close()
        return stats


def _unused(_msg: Any) -> None:  # the subscriptions are drained by Recorder.spin, not by an executor
    return None


@dataclass
class RecordPlan:
    """What to record, decided from the command line before anything starts."""

    known: dict[str, str]  # topics subscribed before they appear: {absolute name: type}
    only: list[str] | None  # --topics: exactly these
    step_topics: list[str]  # velocities and wrenches: the first one dates the recording
    decimate: list[tuple[str, int]]
    custom: dict[str, str]  # the bag's custom_data
    sim_log_time: bool


def plan_recording(args: argparse.Namespace) -> RecordPlan:
    """The topics, decimation, custom_data and log time of ``args`` (raises on a bad input)."""
    decimate = parse_decimation(args.decimate)
    custom = parse_meta(args.meta)
    known: dict[str, str] = {}
    step_topics: list[str] = []
    mode = custom.get("mode")
    if args.formation is not None:
        spec = load_formation(args.formation)
        mode = mode or spec.simulation.mode
        known = m.formation_topics(spec.agent_ids, [(e.tail, e.head) for e in spec.edges], args.namespace)
        custom.setdefault(KEY_FORMATION_YAML, args.formation.read_text(encoding="utf-8"))
        custom.setdefault(KEY_FORMATION_FILE, args.formation.name)
        step_topics = [
            m.absolute(f(a), args.namespace) for a in spec.agent_ids for f in (topics.velocity, topics.wrench)
        ]
    only = None
    if args.topics:
        only = [m.absolute(t, args.namespace) for t in args.topics]
        for t in only:
            k = m.classify(t, args.namespace)
            if k is not None and t not in known:
                known[t] = k.msgtype
        step_topics = [t for t in step_topics if t in only]
    sim_log_time = args.log_time == "sim" or (args.log_time == "auto" and mode == "lockstep")
    return RecordPlan(known, only, step_topics, decimate, custom, sim_log_time)


def record(args: argparse.Namespace, plan: RecordPlan, writer: SegmentedBagWriter) -> tuple[int, dict[str, Any]]:
    """Run the recorder node until SIGINT/SIGTERM and close the bag; returns (exit status, counts)."""
    # our own SIGINT/SIGTERM handlers: rclpy's would shut the context down at once, before the
    # messages already received are written
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # until the node exists: KeyboardInterrupt
    node = None
    stats: dict[str, Any] = {}
    code: int = ExitCode.PASS
    try:
        node = Recorder(
            writer,
            known=plan.known,
            only=plan.only,
            namespace=args.namespace,
            decimate=plan.decimate,
            sim_log_time=plan.sim_log_time,
            step_topics=plan.step_topics,
        )
        check_secure_transport()  # secure mode: refuse to record over a transport that fell back to UDP
        signal.signal(signal.SIGINT, node.request_stop)
        signal.signal(signal.SIGTERM, node.request_stop)
        print(
            f"formation-record: recording {node.topic_count} topics into {args.out} "
            f"(log time: {'simulation' if plan.sim_log_time else 'receive'})",
            flush=True,
        )
        code = spin_until_stopped(node, args)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except InsecureTransportError as exc:
        print(f"formation-record: {exc}", file=sys.stderr)
        code = ExitCode.INVALID
    finally:
        stats, closed = close_recording(node, writer, args.out)
        code = code if closed else ExitCode.INCOMPLETE
        rclpy.try_shutdown()
    return code, stats


def spin_until_stopped(node: Recorder, args: argparse.Namespace) -> int:
    """Record until stopped; INCOMPLETE if writing failed (full disk), else PASS."""
    try:
        node.spin(discovery_period=args.discovery_period, status_period=None if args.quiet else 5.0)
    except (OSError, BagError) as exc:
        print(f"formation-record: I/O error writing {args.out}: {exc}; recording stopped", file=sys.stderr)
        return ExitCode.INCOMPLETE
    except Exception:
        if node.context.ok():
            raise
        # a graph query or wait interrupted by SIGINT/SIGTERM (the context is shut down): a normal stop
    return ExitCode.PASS


def close_recording(node: Recorder | None, writer: SegmentedBagWriter, out: Path) -> tuple[dict[str, Any], bool]:
    """Close the bag (with the counts, if the node exists) and the node; returns (counts, closed cleanly)."""
    stats: dict[str, Any] = {}
    try:
        if node is not None:
            stats = node.finish()
        else:
            writer.close()
    except (BagError, OSError) as exc:
        print(f"formation-record: closing {out} failed: {exc}", file=sys.stderr)
        return stats, False
    finally:
        if node is not None:
            node.destroy_node()
    return stats, True


def report_recording(args: argparse.Namespace, writer: SegmentedBagWriter, stats: dict[str, Any], code: int) -> int:
    """Write ``--stats`` and print the closing lines; returns the exit status."""
    if args.stats is not None and stats:
        try:
            write_json(args.stats, stats)
        except OSError as exc:
            print(f"formation-record: could not write {args.stats}: {exc}", file=sys.stderr)
            code = ExitCode.INCOMPLETE
    rec, wr = sum(stats.get("received", {}).values()), sum(stats.get("written", {}).values())
    print(
        f"formation-record: closed {args.out}: {wr} messages written of {rec} received "
        f"on {len(stats.get('received', {}))} topics, {len(writer.segments)} files",
        flush=True,
    )
    if stats.get("missed_start"):
        print(f"formation-record: WARNING: {stats['missed_start']}", file=sys.stderr, flush=True)
    return code


@guarded("formation-record")
def main(argv: list[str] | None = None) -> int:
    args = record_parser().parse_args(argv)
    try:
        plan = plan_recording(args)
        writer = SegmentedBagWriter(
            args.out,
            storage=args.storage,
            segment_seconds=args.segment_seconds,
            segment_bytes=args.max_bag_size,
            custom_data=plan.custom,
        )
    except (BagError, FormationSpecError, OSError) as exc:
        print(f"formation-record: {exc}", file=sys.stderr)
        return ExitCode.INVALID
    code, stats = record(args, plan, writer)
    return report_recording(args, writer, stats, code)


if __name__ == "__main__":
    sys.exit(main())
