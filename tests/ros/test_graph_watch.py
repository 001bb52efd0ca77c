"""GraphWatch polls: counts every topic, reads in full only what changed or is unsettled, and
every topic in turn (no ROS graph: a stand-in node answers the two graph queries)."""

from __future__ import annotations

from dataclasses import dataclass, field

from formation_deploy.graph_watch import FULL_PERIOD, POLL_PERIOD, GraphWatch
from formation_deploy.publisher_watch import PublisherWatch, expected_publishers


@dataclass
class Endpoint:
    node_name: str
    node_namespace: str
    endpoint_gid: bytes


@dataclass
class GraphNode:
    """The graph queries GraphWatch makes, answered from ``publishers``; counts the full reads."""

    publishers: dict[str, list[Endpoint]]
    reads: list[str] = field(default_factory=list)

    def create_timer(self, period: float, callback: object, clock: object = None) -> None:
        return None

    def count_publishers(self, topic: str) -> int:
        return len(self.publishers.get(topic, []))

    def get_publishers_info_by_topic(self, topic: str) -> list[Endpoint]:
        self.reads.append(topic)
        return list(self.publishers.get(topic, []))

    def get_logger(self) -> GraphNode:
        return self

    def error(self, text: str) -> None:
        pass


SIM = Endpoint("formation_sim", "/", b"\x01")
OUTSIDER = Endpoint("outsider", "/", b"\x99")


def test_a_settled_graph_is_read_in_full_once_per_full_period_and_a_change_at_once() -> None:
    expected = expected_publishers(["1", "2", "3"], [("1", "2"), ("2", "1"), ("2", "3"), ("3", "2")], clock=False)
    sim_topics = [t for t in expected if not t.endswith("/wrench")]
    graph = {t: [SIM] for t in sim_topics}
    graph.update({f"/agent_{a}/wrench": [Endpoint("formation_agent", f"/agent_{a}", bytes([a]))] for a in (2, 3, 4)})
    graph["/agent_1/wrench"] = [Endpoint("formation_agent", "/agent_1", b"\x11")]
    node = GraphNode(graph)
    seen = []
    watch = GraphWatch(node, PublisherWatch(expected), on_intruder=seen.append)  # type: ignore[arg-type]
    polls_per_full = round(FULL_PERIOD / POLL_PERIOD)
    assert polls_per_full == 5
    watch.poll()  # nothing pinned yet: every topic read
    assert len(node.reads) == len(expected) == 10
    node.reads.clear()
    for _ in range(polls_per_full):
        watch.poll()
    assert sorted(node.reads) == sorted(expected)  # settled: each topic once in five polls
    node.reads.clear()
    graph["/agent_2/velocity"] = [SIM, OUTSIDER]  # a second publisher: the count changes
    watch.poll()
    assert "/agent_2/velocity" in node.reads and [i.node for i in seen] == ["/outsider"]
    node.reads.clear()
    for _ in range(polls_per_full):  # an intruder present: that topic is read at every poll
        watch.poll()
    assert node.reads.count("/agent_2/velocity") == polls_per_full
    graph["/agent_3/velocity"] = [OUTSIDER]  # the simulator replaced, the count unchanged
    for _ in range(polls_per_full):
        watch.poll()
    assert [i.topic for i in seen] == ["/agent_2/velocity", "/agent_3/velocity"]


def test_refuse_reads_every_topic_at_every_poll_and_sees_a_swap_at_once() -> None:
    """Under ``refuse`` a publisher swapped with the count unchanged is seen at the next poll (not up to
    FULL_PERIOD later): its messages would be applied meanwhile."""
    expected = expected_publishers(["1", "2"], [("1", "2"), ("2", "1")], clock=False)
    graph = {t: [SIM] for t in expected if not t.endswith("/wrench")}
    graph.update({f"/agent_{a}/wrench": [Endpoint("formation_agent", f"/agent_{a}", bytes([a]))] for a in (1, 2)})
    node = GraphNode(graph)
    seen = []
    watch = GraphWatch(node, PublisherWatch(expected, "refuse"), on_intruder=seen.append)  # type: ignore[arg-type]
    for _ in range(3):
        watch.poll()
    assert len(node.reads) == 3 * len(expected)
    graph["/agent_1/velocity"] = [OUTSIDER]
    watch.poll()
    assert [i.topic for i in seen] == ["/agent_1/velocity"]
    assert not watch.watch.accept("/agent_1/velocity", 1)
