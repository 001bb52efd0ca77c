"""One agent process driven by the test: wrench stamps, and simulation time restarting."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from ros_helpers import PAPER, read_log, ros_context, wait_for_line
from rosgraph_msgs.msg import Clock

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions, qos
from formation_sim.core.simulation import Simulation

NS = 1_000_000_000


def test_agent_answers_each_stamp_and_resets_when_clock_and_stamps_go_back(
    procs, ros_env: dict[str, str], tmp_path: Path
) -> None:
    """Agent 5 (one neighbour, 3): wrench stamped like its measurements; /clock going back with the
    measurements (a new run, or a replay's loop) resets it once, and the jump is counted."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    faults_file = tmp_path / "agent_5_faults.json"
    agent = procs.agent(PAPER, "5", f"faults_file:={faults_file}")
    with ros_context(ros_env) as context:
        node = Node("agent_driver", context=context)
        clock = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
        vel = node.create_publisher(TwistStamped, topics.velocity("5"), qos.CONTROL)
        pose = node.create_publisher(PoseStamped, topics.relative_pose("5", "3"), qos.CONTROL)
        got: list[int] = []
        codec = conversions.wrench_codec("5")
        node.create_subscription(
            WrenchStamped, topics.wrench("5"), lambda d: got.append(codec.decode(d)[0]), qos.CONTROL, raw=True
        )
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        deadline = time.monotonic() + 60
        while not (vel.get_subscription_count() and pose.get_subscription_count() and clock.get_subscription_count()):
            assert time.monotonic() < deadline, read_log(agent)
            time.sleep(0.1)
        time.sleep(1.0)
        p, R = meas.relative_poses["5"]["3"]
        v = meas.velocities[spec.agent_ids.index("5")].tolist()

        def step(ns: int) -> None:
            clock.publish(conversions.clock_bytes(ns))
            time.sleep(0.05)
            pose.publish(conversions.relative_pose_codec("5").encode(ns, conversions.relative_pose_values(p, R)))
            vel.publish(conversions.twist_codec("5").encode(ns, v))
            end = time.monotonic() + 10
            while ns not in got and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.1)

        step(10 * NS)
        step(10 * NS + 1_000_000)
        assert got[:2] == [10 * NS, 10 * NS + 1_000_000], got
        step(1 * NS)  # the clock and the stamps go back: a new run
        assert got[-1] == 1 * NS, got
        assert wait_for_line(agent, "clock jumped back", 10), read_log(agent)
        node.destroy_node()
    os.killpg(agent.pid, signal.SIGINT)
    agent.wait(timeout=30)
    faults = json.loads(faults_file.read_text())["5"]
    assert (faults["clock_jump"]["count"], faults["reset"]["count"]) == (1, 1), faults
    assert faults["reset"]["first"] == "/clock back to 1.000000 s, measurements at 1.000000 s after 10.001000 s"
