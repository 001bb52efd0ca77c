"""``formation-replay BAG``: publish a bag's messages with their recorded timing, and /clock.

Messages are published as the recorded CDR bytes (rclpy's ``Publisher.publish`` accepts
serialized data), each at ``t0 + (log_time − start) / rate`` on the wall clock (a coarse sleep,
then a short spin for sub-millisecond accuracy). ``/clock`` is replayed as recorded when the bag
has it; otherwise ``--clock-hz`` generates it from the bag's log time (as ``ros2 bag play --clock``).
Before starting, the node waits for subscribers (``--wait``), then until every subscription it
sees on its topics has matched its publishers and none has appeared for ``--wait-settle`` s, so
that a recorder started before it misses nothing (one that subscribes as it discovers the topics,
or one told the formation, which subscribes to the ground truth last); its reliable publishers keep
a history of at least :data:`PUBLISHER_DEPTH` messages, so a matched subscriber on a busy machine
loses nothing either. Then it shows progress once a second on stderr. ``--foxglove [HOST:]PORT``
serves the replayed display topics to a live view as well (:mod:`formation_bag.foxglove_server`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import QosDurability, QosHistory, QosReliability

from formation_bag import messages as m
from formation_bag.foxglove_server import DEFAULT_RATE, SUBPROTOCOL, LiveView, LiveViewError, display_topics
from formation_bag.parsers import replay_parser
from formation_bag.reader import Bag
from formation_bag.record_node import SUB_DEPTH, msg_class
from formation_core.errors import BagError, BagTopicError
from formation_msgs_py import topics
from formation_msgs_py.codec import clock_bytes
from formation_msgs_py.ros import qos as fqos

SPIN_BEFORE = 0.003  # s: sleep until this close to a deadline, then spin (scheduler wake-up latency)
#: least history of a reliable replay publisher: what a matched subscriber that is slow to take (or
#: whose side of discovery completes a little later) still gets from the writer's history, as the
#: recorder's subscription queues (formation_bag.record_node.SUB_DEPTH)
PUBLISHER_DEPTH = SUB_DEPTH
WAIT_POLL = 0.05  # s between two looks at the graph while waiting for subscribers


def deepened(profile: QoSProfile) -> QoSProfile:
    """``profile`` with a history of at least :data:`PUBLISHER_DEPTH` if it is reliable and keep-last.

    A publisher's depth is not part of QoS matching: subscribers match exactly as with the recorded
    profile."""
    if profile.reliability != ReliabilityPolicy.RELIABLE or profile.history != HistoryPolicy.KEEP_LAST:
        return profile
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(int(profile.depth), PUBLISHER_DEPTH),
        reliability=profile.reliability,
        durability=profile.durability,
    )


def to_rclpy_qos(profiles: Sequence[Any], topic: str) -> QoSProfile:
    """The first recorded offered QoS profile as an rclpy profile (the project's default if none),
    with the history of a replay publisher (:func:`deepened`)."""
    if topic == topics.CLOCK:
        return deepened(fqos.CLOCK)
    if not profiles:
        return deepened(fqos.CONTROL)
    q = profiles[0]
    return deepened(
        QoSProfile(
            history=HistoryPolicy.KEEP_ALL if q.history == QosHistory.KEEP_ALL else HistoryPolicy.KEEP_LAST,
            depth=max(1, int(q.depth)),
            reliability=ReliabilityPolicy.BEST_EFFORT
            if q.reliability == QosReliability.BEST_EFFORT
            else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if q.durability == QosDurability.TRANSIENT_LOCAL
            else DurabilityPolicy.VOLATILE,
        )
    )


def send_time(t0: float, log_time: int, t_first: int, rate: float) -> float:
    """When a message logged at ``log_time`` [ns] is published: t0 + Δlog / rate [wall s]."""
    return t0 + (log_time - t_first) / m.NS_PER_S / rate


def sleep_until(deadline: float) -> None:
    """Sleep until ``time.perf_counter() >= deadline`` (sub-ms accurate)."""
    while True:
        left = deadline - time.perf_counter()
        if left <= 0:
            return
        if left > SPIN_BEFORE:
            time.sleep(left - SPIN_BEFORE)


class Replayer(Node):
    def __init__(self, bag: Bag, selected: list[str], *, clock_hz: float, live: LiveView | None = None) -> None:
        super().__init__(topics.REPLAY_NODE_NAME)
        self.bag = bag
        infos = bag.topics
        self.live = live
        self.live_topics: frozenset[str] = frozenset()
        self.pubs: dict[str, Any] = {}
        #: relative poses of an older bag (TransformStamped): published as PoseStamped, what agents take
        self.convert: dict[str, str] = {}
        for name in selected:
            info = infos[name]
            msgtype = info.msgtype
            kind = m.classify(name)
            if msgtype == m.TRANSFORM_STAMPED and kind is not None and kind.kind == "relative_pose":
                self.convert[name] = kind.agent or ""
                msgtype = m.POSE_STAMPED
            self.pubs[name] = self.create_publisher(msg_class(msgtype), name, to_rclpy_qos(info.qos, name))
        self.clock_pub = None
        self.clock_hz = 0.0
        if topics.CLOCK not in self.pubs and clock_hz > 0:
            from rosgraph_msgs.msg import Clock

            self.clock_pub = self.create_publisher(Clock, topics.CLOCK, deepened(fqos.CLOCK))
            self.clock_hz = clock_hz
            self._Clock = Clock
        if live is not None:  # the display topics replayed, or generated (/clock)
            generated = {topics.CLOCK} if self.clock_pub is not None else set()
            served = {t: ty for t, ty in display_topics().items() if t in self.pubs or t in generated}
            live.open(served)
            self.live_topics = frozenset(served)

    def subscription_counts(self) -> dict[str, tuple[int, int]]:
        """Per topic published: (subscriptions the graph shows, subscriptions matched with our publisher)."""
        pubs = dict(self.pubs)
        if self.clock_pub is not None:
            pubs[topics.CLOCK] = self.clock_pub
        return {name: (self.count_subscribers(name), pub.get_subscription_count()) for name, pub in pubs.items()}

    def wait_for_subscribers(self, mode: str, timeout: float, settle: float) -> list[str]:
        """Wait until ``any``/``all`` topics have a subscriber, every subscription the graph shows on
        them has matched our publishers, and none appeared or matched for ``settle`` s (at most
        ``timeout`` s); returns what was still missing then (empty: ready).

        DDS delivers nothing published before both sides of a topic have matched. A recorder that
        subscribes as it discovers topics (every 0.5 s) or that subscribes to the ground truth last
        (``formation-record --formation``, 0.5 s after it matched the rest) adds subscriptions a
        moment after the first ones: each change starts the ``settle`` s again.
        """
        if mode == "none":
            return []
        check = any if mode == "any" else all
        deadline = time.monotonic() + timeout
        seen = self.subscription_counts()
        since = time.monotonic()
        while True:
            wanted = check(matched > 0 for _, matched in seen.values())
            unmatched = {t: (n, k) for t, (n, k) in seen.items() if k < n}
            now = time.monotonic()
            if wanted and not unmatched and now - since >= settle:
                return []
            if now >= deadline:
                if wanted:
                    missing = []
                elif mode == "any":
                    missing = ["no subscriber"]
                else:
                    missing = ["no subscriber on " + ", ".join(sorted(t for t, (_, k) in seen.items() if k == 0))]
                return missing + [f"{t}: {k} of {n} subscriptions matched" for t, (n, k) in sorted(unmatched.items())]
            time.sleep(WAIT_POLL)
            now_seen = self.subscription_counts()
            if now_seen != seen:
                seen, since = now_seen, time.monotonic()

    def play(
        self,
        *,
        rate: float,
        start: int | None,
        stop: int | None,
        progress: bool,
    ) -> int:
        """Publish once; returns the number of messages published."""
        t_first = start if start is not None else self.bag.start_time
        t_last = stop if stop is not None else self.bag.end_time
        span = max(1, t_last - t_first)
        t0 = time.perf_counter()
        count = 0
        next_progress = t0 + 1.0
        clock_period = None if not self.clock_hz else round(m.NS_PER_S / self.clock_hz)
        next_clock = t_first
        ok = self.context.ok
        if self.live is not None:
            self.live.rewind()
        for msg in self.bag.messages(self.pubs, start=start, stop=None if stop is None else stop + 1):
            if clock_period is not None and self.clock_pub is not None:  # both set by --clock
                while next_clock <= msg.log_time:
                    sleep_until(send_time(t0, next_clock, t_first, rate))
                    self.clock_pub.publish(self._Clock(clock=_time(next_clock)))
                    if self.live is not None:
                        self.live.send(topics.CLOCK, clock_bytes(next_clock), next_clock)
                    next_clock += clock_period
            sleep_until(send_time(t0, msg.log_time, t_first, rate))
            if not ok():
                break
            observer = self.convert.get(msg.topic)
            data = bytes(msg.data) if observer is None else m.pose_stamped_from_transform(msg.data, observer)
            self.pubs[msg.topic].publish(data)
            if msg.topic in self.live_topics:
                self.live.send(msg.topic, data, msg.log_time)  # type: ignore[union-attr]  # live_topics: with live
            count += 1
            if progress and time.perf_counter() >= next_progress:
                done = (msg.log_time - t_first) / span
                print(
                    f"formation-replay: {(msg.log_time - t_first) / 1e9:8.2f}/{span / 1e9:.2f} s "
                    f"({100 * done:5.1f} %), {count} messages",
                    file=sys.stderr,
                    flush=True,
                )
                next_progress += 1.0
        return count

    def wait_for_acks(self, timeout: float) -> None:
        """Reliable topics: stay until the subscribers acknowledged the last messages."""
        from rclpy.duration import Duration

        for pub in self.pubs.values():
            pub.wait_for_all_acked(Duration(nanoseconds=round(timeout * 1e9)))


def _time(ns: int) -> Any:
    from builtin_interfaces.msg import Time

    sec, nsec = divmod(ns, m.NS_PER_S)
    return Time(sec=sec, nanosec=nsec)


def main(argv: list[str] | None = None) -> int:
    args = replay_parser().parse_args(argv)
    if args.rate <= 0:
        print(f"formation-replay: --rate must be positive, got {args.rate}", file=sys.stderr)
        return 2
    try:
        bag = Bag(args.bag)
        available = bag.topics
        selected = list(available)
        if args.topics:
            selected = [m.absolute(t) for t in args.topics]
            missing = [t for t in selected if t not in available]
            if missing:
                raise BagTopicError(
                    f"bag {args.bag} has no topic {', '.join(missing)} (has: {', '.join(sorted(available))})"
                )
        for lost in bag.lost:
            print(f"formation-replay: warning: lost {lost}", file=sys.stderr)
    except BagError as exc:
        print(f"formation-replay: {exc}", file=sys.stderr)
        return 2
    start = None if args.start is None else bag.start_time + round(args.start * m.NS_PER_S)
    stop = None if args.end is None else bag.start_time + round(args.end * m.NS_PER_S)
    live = None
    if args.foxglove is not None:
        try:
            live = LiveView(args.foxglove, name="formation-replay", rate=DEFAULT_RATE)
        except LiveViewError as exc:
            print(f"formation-replay: {exc}", file=sys.stderr)
            bag.close()
            return 2
        print(f"formation-replay: live view on {live.url} (Foxglove WebSocket, {SUBPROTOCOL})", flush=True)
    rclpy.init(args=None)
    node = None
    try:
        node = Replayer(bag, selected, clock_hz=args.clock_hz, live=live)
        missing = node.wait_for_subscribers(args.wait, args.wait_timeout, args.wait_settle)
        if missing:
            print(
                f"formation-replay: after {args.wait_timeout:g} s still {'; '.join(missing)}; starting anyway",
                file=sys.stderr,
            )
        print(f"formation-replay: replaying {len(selected)} topics of {args.bag} at rate {args.rate:g}", flush=True)
        while True:
            n = node.play(rate=args.rate, start=start, stop=stop, progress=not args.quiet)
            node.wait_for_acks(5.0)
            print(f"formation-replay: published {n} messages", flush=True)
            if not args.loop or not node.context.ok():
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        bag.close()
        if live is not None:
            live.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
