"""The rclpy side of :mod:`formation_deploy.publisher_watch`: poll the ROS graph, log intruders.

A node creates one :class:`GraphWatch` for the topics it subscribes to (the simulator: every
topic of the formation). It polls the graph on a steady-clock timer (wall time, also under
``use_sim_time``), logs each new intruder once, and answers :meth:`accept` for every taken message
under the ``refuse`` policy. A report withdrawn (the expected node, named late) is logged as a warning.

Reading a topic's publishers (``get_publishers_info_by_topic``, ~40 µs and a Python object per
endpoint) for the ~80 topics of a 20-agent formation five times a second was 12 % of a realtime
simulator's CPU; counting them costs ~7 µs. So each poll counts, and reads in full only a topic
whose count changed or that is not settled (:meth:`PublisherWatch.settled`: its one expected
publisher pinned, nobody else); every topic is also read in full once per :data:`FULL_PERIOD`, a
share of them at each poll (a publisher replaced by another between two polls leaves the count
unchanged). Under the ``refuse`` policy every topic is read in full at every poll: there, a swap
seen 1 s late would let an outsider's messages through for up to 1 s, and the user chose security.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.subscription import Subscription

from formation_deploy.publisher_watch import Intruder, PublisherInfo, PublisherWatch, describe
from formation_ros.rclpy_internals import RCLError

#: Graph poll period [wall s]: an intruder is reported within this plus the discovery latency.
POLL_PERIOD = 0.2
#: Every topic's publishers are read in full at least this often [wall s].
FULL_PERIOD = 1.0


class GraphWatch:
    """Polls the publishers of ``watch.expected``'s topics (absolute names) for ``node``."""

    def __init__(
        self,
        node: Node,
        watch: PublisherWatch,
        *,
        period: float = POLL_PERIOD,
        on_intruder: Callable[[Intruder], None] | None = None,
    ) -> None:
        self.node = node
        self.watch = watch
        self.on_intruder = on_intruder
        self.counts: dict[str, int] = {}
        # topic k is read in full when polls % shares == k % shares (refuse: always)
        self.shares = 1 if watch.policy == "refuse" else max(1, round(FULL_PERIOD / period))
        self.polls = 0
        self.timer = node.create_timer(period, self.poll, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def poll(self) -> None:
        try:
            self._poll()
        except RCLError:
            if self.node.context.ok():
                raise
            # SIGINT/SIGTERM shut the context down (rclpy's handler): the node is stopping

    def _poll(self) -> None:
        now = time.monotonic()
        withdrawn = len(self.watch.withdrawn)
        share = self.polls % self.shares
        self.polls += 1
        for k, topic in enumerate(self.watch.expected):
            count = self.node.count_publishers(topic)
            if k % self.shares != share and count == self.counts.get(topic) and self.watch.settled(topic):
                continue
            self.counts[topic] = count
            infos = self.node.get_publishers_info_by_topic(topic)
            pubs = [PublisherInfo(i.node_name, i.node_namespace, bytes(i.endpoint_gid).hex()) for i in infos]
            for intruder in self.watch.observe(topic, pubs, now):
                self.node.get_logger().error(describe(intruder))
                if self.on_intruder is not None:
                    self.on_intruder(intruder)
        for late in self.watch.withdrawn[withdrawn:]:
            msg = f"{late.topic}: the nameless publisher reported is {late.node}, {late.reason}"
            self.node.get_logger().warning(msg)

    def accept(self, topic: str, subscription: Subscription) -> bool:
        """Whether to apply a message just taken from ``subscription`` of ``topic`` (see PublisherWatch.accept)."""
        if self.watch.policy == "report":
            return self.watch.accept(topic, 1)  # always True; counts what is applied beside an intruder
        return self.watch.accept(topic, subscription.get_publisher_count())
