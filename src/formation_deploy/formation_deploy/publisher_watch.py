"""Who may publish what (docs/topics.md, docs/security.md), and the watch that reports everyone else
(no ROS import).

The formation expects exactly one publisher per topic: the simulator (or, replaying a bag in its
stead, formation-replay) for ``/clock``, relative poses and velocities, agent i for
``/agent_<i>/wrench``. A node feeds the watch what the ROS graph says (topic, node name, endpoint
GID); the watch pins the expected publisher by its GID the first time exactly one publisher of an
expected node name is seen, and reports every other publisher once, as an :class:`Intruder`,
with its node name and GID.

Policy ``report`` only reports. Policy ``refuse`` also refuses every message of a topic while it
has a publisher other than the pinned one: rclpy 7.1.6 does not give the publisher GID of a
taken message (its message info holds timestamps and sequence numbers only), so the message of
an intruder cannot be told from the expected one's and the topic as a whole is refused: a fail-safe
(the formation sees a missing measurement or wrench) instead of a command from an outsider.
Under ``report`` the messages a topic takes while an intruder is present are counted as applied
(any of them may be the intruder's).

Either way a run with an intruder is no evidence about the controller: :func:`untrusted_input`
turns the report into the reason of its INCOMPLETE verdict (``untrusted input``, exit 4), naming
every intruder with the messages applied or refused on its topic.

An endpoint is nameless until its participant's ROS node information arrives; after
:data:`NAME_GRACE` it is reported. If it then turns out to be the topic's one publisher with the
expected node name, the report is withdrawn (kept under ``withdrawn``) and it is pinned: on a busy
machine a name can take longer than the grace, and a refused simulator or agent would stop the run.
A name can also never arrive (seen about once in a few hundred runs on a loaded machine, most often
under TLS): an endpoint that stayed nameless for the whole run and was its topic's only publisher
from start to end is the expected one (the formation's own process is alive and publishes there, and
an outsider would be a second publisher), so its report is withdrawn when the watch reports
(:meth:`PublisherWatch.report`), with that reason.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from formation_msgs_py import topics

Policy = Literal["report", "refuse"]
POLICIES: tuple[Policy, ...] = ("report", "refuse")
#: Who a topic concerns, for ``/clock`` (every agent uses it).
ALL_AGENTS = "all"
#: The node name the rmw gives an endpoint until its participant's ROS node information arrives.
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
#: Wall seconds to wait for an endpoint's node name before reporting it as nameless (a raw DDS writer).
NAME_GRACE = 0.5


@dataclass(frozen=True)
class Expected:
    """The nodes (fully qualified names) of which one alone may publish on a topic, and the agent it concerns."""

    nodes: tuple[str, ...]
    agent: str


@dataclass(frozen=True)
class PublisherInfo:
    """One publisher endpoint as the ROS graph reports it."""

    node: str  # node name without namespace
    namespace: str
    gid: str  # endpoint GID, hex

    @property
    def qualified_node(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.node}"


@dataclass
class Intruder:
    """A publisher the formation does not expect; wall times from the watching node's clock [s]."""

    topic: str
    agent: str
    node: str
    gid: str
    first_seen: float
    last_seen: float
    reason: str

    def as_dict(self) -> dict[str, str | float]:
        return {
            "topic": self.topic,
            "agent": self.agent,
            "node": self.node,
            "gid": self.gid,
            "first_seen": self.first_seen,
            "last_seen": self.last_seen,
            "reason": self.reason,
        }


def expected_publishers(
    agent_ids: Sequence[str], links: Iterable[tuple[str, str]], *, clock: bool = True
) -> dict[str, Expected]:
    """The expected publisher of every topic (absolute name) of a formation, or of one agent's subscriptions.

    ``links`` are (observer, target) pairs of relative-pose topics; ``agent_ids`` get a velocity
    and a wrench topic each.
    """
    sim = ("/" + topics.SIM_NODE_NAME, "/" + topics.REPLAY_NODE_NAME)
    out: dict[str, Expected] = {}
    if clock:
        out[topics.CLOCK] = Expected(sim, ALL_AGENTS)
    for a in agent_ids:
        out["/" + topics.velocity(a)] = Expected(sim, a)
        out["/" + topics.wrench(a)] = Expected((topics.agent_node(a),), a)
    for observer, target in links:
        out["/" + topics.relative_pose(observer, target)] = Expected(sim, observer)
    return out


