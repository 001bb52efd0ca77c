"""The publisher watch without ROS: who is expected, who is reported, what is refused."""

from __future__ import annotations

import pytest

from formation_deploy.publisher_watch import (
    NAME_GRACE,
    UNKNOWN_NODE,
    Expected,
    PublisherInfo,
    PublisherWatch,
    expected_publishers,
    merge_security,
    untrusted_input,
)

SIM = PublisherInfo("formation_sim", "/", "aa01")
AGENT3 = PublisherInfo("formation_agent", "/agent_3", "bb03")
OUTSIDER = PublisherInfo("outsider", "/tools", "ee99")


def _watch(policy: str = "report") -> PublisherWatch:
    return PublisherWatch(expected_publishers(["1", "3"], [("1", "3"), ("3", "1")]), policy)  # type: ignore[arg-type]


def test_expected_publishers_follow_design_section_3() -> None:
    """The simulator publishes /clock, velocities and relative poses; agent i its own wrench."""
    exp = expected_publishers(["1", "3"], [("1", "3")])
    assert exp["/clock"] == Expected(("/formation_sim", "/formation_replay"), "all")
    assert exp["/agent_3/velocity"] == Expected(("/formation_sim", "/formation_replay"), "3")
    assert exp["/agent_1/relative_pose/agent_3"] == Expected(("/formation_sim", "/formation_replay"), "1")
    assert exp["/agent_3/wrench"] == Expected(("/agent_3/formation_agent",), "3")
    assert len(exp) == 6


def test_outsider_reported_once_with_node_name_and_gid() -> None:
    """A second publisher on agent 3's wrench is an intruder, reported once, its last sighting updated."""
    w = _watch()
    assert w.observe("/agent_3/wrench", [AGENT3], 1.0) == []
    new = w.observe("/agent_3/wrench", [AGENT3, OUTSIDER], 2.0)
    assert [(i.node, i.gid, i.agent, i.first_seen) for i in new] == [("/tools/outsider", "ee99", "3", 2.0)]
    assert w.observe("/agent_3/wrench", [AGENT3, OUTSIDER], 3.5) == []
    report = w.report()
    assert report["intruders_per_agent"] == {"3": 1}
    assert report["intruders"][0]["last_seen"] == 3.5  # type: ignore[index]


def test_impostor_with_the_expected_name_is_an_intruder_once_one_is_pinned() -> None:
    """The first lone publisher of the expected name is pinned by GID; a later namesake is reported."""
    w = _watch()
    w.observe("/agent_1/relative_pose/agent_3", [SIM], 0.0)
    impostor = PublisherInfo("formation_sim", "/", "cc77")
    new = w.observe("/agent_1/relative_pose/agent_3", [SIM, impostor], 0.2)
    assert [(i.gid, i.reason) for i in new] == [("cc77", "second publisher with the expected node name")]
    assert w.pinned["/agent_1/relative_pose/agent_3"] == "aa01"


def test_replay_stands_in_for_the_simulator_but_not_beside_it() -> None:
    """formation-replay alone is pinned for the measurements; joining a live simulator it is an intruder."""
    replay = PublisherInfo("formation_replay", "/", "ff42")
    alone = _watch()
    assert alone.observe("/agent_3/velocity", [replay], 0.0) == []
    assert alone.pinned["/agent_3/velocity"] == "ff42"
    live = _watch()
    live.observe("/agent_3/velocity", [SIM], 0.0)
    assert [i.node for i in live.observe("/agent_3/velocity", [SIM, replay], 0.2)] == ["/formation_replay"]


def test_two_namesakes_at_first_sight_are_both_intruders() -> None:
    """If two publishers claim the expected name before one is pinned, neither is trusted."""
    w = _watch()
    twin = PublisherInfo("formation_sim", "/", "cc77")
    new = w.observe("/clock", [SIM, twin], 0.0)
    assert {i.gid for i in new} == {"aa01", "cc77"}
    assert "/clock" not in w.pinned


def test_nameless_publisher_waits_for_its_name_then_is_reported() -> None:
    """An endpoint whose node name has not arrived yet is reported only after NAME_GRACE, from its first sighting."""
    w = _watch()
    w.observe("/agent_3/velocity", [SIM], 0.0)
    nameless = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "dd11")
    assert w.observe("/agent_3/velocity", [SIM, nameless], 1.0) == []
    new = w.observe("/agent_3/velocity", [SIM, nameless], 1.0 + NAME_GRACE)
    assert [(i.gid, i.first_seen) for i in new] == [("dd11", 1.0)]


