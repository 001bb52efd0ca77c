"""Bad messages published by a test into running processes: refused, counted, reported; nothing crashes."""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from ros_helpers import PAPER, REALTIME, read_log, ros_context, wait_for_line
from rosgraph_msgs.msg import Clock

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions, qos
from formation_sim.core.simulation import Simulation

NS = 1_000_000_000
#: what the first test sends agent 5 that it must refuse, by fault kind (the future step is a pose and a velocity)
REFUSED_COUNTS = {
    "refused_bad_quaternion": 2,
    "refused_non_finite": 2,
    "refused_out_of_range": 1,
    "refused_malformed": 1,
    "refused_future_stamp": 2,
}
IDENTITY_Q = (0.0, 0.0, 0.0, 1.0)


def _refused_wrenches(summary: dict) -> dict[str, dict[str, dict]]:
    """{agent: {kind: fault}} of the simulator's ``refused_wrench_<kind>`` faults in summary.json."""
    prefix = "refused_wrench_"
    out: dict[str, dict[str, dict]] = {}
    for agent, kinds in summary["faults"].items():
        for kind, fault in kinds.items():
            if kind.startswith(prefix):
                out.setdefault(agent, {})[kind.removeprefix(prefix)] = fault
    return out


@contextmanager
def injector_node(ros_env: dict[str, str]) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node of this test process in the run's domain, with its executor."""
    with ros_context(ros_env) as context:
        node = Node("bad_input_injector", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            yield node, executor
        finally:
            node.destroy_node()


def test_agent_refuses_bad_measurements_and_keeps_answering(procs, ros_env: dict[str, str], tmp_path: Path) -> None:
    """Agent 5 (neighbour 3) gets a zero quaternion, (0,0,0,2), a NaN pose, a 1e6 m pose, a NaN velocity
    and a pose from the future: zero wrench for the refused steps, nothing for the future stamp, a normal
    wrench for the next good step, and the process stays alive. Every refusal is counted by kind in
    the fault counts it writes when it stops (merged into summary.json by formation-launch)."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    faults_file = tmp_path / "agent_5_faults.json"
    agent = procs.agent(PAPER, "5", f"faults_file:={faults_file}")
    p, R = meas.relative_poses["5"]["3"]
    good = conversions.relative_pose_values(p, R)
    v = meas.velocities[spec.agent_ids.index("5")].tolist()
    with injector_node(ros_env) as (node, executor):
        clock = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
        vel = node.create_publisher(TwistStamped, topics.velocity("5"), qos.CONTROL)
        pose = node.create_publisher(PoseStamped, topics.relative_pose("5", "3"), qos.CONTROL)
        got: dict[int, tuple[float, ...]] = {}
        codec = conversions.wrench_codec("5")
        node.create_subscription(
            WrenchStamped, topics.wrench("5"), lambda d: got.__setitem__(*codec.decode(d)), qos.CONTROL, raw=True
        )
        deadline = time.monotonic() + 60
        while not (vel.get_subscription_count() and pose.get_subscription_count() and clock.get_subscription_count()):
            assert time.monotonic() < deadline, read_log(agent)
            time.sleep(0.1)
        time.sleep(1.0)
        pose_codec, vel_codec = conversions.relative_pose_codec("5"), conversions.twist_codec("5")

        def step(ns: int, pose_values, velocity, wait: float = 10.0, clock_ns: int = 0) -> tuple[float, ...] | None:
            clock.publish(conversions.clock_bytes(clock_ns or ns))
            time.sleep(0.05)
            pose.publish(pose_codec.encode(ns, pose_values))
            vel.publish(vel_codec.encode(ns, velocity))
            end = time.monotonic() + wait
            while ns not in got and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.1)
            return got.get(ns)

        base = 10 * NS
        assert any(step(base, good, v)), "a good step gets a non-zero wrench"
        bad = {
            "zero quaternion": ((*p, 0.0, 0.0, 0.0, 0.0), v),
            "non-unit quaternion": ((*p, 0.0, 0.0, 0.0, 2.0), v),
            "NaN pose": ((math.nan, *p[1:], *IDENTITY_Q), v),
            "1e6 m": ((1e6, 0.0, 0.0, *IDENTITY_Q), v),
            "NaN velocity": (good, [math.nan, *v[1:]]),
        }
        for k, (name, (pose_values, velocity)) in enumerate(bad.items(), start=1):
            u = step(base + k * 1_000_000, pose_values, velocity)
            assert u == (0.0,) * 6, (name, u, read_log(agent))
        # bytes that are no PoseStamped (anyone may publish raw CDR): dropped, counted, no crash
        pose.publish(b"\x00\x01\x00\x00garbage")
        # from the future: dropped (it names no step to answer), counted
        assert step((2**31 - 1) * NS, good, v, wait=1.0, clock_ns=base + 9_000_000) is None
        u = step(base + 10_000_000, good, v)
        assert u is not None and any(u) and all(math.isfinite(x) for x in u)
        assert agent.poll() is None, read_log(agent)
    os.killpg(agent.pid, signal.SIGINT)
    agent.wait(timeout=30)
    log = read_log(agent)
    for kind in ("bad_quaternion", "non_finite", "out_of_range", "future_stamp", "malformed"):
        assert f"refused ({kind}, " in log, log
    assert "Traceback" not in log
    faults = json.loads(faults_file.read_text())["5"]
    counts = {kind: c["count"] for kind, c in faults.items()}
    assert counts == REFUSED_COUNTS, (faults, log)
    quaternion = faults["refused_bad_quaternion"]
    assert (quaternion["first_t"], quaternion["last_t"]) == (10.001, 10.002), quaternion


def test_realtime_run_with_injected_faults_finishes_and_reports_them(procs, ros_env, tmp_path: Path) -> None:
    """The acceptance run: NaN pose, zero quaternion, 1e6 m translation into agent 1; a NaN wrench, a
    future-stamped wrench and bytes that are no wrench into the simulator. It runs its whole duration,
    reports each injection by agent and kind, and no applied wrench exceeds the actuator limits."""
    spec = load_formation(REALTIME)
    faults_file = tmp_path / "agent_1_faults.json"  # agent 1 counts what it refuses (counted, not sampled)
    agents = {a.id: procs.agent(REALTIME, a.id) for a in spec.agents if a.id != "1"}
    agents["1"] = procs.agent(REALTIME, "1", f"faults_file:={faults_file}")
    out = tmp_path / "out"
    sim = procs.sim(
        REALTIME, out, "--duration", "4", "--physics-rate", "100", "--progress-period", "0.2", "--lag-budget", "30"
    )

    with injector_node(ros_env) as (node, executor):
        latest = [0]
        node.create_subscription(
            Clock, topics.CLOCK, lambda m: latest.__setitem__(0, m.clock.sec * NS + m.clock.nanosec), qos.CLOCK
        )
        pose = node.create_publisher(PoseStamped, topics.relative_pose("1", "2"), qos.measurements("reliable"))
        wrench = node.create_publisher(WrenchStamped, topics.wrench("1"), qos.CONTROL)
        pose_codec, wrench_codec = conversions.relative_pose_codec("1"), conversions.wrench_codec("1")
        stop = threading.Event()

        def spin() -> None:
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.05)

        spinner = threading.Thread(target=spin)
        spinner.start()
        try:
            assert wait_for_line(sim, "progress t=", 120), read_log(sim)
            deadline = time.monotonic() + 60
            while latest[0] < NS // 2:  # half a second of sim time in
                assert time.monotonic() < deadline and sim.poll() is None, read_log(sim)
                time.sleep(0.05)
            # injections sent before agent 1 and the simulator matched the injector would be lost
            while pose.get_subscription_count() < 1 or wrench.get_subscription_count() < 1:
                assert time.monotonic() < deadline and sim.poll() is None, read_log(sim)
                time.sleep(0.05)
            for _ in range(3):  # a few times, spread over a second of the run
                ns = latest[0]
                pose.publish(pose_codec.encode(ns, (math.nan, 0.0, 0.0, *IDENTITY_Q)))
                pose.publish(pose_codec.encode(ns, (2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
                pose.publish(pose_codec.encode(ns, (1e6, 0.0, 0.0, *IDENTITY_Q)))
                wrench.publish(wrench_codec.encode(ns, (math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)))
                wrench.publish(wrench_codec.encode((2**31 - 1) * NS, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
                wrench.publish(b"\x00\x01\x00\x00garbage")
                time.sleep(0.3)
            code = sim.wait(timeout=120)
            os.killpg(agents["1"].pid, signal.SIGINT)  # agent 1 writes its fault counts when it stops
            agents["1"].wait(timeout=30)
        finally:
            stop.set()
            spinner.join(timeout=5)
    log = read_log(sim)
    # the injector is an intruder: no verdict on the controller (untrusted input, exit 4)
    assert code == 4, log
    assert "Traceback" not in log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["incomplete_reason"].startswith("untrusted input: "), summary["incomplete_reason"]
    assert "node /bad_input_injector" in summary["incomplete_reason"]
    assert summary["first_violation"] is None, log  # nothing refused is integrated: the funnels held
    assert summary["duration"] == 4.0, summary
    refused = _refused_wrenches(summary)
    rw = refused["1"]
    assert min(rw[k]["count"] for k in ("non_finite", "future_step", "malformed")) >= 1, rw
    assert rw["non_finite"]["first"] == "non-finite value", rw  # the reason, first and last
    assert set(refused) == {"1"}, refused
    # each of the three bad poses was sent three times, stamped with the latest /clock
    refused = {k: c["count"] for k, c in json.loads(faults_file.read_text())["1"].items() if k.startswith("refused_")}
    assert refused == {"refused_non_finite": 3, "refused_bad_quaternion": 3, "refused_out_of_range": 3}, refused
    u = np.load(out / "trajectory.npz")["u"]
    for i, a in enumerate(spec.agents):
        assert np.all(np.isfinite(u[:, i]))
        assert np.linalg.norm(u[:, i, :3], axis=1).max() <= a.dynamics.max_force * (1 + 1e-9)
        assert np.linalg.norm(u[:, i, 3:], axis=1).max() <= a.dynamics.max_torque * (1 + 1e-9)
        assert summary["agents"][a.id]["peak_force"] <= a.dynamics.max_force * (1 + 1e-9)


def test_lockstep_run_is_not_stalled_by_a_future_stamped_wrench(procs, ros_env, tmp_path: Path) -> None:
    """Lockstep: wrenches stamped 2³¹−1 s and NaN wrenches for agent 2 all through the run (once, one such
    wrench stalled the run and blamed the healthy agent): the run completes and reports them for agent 2."""
    spec = load_formation(REALTIME)
    out = tmp_path / "out"
    with injector_node(ros_env) as (node, executor):
        latest = [0]
        node.create_subscription(
            Clock, topics.CLOCK, lambda m: latest.__setitem__(0, m.clock.sec * NS + m.clock.nanosec), qos.CLOCK
        )
        wrench = node.create_publisher(WrenchStamped, topics.wrench("2"), qos.CONTROL)
        codec = conversions.wrench_codec("2")
        sim = procs.sim(REALTIME, out, "--mode", "lockstep", "--duration", "1", "--physics-rate", "100")
        # the simulator steps once the agents are matched: the injector must be matched before that,
        # or on a busy machine the 100 steps can be over before it is discovered
        deadline = time.monotonic() + 120
        while wrench.get_subscription_count() < 1:
            assert sim.poll() is None and time.monotonic() < deadline, read_log(sim)
            executor.spin_once(timeout_sec=0.05)
        for a in spec.agents:
            procs.agent(REALTIME, a.id)
        deadline = time.monotonic() + 180
        while sim.poll() is None:
            assert time.monotonic() < deadline, read_log(sim)
            executor.spin_once(timeout_sec=0.02)
            wrench.publish(codec.encode((2**31 - 1) * NS, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
            wrench.publish(codec.encode(latest[0], (math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)))
    log = read_log(sim)
    assert sim.returncode == 4, log  # the injector is an intruder: untrusted input
    summary = json.loads((out / "summary.json").read_text())
    assert summary["incomplete_reason"].startswith("untrusted input: "), summary["incomplete_reason"]
    assert summary["duration"] == 1.0 and summary["steps"] == 100, summary
    refused = _refused_wrenches(summary)
    assert refused["2"]["future_step"]["count"] >= 1, refused
    # a healthy agent may answer a re-sent step twice, the second time after the step was integrated
    others = {a: set(kinds) for a, kinds in refused.items() if a != "2"}
    assert all(kinds <= {"past_step"} for kinds in others.values()), refused
