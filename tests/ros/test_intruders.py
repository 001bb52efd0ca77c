"""Intruder detection in an agent process: an outsider's publishers are reported by node name within
1 s, and under ``intruder_policy:=refuse`` none of its measurements reaches the controller."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from ros_helpers import PAPER, REALTIME, executable, launch_beside_a_forger, read_log, ros_context
from rosgraph_msgs.msg import Clock

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions, qos
from formation_sim.core.simulation import Simulation

NS = 1_000_000_000
#: an intruder is reported within this many wall seconds of its publisher's creation
REPORT_WITHIN = 1.0


def _reported_at(proc, topic: str, node: str, deadline: float) -> float | None:
    """Wall time (monotonic) at which the agent's log names ``node`` as intruder on ``topic``."""
    pattern = re.compile(rf"intruder on {re.escape(topic)} .*node /{node}, gid [0-9a-f]+")
    while time.monotonic() < deadline:
        if pattern.search(read_log(proc)):
            return time.monotonic()
        time.sleep(0.02)
    return None


@pytest.mark.parametrize("policy", ["report", "refuse"])
def test_agent_reports_an_outsider_and_refuses_its_measurements(procs, ros_env: dict[str, str], policy: str) -> None:
    """Outsider on /agent_3/wrench and /agent_3/relative_pose/agent_1: named by agent 3 within 1 s; under
    refuse, no wrench answers the measurements it then plays."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    agent = procs.start(
        "agent_3",
        [
            executable("formation-agent"),
            "--ros-args",
            "-p",
            f"formation_file:={PAPER}",
            "-p",
            "agent_id:='3'",
            "-p",
            f"intruder_policy:={policy}",
        ],
    )
    with ros_context(ros_env) as context:
        node = Node("outsider", context=context)
        got: list[int] = []
        codec = conversions.wrench_codec("3")
        node.create_subscription(
            WrenchStamped, topics.wrench("3"), lambda d: got.append(codec.decode(d)[0]), qos.CONTROL, raw=True
        )
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        # participants discovered both ways (the agent's diagnostics reach us): what is timed below is
        # the report of new publishers, not the first discovery of a participant
        diagnostics = node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, lambda _m: None, qos.DIAGNOSTICS)
        deadline = time.monotonic() + 60
        while diagnostics.get_publisher_count() == 0:
            assert time.monotonic() < deadline and agent.poll() is None, read_log(agent)
            executor.spin_once(timeout_sec=0.1)
        time.sleep(0.5)
        created = time.monotonic()
        fake_wrench = node.create_publisher(WrenchStamped, topics.wrench("3"), qos.CONTROL)
        pose = node.create_publisher(PoseStamped, topics.relative_pose("3", "1"), qos.CONTROL)
        wrench_seen = _reported_at(agent, "/agent_3/wrench", "outsider", created + 10)
        pose_seen = _reported_at(agent, "/agent_3/relative_pose/agent_1", "outsider", created + 10)
        assert wrench_seen is not None and pose_seen is not None, read_log(agent)
        assert wrench_seen - created <= REPORT_WITHIN, (wrench_seen - created, read_log(agent))
        assert pose_seen - created <= REPORT_WITHIN, (pose_seen - created, read_log(agent))

        # the outsider now plays the simulator for agent 3: clock, pose, velocity stamped 7 s
        clock = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
        vel = node.create_publisher(TwistStamped, topics.velocity("3"), qos.CONTROL)
        deadline = time.monotonic() + 30
        while not (vel.get_subscription_count() and pose.get_subscription_count() and clock.get_subscription_count()):
            assert time.monotonic() < deadline, read_log(agent)
            time.sleep(0.1)
        fake_wrench.publish(codec.encode(1, [50.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
        p, R = meas.relative_poses["3"]["1"]
        pose_values = conversions.relative_pose_values(p, R)
        v = meas.velocities[spec.agent_ids.index("3")].tolist()
        stamp = 7 * NS
        end = time.monotonic() + 3.0
        while time.monotonic() < end and stamp not in got:
            clock.publish(conversions.clock_bytes(stamp))
            pose.publish(conversions.relative_pose_codec("3").encode(stamp, pose_values))
            vel.publish(conversions.twist_codec("3").encode(stamp, v))
            executor.spin_once(timeout_sec=0.2)
        if policy == "report":
            assert stamp in got, read_log(agent)  # the outsider's measurements were used: the threat is real
        else:
            assert stamp not in got, read_log(agent)  # no wrench answered the outsider's measurements
        node.destroy_node()


@pytest.mark.parametrize("policy", ["report", "refuse"])
def test_simulator_applies_an_outsiders_wrench_only_when_reporting(
    ros_env: dict[str, str], tmp_path: Path, policy: str
) -> None:
    """Realtime run with an outsider answering each of agent 3's velocities with 50 N on /agent_3/wrench
    (the same stamp: plausible): the simulator names it in summary.json; report applies its 50 N (the
    threat), refuse never does and counts what it refused; either way never PASS (nor a FAIL blamed on
    the controller): INCOMPLETE, untrusted input, exit 4, the verdict block naming the outsider."""
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(REALTIME), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    # the lag budget is not what this test is about: a loaded machine must not end the run INCOMPLETE
    cmd += ["--duration", "3", "--physics-rate", "100", "--intruder-policy", policy, "--lag-budget", "30"]
    code, log, _ = launch_beside_a_forger(cmd, ros_env)
    assert code == 4, log
    summary = json.loads((out / "summary.json").read_text())
    assert ("/agent_3/wrench", "/outsider") in {(i["topic"], i["node"]) for i in summary["security"]["intruders"]}
    assert summary["verdict"] == "INCOMPLETE" and summary["incomplete_reason"].startswith("untrusted input: "), log
    gid = next(i["gid"] for i in summary["security"]["intruders"] if i["node"] == "/outsider")
    assert re.search(
        rf"^  intruder: node /outsider gid {gid} on /agent_3/wrench \(\d+ applied, \d+ refused\)$", log, re.M
    ), log
    u = np.load(out / "trajectory.npz")["u"]
    applied = np.any(u[:, load_formation(REALTIME).agent_ids.index("3"), 0] == 50.0)
    if policy == "report":
        assert applied, log
        assert summary["security"]["applied_while_intruder"]["/agent_3/wrench"] > 0
    else:
        assert not applied, log
        assert summary["security"]["refused_messages"]["/agent_3/wrench"] > 0