def test_nameless_intruder_takes_its_name_when_it_arrives() -> None:
    """On a busy machine a name can arrive after NAME_GRACE: the report then names the node."""
    w = _watch()
    w.observe("/agent_3/velocity", [SIM], 0.0)
    nameless = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "ee99")
    w.observe("/agent_3/velocity", [SIM, nameless], 1.0)
    assert len(w.observe("/agent_3/velocity", [SIM, nameless], 1.0 + NAME_GRACE)) == 1
    assert w.observe("/agent_3/velocity", [SIM, OUTSIDER], 2.0 + NAME_GRACE) == []  # not a second intruder
    (intruder,) = w.intruders.values()
    assert (intruder.node, intruder.gid, intruder.last_seen) == ("/tools/outsider", "ee99", 2.0 + NAME_GRACE)


def test_expected_publisher_named_late_is_pinned_not_reported() -> None:
    """The simulator seen first without its name, then with it: pinned, never reported."""
    w = _watch()
    early = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "aa01")
    assert w.observe("/agent_3/velocity", [early], 0.0) == []
    assert w.observe("/agent_3/velocity", [SIM], 0.2) == []
    assert w.pinned["/agent_3/velocity"] == "aa01" and w.intruders == {}


def test_report_policy_accepts_everything() -> None:
    """Report-only never refuses a message, even with an intruder present."""
    w = _watch("report")
    w.observe("/agent_3/wrench", [AGENT3, OUTSIDER], 0.0)
    assert w.accept("/agent_3/wrench", 2)
    assert w.report()["refused_messages"] == {}


def test_refuse_policy_refuses_a_topic_while_an_intruder_is_there() -> None:
    """Refuse: messages are applied only from a lone pinned publisher; intruder present, unpinned or
    unclassified extra publishers are refused and counted."""
    w = _watch("refuse")
    topic = "/agent_3/wrench"
    assert not w.accept(topic, 1)  # nothing pinned yet: who sent it is unknown
    w.observe(topic, [AGENT3], 0.0)
    assert w.accept(topic, 1)
    assert not w.accept(topic, 2)  # matched a second publisher the poll has not seen yet
    w.observe(topic, [AGENT3, OUTSIDER], 0.2)
    assert not w.accept(topic, 1)
    w.observe(topic, [AGENT3], 0.4)  # the outsider left
    assert w.accept(topic, 1)
    assert w.report()["refused_messages"] == {topic: 3}


def test_pinned_publisher_restarting_is_pinned_again() -> None:
    """When the pinned publisher leaves, the next lone publisher of the expected name is pinned."""
    w = _watch()
    w.observe("/agent_3/wrench", [AGENT3], 0.0)
    restarted = PublisherInfo("formation_agent", "/agent_3", "bb04")
    assert w.observe("/agent_3/wrench", [restarted], 1.0) == []
    assert w.pinned["/agent_3/wrench"] == "bb04"


def test_unknown_policy_is_refused_with_its_value() -> None:
    """A policy that is neither report nor refuse raises ValueError naming it."""
    with pytest.raises(ValueError, match="'block'"):
        PublisherWatch({}, "block")  # type: ignore[arg-type]


def test_expected_publisher_named_after_the_grace_is_withdrawn_and_pinned() -> None:
    """On a busy machine the simulator's name can come after NAME_GRACE: reported nameless, then
    withdrawn and pinned once named, so that ``refuse`` applies its messages again."""
    w = _watch("refuse")
    early = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "aa01")
    w.observe("/agent_3/velocity", [early], 0.0)
    assert len(w.observe("/agent_3/velocity", [early], NAME_GRACE)) == 1
    assert not w.accept("/agent_3/velocity", 1)
    assert w.observe("/agent_3/velocity", [SIM], 0.9) == []
    assert w.intruders == {} and w.pinned["/agent_3/velocity"] == "aa01"
    assert w.accept("/agent_3/velocity", 1)
    report = w.report()
    assert report["intruders"] == [] and report["refused_messages"] == {"/agent_3/velocity": 1}
    (late,) = report["withdrawn"]  # type: ignore[misc]
    assert (late["node"], late["first_seen"], late["last_seen"]) == ("/formation_sim", 0.0, 0.9)


def test_named_late_twin_of_a_pinned_publisher_stays_an_intruder() -> None:
    """A nameless endpoint that turns out to carry the expected name while the expected one is pinned
    is a second publisher with that name: still reported."""
    w = _watch("refuse")
    w.observe("/agent_3/velocity", [SIM], 0.0)
    twin = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "ff02")
    w.observe("/agent_3/velocity", [SIM, twin], 1.0)
    assert len(w.observe("/agent_3/velocity", [SIM, twin], 1.0 + NAME_GRACE)) == 1
    named = PublisherInfo("formation_sim", "/", "ff02")
    assert w.observe("/agent_3/velocity", [SIM, named], 2.0) == []
    assert list(w.intruders) == [("/agent_3/velocity", "ff02")] and w.withdrawn == []
    assert not w.accept("/agent_3/velocity", 2)