@dataclass
class PublisherWatch:
    """Classifies the publishers of the watched topics; counts intruders and refused messages."""

    expected: Mapping[str, Expected]
    policy: Policy = "report"
    pinned: dict[str, str] = field(default_factory=dict)
    intruders: dict[tuple[str, str], Intruder] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    #: messages accepted (``report``) while an intruder was present on their topic
    applied: dict[str, int] = field(default_factory=dict)
    #: nameless sightings withdrawn: the topic's expected publisher, whose name came late
    withdrawn: list[Intruder] = field(default_factory=list)
    _present: dict[str, set[str]] = field(default_factory=dict)
    #: every publisher GID ever seen per topic
    _seen: dict[str, set[str]] = field(default_factory=dict)
    _nameless_since: dict[tuple[str, str], float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.policy not in POLICIES:
            raise ValueError(f"intruder policy {self.policy!r} is not one of {', '.join(POLICIES)}")

    def observe(self, topic: str, publishers: Sequence[PublisherInfo], wall: float) -> list[Intruder]:
        """Record the publishers of ``topic`` seen at ``wall``; return the intruders seen for the first time."""
        exp = self.expected[topic]
        gids = {p.gid for p in publishers}
        self._seen.setdefault(topic, set()).update(gids)
        if self.pinned.get(topic) not in gids:  # never pinned, or the pinned one left (a restart)
            self.pinned.pop(topic, None)
            claimants = [
                p for p in publishers if p.qualified_node in exp.nodes and (topic, p.gid) not in self.intruders
            ]
            if len(claimants) == 1:
                self.pinned[topic] = claimants[0].gid
        pinned = self.pinned.get(topic)
        new: list[Intruder] = []
        present: set[str] = set()
        for p in publishers:
            if p.gid == pinned:
                continue
            present.add(p.gid)  # refused (under "refuse") from its first sighting, named or not
            key = (topic, p.gid)
            known = self.intruders.get(key)
            if known is not None:
                known.last_seen = wall
                if known.node != p.qualified_node and p.node != UNKNOWN_NODE:
                    known.node = p.qualified_node  # reported nameless; its name arrived since
                    if pinned is None and p.qualified_node in exp.nodes and len(publishers) == 1:
                        # the expected node, named after NAME_GRACE (a busy machine): it is the
                        # topic's one publisher, as when pinned on time; the report keeps the sighting
                        del self.intruders[key]
                        late = wall - known.first_seen
                        known.reason = f"the expected node, named {late:.3f} s after its first sighting"
                        self.withdrawn.append(known)
                        self.pinned[topic] = pinned = p.gid
                        present.discard(p.gid)
                continue
            first = wall
            if p.node == UNKNOWN_NODE:  # maybe the expected node, whose name has not arrived yet
                first = self._nameless_since.setdefault(key, wall)
                if wall - first < NAME_GRACE:
                    continue
                reason = "a publisher without a ROS node name"
            elif p.qualified_node in exp.nodes:
                reason = "second publisher with the expected node name"
            else:
                reason = "unexpected node"
            first = self._nameless_since.pop(key, first)
            intruder = Intruder(topic, exp.agent, p.qualified_node, p.gid, first, wall, reason)
            self.intruders[key] = intruder
            new.append(intruder)
        self._present[topic] = present
        return new

    def settled(self, topic: str) -> bool:
        """Whether ``topic``'s last observation showed its pinned publisher and nobody else."""
        return topic in self.pinned and not self._present.get(topic)

    def accept(self, topic: str, publisher_count: int) -> bool:
        """Whether to apply a message of ``topic`` taken now, given its matched publisher count.

        Under ``refuse``, a message is applied only while the topic's one matched publisher is the
        pinned one: a topic with an intruder present, without a pinned publisher yet, or with more
        matched publishers than the one expected (one the graph poll has not classified yet) is refused.
        """
        if self.policy == "report":
            if self._present.get(topic):
                self.applied[topic] = self.applied.get(topic, 0) + 1
            return True
        if self._present.get(topic) or topic not in self.pinned or publisher_count > 1:
            self.refused[topic] = self.refused.get(topic, 0) + 1
            return False
        return True

    def _withdraw_sole_nameless(self) -> None:
        """Withdraw the report of every nameless endpoint that was its topic's only publisher throughout."""
        for key, intruder in list(self.intruders.items()):
            topic, gid = key
            if UNKNOWN_NODE in intruder.node and topic not in self.pinned and self._seen.get(topic) == {gid}:
                del self.intruders[key]
                intruder.reason = "the topic's only publisher, nameless to the end: its node information never arrived"
                self.withdrawn.append(intruder)

    def report(self) -> dict[str, object]:
        """For summary.json: the policy, every intruder, counts per agent and refused messages per topic."""
        self._withdraw_sole_nameless()
        per_agent: dict[str, int] = {}
        for intruder in self.intruders.values():
            per_agent[intruder.agent] = per_agent.get(intruder.agent, 0) + 1
        return {
            "policy": self.policy,
            "intruders": [i.as_dict() for i in self.intruders.values()],
            "intruders_per_agent": per_agent,
            "refused_messages": dict(self.refused),
            "applied_while_intruder": dict(self.applied),
            "withdrawn": [i.as_dict() for i in self.withdrawn],
        }


def security_file(faults_file: str | os.PathLike[str]) -> Path:
    """Where a process that writes its faults to ``faults_file`` writes its :meth:`PublisherWatch.report`."""
    path = Path(faults_file)
    return path.with_name(f"{path.stem}_security.json")


def merge_security(reports: Sequence[Mapping[str, Any] | None]) -> dict[str, Any] | None:
    """One report of several watches' :meth:`PublisherWatch.report` (the simulator's and the agents'):
    every intruder once (by topic and GID, earliest first sighting), messages applied and refused
    summed per topic (each watch counts only the topics its node takes messages from), the first
    report's policy. None when there is no report."""
    present = [r for r in reports if isinstance(r, Mapping)]
    if not present:
        return None
    intruders: dict[tuple[str, str], dict[str, Any]] = {}
    withdrawn: dict[tuple[str, str], dict[str, Any]] = {}
    refused: dict[str, int] = {}
    applied: dict[str, int] = {}
    for report in present:
        for into, key in ((intruders, "intruders"), (withdrawn, "withdrawn")):
            for i in report.get(key) or []:
                k = (str(i.get("topic")), str(i.get("gid")))
                if k not in into or i.get("first_seen", math.inf) < into[k].get("first_seen", math.inf):
                    into[k] = dict(i)
        for counts, key in ((refused, "refused_messages"), (applied, "applied_while_intruder")):
            for topic, n in (report.get(key) or {}).items():
                counts[topic] = counts.get(topic, 0) + int(n)
    for k in intruders:
        withdrawn.pop(k, None)  # withdrawn by one watch, an intruder to another
    per_agent: dict[str, int] = {}
    for i in intruders.values():
        per_agent[str(i.get("agent"))] = per_agent.get(str(i.get("agent")), 0) + 1
    return {
        "policy": present[0].get("policy"),
        "intruders": list(intruders.values()),
        "intruders_per_agent": per_agent,
        "refused_messages": refused,
        "applied_while_intruder": applied,
        "withdrawn": list(withdrawn.values()),
    }


UNTRUSTED = "untrusted input"


def untrusted_input(security: Mapping[str, object] | None) -> str | None:
    """The INCOMPLETE reason of a run whose :meth:`PublisherWatch.report` is ``security``, or None
    when no intruder was seen.

    Any intruder makes the run's evidence untrusted: under ``report`` its messages were applied
    (rclpy cannot tell them from the expected publisher's), under ``refuse`` an agent's own messages
    were refused while it was there. Each intruder is named with its node, GID, topic and the
    messages applied or refused on that topic as this watch counted them (a topic the watching node
    does not subscribe to counts in the agent that does).
    """
    lines = intruder_lines(security)
    if not lines:
        return None
    assert security is not None
    return f"{untrusted_header(security)}: " + "; ".join(lines)


def untrusted_header(security: Mapping[str, object]) -> str:
    """``untrusted input: N intruder(s) (policy P)``: the reason without the intruders' names."""
    intruders = security.get("intruders") or []
    n = len(intruders) if isinstance(intruders, list) else 0
    return f"{UNTRUSTED}: {n} intruder(s) (policy {security.get('policy')})"


def intruder_lines(security: Mapping[str, object] | None) -> list[str]:
    """One line per intruder of a :meth:`PublisherWatch.report`: node, GID, topic, messages applied and refused."""
    intruders = (security or {}).get("intruders") or []
    refused = (security or {}).get("refused_messages") or {}
    applied = (security or {}).get("applied_while_intruder") or {}
    if not isinstance(intruders, list) or not isinstance(refused, Mapping) or not isinstance(applied, Mapping):
        return []
    return [
        f"node {i.get('node')} gid {i.get('gid')} on {i.get('topic')} "
        f"({applied.get(i.get('topic'), 0)} applied, {refused.get(i.get('topic'), 0)} refused)"
        for i in intruders
        if isinstance(i, Mapping)
    ]


def describe(intruder: Intruder) -> str:
    """One log line for an intruder."""
    return (
        f"intruder on {intruder.topic} (agent {intruder.agent}): node {intruder.node}, gid {intruder.gid} "
        f"({intruder.reason})"
    )
