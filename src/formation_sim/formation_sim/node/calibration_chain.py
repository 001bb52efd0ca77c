"""The floor of a realtime run, for ``formation-check --calibrate``: a chain's messages with no work.

    python -m formation_sim.node.calibration_chain sim|agent:ID --agents N --rate HZ --ticks K --warmup W

One simulator process and one process per agent of a chain of N agents (ids ``c0`` … ``c{N-1}``)
exchange a realtime run's messages with its topics, QoS, CDR bytes and executor (rclpy's
EventsExecutor), as ``benchmarks/floor_bench.py --rate`` does: per tick the simulator publishes each
agent's relative poses and velocity, and ``/clock`` every ``--clock-every`` ticks; an agent answers
its wrench once its tick's messages are in. Each process prints one JSON line: its CPU [s]
(``getrusage``, every thread) and wall [s] over ``--ticks`` ticks after ``--warmup``, and the
messages it sent and took in that span.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from typing import Any

from formation_sim.capacity import chain_ids, chain_neighbours

#: an agent that hears no tick for this long [wall s] ends: its simulator is gone
IDLE_TIMEOUT_S = 60.0


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _node(name: str, sim_time: bool) -> Any:
    import rclpy
    from rclpy.parameter import Parameter

    rclpy.init()
    overrides = [Parameter("use_sim_time", Parameter.Type.BOOL, True)] if sim_time else []
    return rclpy.create_node(name, parameter_overrides=overrides)


def agent(agent_id: str, n: int, ticks: int, warmup: int, clock_every: int) -> dict[str, Any]:
    """Take each tick's messages, answer the wrench; CPU over ``ticks`` ticks after ``warmup``."""
    from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
    from rclpy.experimental import EventsExecutor

    from formation_msgs_py import topics
    from formation_msgs_py.codec import stamp_of
    from formation_msgs_py.ros import conversions, qos

    neighbours = chain_neighbours(n)[agent_id]
    node = _node(f"floor_{agent_id}", sim_time=clock_every > 0)
    wrench = conversions.wrench_codec(agent_id)
    pub = node.create_publisher(WrenchStamped, topics.wrench(agent_id), qos.CONTROL)
    need = len(neighbours) + 1
    st = {"ns": -1, "got": 0, "ticks": 0, "cpu0": 0.0, "wall0": 0.0}
    zero = (0.0,) * 6

    def on_message(data: bytes) -> None:
        ns = stamp_of(data)
        if ns != st["ns"]:
            st["ns"], st["got"] = ns, 0
        st["got"] += 1
        if st["got"] == need:
            pub.publish(wrench.encode(ns, zero))
            st["ticks"] += 1
            if st["ticks"] == warmup:
                st["cpu0"], st["wall0"] = _cpu_s(), time.monotonic()

    subs = [node.create_subscription(TwistStamped, topics.velocity(agent_id), on_message, qos.CONTROL, raw=True)]
    for j in neighbours:
        subs.append(
            node.create_subscription(PoseStamped, topics.relative_pose(agent_id, j), on_message, qos.CONTROL, raw=True)
        )
    executor = EventsExecutor(context=node.context)
    executor.add_node(node)
    last = time.monotonic()
    while st["ticks"] < warmup + ticks:
        seen = st["ticks"]
        executor.spin_once(timeout_sec=1.0)
        if st["ticks"] != seen:
            last = time.monotonic()
        elif not node.context.ok() or time.monotonic() - last > IDLE_TIMEOUT_S:
            raise RuntimeError(f"floor agent {agent_id}: no tick for {IDLE_TIMEOUT_S:g} s (no simulator)")
    cpu, wall = _cpu_s() - st["cpu0"], time.monotonic() - st["wall0"]
    time.sleep(0.5)  # the simulator's last takes before this writer goes
    executor.shutdown()
    node.destroy_node()
    clock = ticks / clock_every if clock_every else 0.0
    return {"cpu_s": cpu, "wall_s": wall, "messages": ticks * (need + 1) + clock}