def test_report_policy_counts_what_it_applies_beside_an_intruder() -> None:
    """Report: messages taken while an intruder is present are counted as applied; before it, not."""
    w = _watch("report")
    topic = "/agent_3/wrench"
    w.observe(topic, [AGENT3], 0.0)
    assert w.accept(topic, 1)
    w.observe(topic, [AGENT3, OUTSIDER], 0.2)
    assert w.accept(topic, 1) and w.accept(topic, 1)
    assert w.report()["applied_while_intruder"] == {topic: 2}


def test_untrusted_input_names_every_intruder_with_its_counts() -> None:
    """No intruder: trusted (None); each intruder: node, GID, topic, messages applied and refused."""
    w = _watch("refuse")
    assert untrusted_input(w.report()) is None
    assert untrusted_input(None) is None
    w.observe("/agent_3/wrench", [AGENT3, OUTSIDER], 0.0)
    w.observe("/agent_1/relative_pose/agent_3", [SIM, PublisherInfo("spy", "/", "dd02")], 0.0)
    for _ in range(3):
        w.accept("/agent_3/wrench", 1)
    assert untrusted_input(w.report()) == (
        "untrusted input: 2 intruder(s) (policy refuse): "
        "node /tools/outsider gid ee99 on /agent_3/wrench (0 applied, 3 refused); "
        "node /spy gid dd02 on /agent_1/relative_pose/agent_3 (0 applied, 0 refused)"
    )


def test_sole_publisher_nameless_to_the_end_is_withdrawn_at_the_report() -> None:
    """A topic's only endpoint, whose node name never arrived, is the expected one: withdrawn, not untrusted."""
    w = _watch()
    nameless = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "bb03")
    w.observe("/agent_3/wrench", [nameless], 0.0)
    assert len(w.observe("/agent_3/wrench", [nameless], NAME_GRACE)) == 1  # reported during the run
    report = w.report()
    assert report["intruders"] == [] and untrusted_input(report) is None
    (withdrawn,) = report["withdrawn"]  # type: ignore[misc]
    assert withdrawn["gid"] == "bb03" and "nameless to the end" in withdrawn["reason"]


def test_nameless_beside_another_publisher_stays_an_intruder() -> None:
    """A nameless endpoint that ever shared its topic with another publisher is still reported at the end."""
    w = _watch()
    nameless = PublisherInfo(UNKNOWN_NODE, "_NODE_NAMESPACE_UNKNOWN_", "dd11")
    w.observe("/agent_3/wrench", [AGENT3, nameless], 0.0)
    w.observe("/agent_3/wrench", [AGENT3, nameless], NAME_GRACE)
    w.observe("/agent_3/wrench", [nameless], 2 * NAME_GRACE)  # the agent's endpoint gone: still not the only one ever
    assert [i["gid"] for i in w.report()["intruders"]] == ["dd11"]  # type: ignore[union-attr]


def _intruder(topic: str, gid: str, first_seen: float, agent: str = "3") -> dict[str, object]:
    return {
        "topic": topic,
        "agent": agent,
        "node": "/outsider",
        "gid": gid,
        "first_seen": first_seen,
        "last_seen": first_seen + 1.0,
        "reason": "not a process of the formation",
    }


def test_reports_of_several_watches_merge_into_one() -> None:
    """The simulator's and the agents' reports: every intruder once (earliest sighting), counts summed
    per topic, a withdrawal undone where another watch saw an intruder, None without a report."""
    pose = "/agent_3/relative_pose/agent_1"
    sim = {
        "policy": "report",
        "intruders": [_intruder("/agent_3/wrench", "g1", 2.0)],
        "refused_messages": {},
        "applied_while_intruder": {"/agent_3/wrench": 4},
        "withdrawn": [_intruder(pose, "g2", 1.0)],
    }
    agent3 = {
        "policy": "report",
        "intruders": [_intruder(pose, "g2", 5.4), _intruder("/agent_3/wrench", "g1", 1.5)],
        "refused_messages": {},
        "applied_while_intruder": {pose: 7},
        "withdrawn": [],
    }
    merged = merge_security([sim, None, agent3])
    assert merged is not None
    assert [(i["topic"], i["first_seen"]) for i in merged["intruders"]] == [("/agent_3/wrench", 1.5), (pose, 5.4)]
    assert merged["applied_while_intruder"] == {"/agent_3/wrench": 4, pose: 7}
    assert merged["intruders_per_agent"] == {"3": 2} and merged["withdrawn"] == []
    assert merge_security([None, None]) is None
