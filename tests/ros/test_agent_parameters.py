"""An agent's parameters through the rclpy parameter client: read-only, live, refused with a reason."""

from __future__ import annotations

import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from ros_helpers import PAPER, executable, read_log, ros_context
from rosgraph_msgs.msg import Clock

from formation_agent.agent_node import AgentNode, resolve_agent_id
from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions, qos
from formation_sim.core.simulation import Simulation

NS = 1_000_000_000


def test_agent_parameters_read_only_live_and_checked(procs, ros_env: dict[str, str], tmp_path) -> None:
    """Agent 5 from an all-agents params file: agent_id is read-only, gamma is live, gamma < 0 is refused."""
    params = tmp_path / "agents.yaml"
    params.write_text(
        f"/**:\n  ros__parameters:\n    formation_file: {PAPER}\n"
        "/agent_5/formation_agent:\n  ros__parameters:\n    gamma: 12.0\n"
        "/agent_4/formation_agent:\n  ros__parameters:\n    gamma: 99.0\n"
    )
    agent = procs.start(
        "agent_5", [executable("formation-agent"), "--ros-args", "--params-file", str(params), "-r", "__ns:=/agent_5"]
    )
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    with ros_context(ros_env) as context:
        node = Node("parameter_driver", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        client = AsyncParameterClient(node, "/agent_5/formation_agent")
        assert client.wait_for_services(timeout_sec=60), read_log(agent)

        def call(future):
            executor.spin_until_future_complete(future, timeout_sec=20)
            assert future.done(), "no answer from the parameter service"
            return future.result()

        def set_one(name: str, value) -> tuple[bool, str]:
            result = call(client.set_parameters([Parameter(name, value=value)])).results[0]
            return result.successful, result.reason

        got = call(client.get_parameters(["agent_id", "gamma", "formation_file"])).values
        assert (got[0].string_value, got[1].double_value, got[2].string_value) == ("5", 12.0, str(PAPER))
        ok, reason = set_one("agent_id", "2")
        assert not ok and "read-only" in reason, reason
        ok, reason = set_one("gamma", -1.0)
        assert not ok and "gamma" in reason and "-1.0 must be > 0" in reason, reason
        assert call(client.get_parameters(["gamma"])).values[0].double_value == 12.0

        clock = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
        vel = node.create_publisher(TwistStamped, topics.velocity("5"), qos.CONTROL)
        pose = node.create_publisher(PoseStamped, topics.relative_pose("5", "3"), qos.CONTROL)
        wrenches: dict[int, tuple[float, ...]] = {}
        codec = conversions.wrench_codec("5")

        def on_wrench(data: bytes) -> None:
            ns, u = codec.decode(data)
            wrenches[ns] = tuple(u)

        node.create_subscription(WrenchStamped, topics.wrench("5"), on_wrench, qos.CONTROL, raw=True)
        deadline = time.monotonic() + 60
        while not (vel.get_subscription_count() and pose.get_subscription_count() and clock.get_subscription_count()):
            assert time.monotonic() < deadline, read_log(agent)
            executor.spin_once(timeout_sec=0.1)
        time.sleep(1.0)
        p, R = meas.relative_poses["5"]["3"]
        v = meas.velocities[spec.agent_ids.index("5")].tolist()

        def step(ns: int) -> np.ndarray:
            clock.publish(conversions.clock_bytes(ns))
            pose.publish(conversions.relative_pose_codec("5").encode(ns, conversions.relative_pose_values(p, R)))
            vel.publish(conversions.twist_codec("5").encode(ns, v))
            end = time.monotonic() + 20
            while ns not in wrenches and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.1)
            assert ns in wrenches, read_log(agent)
            return np.array(wrenches[ns])

        u_12 = step(1 * NS)
        assert set_one("gamma", 24.0) == (True, "")
        u_24 = step(1 * NS + 1000)
        # the same measurements 1 µs later: ρ_v and ρ_e move by ~1e-7 relative, the wrench is ∝ γ
        assert np.linalg.norm(u_12) > 1e-5  # ~2e-4 at the first step: ρ_v0 = 2|e_v(0)| + 1 keeps ξ_v small
        np.testing.assert_allclose(u_24, 2.0 * u_12, rtol=1e-5)
        node.destroy_node()


ONE_AGENT = "/**:\n  ros__parameters:\n    agent_id: '3'\n    formation_file: {paper}\n    gamma: 7.5\n"
ALL_AGENTS = (
    "/**:\n  ros__parameters:\n    formation_file: {paper}\n"
    "/agent_3/formation_agent:\n  ros__parameters:\n    gamma: 12.0\n"
    "/agent_4/formation_agent:\n  ros__parameters:\n    gamma: 99.0\n"
)


@pytest.mark.parametrize(
    ("text", "extra", "gamma"),
    [(ONE_AGENT, [], 7.5), (ALL_AGENTS, ["-p", "agent_id:=3"], 12.0), (ALL_AGENTS, ["-r", "__ns:=/agent_3"], 12.0)],
    ids=["one-agent", "all-agents-by-id", "all-agents-by-namespace"],
)
def test_params_file_for_one_agent_and_for_all(ros_env: dict[str, str], tmp_path, text, extra, gamma) -> None:
    """--params-file: a file for one agent (/** with agent_id), or one for all with a section per
    agent, chosen by -p agent_id:=ID or by the namespace; the node is /agent_3/formation_agent."""
    params = tmp_path / "params.yaml"
    params.write_text(text.format(paper=PAPER))
    ros_args = ["--params-file", str(params), *extra]
    with ros_context(ros_env, ros_args) as context:
        node = AgentNode(resolve_agent_id(["formation-agent", "--ros-args", *ros_args], context), context=context)
        try:
            assert node.get_fully_qualified_name() == "/agent_3/formation_agent"
            assert (node.agent_id, node.get_parameter("gamma").value) == ("3", gamma)
        finally:
            node.destroy_node()