def simulator(n: int, ticks: int, warmup: int, rate: float, clock_every: int) -> dict[str, Any]:
    """Publish every tick's measurements on the wall clock at ``rate`` [Hz]; take the wrenches."""
    from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
    from rclpy.experimental import EventsExecutor
    from rosgraph_msgs.msg import Clock

    from formation_msgs_py import topics
    from formation_msgs_py.codec import stamp_of
    from formation_msgs_py.ros import conversions, qos

    node = _node("floor_sim", sim_time=False)
    ids = chain_ids(n)
    out: list[tuple[Any, Any, tuple[float, ...]]] = []
    pose = (1.0, 0.5, 0.25, 0.0, 0.0, 0.0, 1.0)
    for i, neighbours in chain_neighbours(n).items():
        for j in neighbours:
            pub = node.create_publisher(PoseStamped, topics.relative_pose(i, j), qos.CONTROL)
            out.append((pub, conversions.relative_pose_codec(i), pose))
        pub = node.create_publisher(TwistStamped, topics.velocity(i), qos.CONTROL)
        out.append((pub, conversions.twist_codec(i), (0.0,) * 6))
    clock_pub = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
    answered: dict[int, int] = {}

    def on_wrench(data: bytes) -> None:
        ns = stamp_of(data)
        answered[ns] = answered.get(ns, 0) + 1

    for i in ids:
        node.create_subscription(WrenchStamped, topics.wrench(i), on_wrench, qos.CONTROL, raw=True)
    executor = EventsExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 120.0
    while any(p.get_subscription_count() == 0 for p, _, _ in out) or any(
        node.count_publishers(topics.wrench(i)) == 0 for i in ids
    ):
        if time.monotonic() > deadline:
            raise RuntimeError("floor simulator: the agents did not match within 120 s")
        executor.spin_once(timeout_sec=0.05)
    time.sleep(1.0)  # the agents' side of discovery
    dt_ns = round(1e9 / rate)
    period = 1.0 / rate
    on_time, cpu0, wall0, t0 = 0, 0.0, 0.0, time.monotonic()
    for k in range(warmup + ticks + 1):
        ns = (k + 1) * dt_ns
        tick = t0 + k * period
        while (now := time.monotonic()) < tick:
            executor.spin_once(timeout_sec=tick - now)
            if not node.context.ok():
                raise RuntimeError("floor simulator: stopped")
        if k > warmup and answered.get(ns - dt_ns, 0) == n and now - tick < period / 2:
            on_time += 1
        if k == warmup:
            cpu0, wall0 = _cpu_s(), time.monotonic()
        if k == warmup + ticks:
            break
        for pub, codec, values in out:
            pub.publish(codec.encode(ns, values))
        if clock_every and k % clock_every == 0:
            clock_pub.publish(conversions.clock_bytes(ns))
        answered.pop(ns - 2 * dt_ns, None)
    cpu, wall = _cpu_s() - cpu0, time.monotonic() - wall0
    time.sleep(0.5)
    executor.shutdown()
    node.destroy_node()
    clock = ticks / clock_every if clock_every else 0.0
    return {
        "cpu_s": cpu,
        "wall_s": wall,
        "messages": ticks * (len(out) + n) + clock,
        "on_time_fraction": on_time / ticks,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("role", help="sim or agent:ID")
    p.add_argument("--agents", type=int, required=True)
    p.add_argument("--rate", type=float, required=True, help="tick rate [Hz]")
    p.add_argument("--ticks", type=int, required=True)
    p.add_argument("--warmup", type=int, required=True)
    p.add_argument("--clock-every", type=int, default=10, help="/clock every this many ticks (0: none)")
    a = p.parse_args(argv)
    if a.role == "sim":
        res = simulator(a.agents, a.ticks, a.warmup, a.rate, a.clock_every)
    else:
        res = agent(a.role.split(":", 1)[1], a.agents, a.ticks, a.warmup, a.clock_every)
    print(json.dumps(res), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
