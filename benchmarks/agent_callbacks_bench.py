"""CPU of one agent's callbacks per step, in process, without DDS.

    .venv/bin/python benchmarks/agent_callbacks_bench.py [FORMATION] [--agent ID] [--steps N]

Builds the real :class:`formation_agent.agent_node.AgentNode` (parameters, input check, compiled
controller) with its wrench publisher replaced by a list, feeds it the CDR bytes a simulator would
send for N steps of the formation's open-loop motion (each step: the neighbours' relative poses,
then the velocity) and times the callbacks: ``time.process_time`` over the steps after a warm-up
of 200. Prints µs per step for the poses and for the velocity (which computes and publishes), and
a SHA-1 of every wrench sent, to compare two checkouts' outputs. Results in BENCHMARKS.md ("Lockstep ROS 2 runs").
"""

from __future__ import annotations

import argparse
import hashlib
import os
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
WARMUP = 200


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("formation", nargs="?", type=Path, default=REPO / "config" / "paper_5agents.yaml")
    p.add_argument("--agent", default="3", help="agent id (default 3)")
    p.add_argument("--steps", type=int, default=3000)
    args = p.parse_args()
    os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="agent_callbacks_bench."))

    import rclpy

    from formation_agent.agent_node import AgentNode
    from formation_core.formation import simulator_view
    from formation_core.spec import load_formation
    from formation_msgs_py import topics
    from formation_msgs_py.ros import conversions
    from formation_sim.core.simulation import Simulation

    path = args.formation.resolve()
    rclpy.init(args=["bench", "--ros-args", "-p", f"formation_file:={path}", "-p", "use_sim_time:=true"])
    try:
        spec = load_formation(path)
        node = AgentNode(args.agent)
        sent: list[bytes] = []
        node._pub.publish = lambda data: sent.append(bytes(data))  # no DDS: the bytes only
        sim = Simulation(simulator_view(spec))
        i = spec.agent_ids.index(args.agent)
        twist = conversions.twist_codec(args.agent)
        steps = []
        for k in range(WARMUP + args.steps):
            meas = sim.sense()
            ns = round(k * 1e9 / spec.simulation.control_rate)
            poses = []
            for j, (pj, Rj) in meas.relative_poses[args.agent].items():
                codec = conversions.relative_pose_codec(args.agent)
                data = codec.encode(ns, conversions.relative_pose_values(pj, Rj))
                poses.append((j, codec, "/" + topics.relative_pose(args.agent, j), data))
            steps.append((poses, twist.encode(ns, meas.velocities[i].tolist())))
            sim.advance(np.zeros((len(spec.agents), 6)))
        t_poses = t_velocity = 0.0
        clock = time.process_time
        for k, (poses, velocity) in enumerate(steps):
            a = clock()
            for j, codec, topic, data in poses:
                node._on_pose(j, codec, topic, data)
            b = clock()
            node._on_velocity(velocity)
            if k >= WARMUP:
                t_poses += b - a
                t_velocity += clock() - b
        n_poses = len(steps[-1][0])
        per_step = [1e6 * x / args.steps for x in (t_poses, t_velocity, t_poses + t_velocity)]
        digest = hashlib.sha1(b"".join(sent)).hexdigest()
        print(
            f"{path.name}, agent {args.agent} ({n_poses} neighbours), {args.steps} steps: "
            "poses {:.1f} µs, velocity (computes, publishes) {:.1f} µs, total {:.1f} µs per step; ".format(*per_step)
            + f"{len(sent)} wrenches, sha1 {digest[:16]}"
        )
        node.destroy_node()
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
