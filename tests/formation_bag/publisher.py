"""A small rclpy publisher for the recorder tests: ``python publisher.py N RATE [--formation FILE]``.

Publishes N steps at RATE Hz (0 = as fast as possible): per step /clock, the ground truth and,
for every agent of the formation (default config/paper_5agents.yaml), its velocity and wrench
and every relative pose, all stamped k/1000 s. Prints "published N" per topic at the end as JSON.
Waits for a subscriber on every topic first (at most 10 s), and for every subscriber to
acknowledge step 0 before it publishes the others. BAG_TEST_BEST_EFFORT=1 publishes best effort.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy

from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions as cv

ROOT = Path(__file__).resolve().parents[2]


def main() -> int:
    n, rate = int(sys.argv[1]), float(sys.argv[2])
    spec = load_formation(sys.argv[4] if len(sys.argv) > 4 else ROOT / "config/paper_5agents.yaml")
    from geometry_msgs.msg import PoseArray, PoseStamped, TwistStamped, WrenchStamped
    from rosgraph_msgs.msg import Clock

    rclpy.init()
    node = rclpy.create_node("bag_test_publisher")
    # reliable with a deep history: on a loaded machine the project's keep-last-10 publishers may
    # overwrite samples before delivery; this publisher tests the recorder, so it loses nothing
    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    if os.environ.get("BAG_TEST_BEST_EFFORT"):  # as formation-sim --measurement-qos best-effort
        deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
    pubs = {topics.CLOCK: node.create_publisher(Clock, topics.CLOCK, deep)}
    pubs["/" + topics.GROUND_TRUTH] = node.create_publisher(PoseArray, topics.GROUND_TRUTH, deep)
    ids = list(spec.agent_ids)
    links = [(e.tail, e.head) for e in spec.edges] + [(e.head, e.tail) for e in spec.edges]
    for a in ids:
        pubs["/" + topics.velocity(a)] = node.create_publisher(TwistStamped, topics.velocity(a), deep)
        pubs["/" + topics.wrench(a)] = node.create_publisher(WrenchStamped, topics.wrench(a), deep)
    for i, j in links:
        name = topics.relative_pose(i, j)
        pubs["/" + name] = node.create_publisher(PoseStamped, name, deep)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in pubs.values()):
        time.sleep(0.02)
    from rclpy.duration import Duration

    rng = np.random.default_rng(1)
    p = np.array([a.position for a in spec.agents])
    R = np.array([a.R_world_body for a in spec.agents])
    counts = dict.fromkeys(pubs, 0)
    period = 0.0 if rate <= 0 else 1.0 / rate
    t0 = time.perf_counter()
    for k in range(n):
        t = k / 1000.0
        stamp = cv.stamp_from_seconds(t)
        pubs[topics.CLOCK].publish(cv.clock_msg(t))
        pubs["/" + topics.GROUND_TRUTH].publish(
            cv.ground_truth_bytes(k * 1_000_000, (p + 0.001 * k).tolist(), R.tolist())
        )
        for i, j in links:
            pi, pj = spec.agent(i).index, spec.agent(j).index
            msg = cv.relative_pose_to_msg(t, i, R[pi].T @ (p[pj] - p[pi]), R[pi].T @ R[pj])
            pubs["/" + topics.relative_pose(i, j)].publish(msg)
        for a in ids:
            pubs["/" + topics.velocity(a)].publish(cv.twist_to_msg(t, a, rng.standard_normal(6)))
            pubs["/" + topics.wrench(a)].publish(cv.wrench_to_msg(stamp, a, rng.standard_normal(6)))
        for key in counts:
            counts[key] += 1
        if k == 0:
            # step 0 stays in each reliable writer's history until acknowledged: once every
            # subscriber has acknowledged it, both sides of discovery are complete
            for pub in pubs.values():
                pub.wait_for_all_acked(Duration(seconds=60))
            if os.environ.get("BAG_TEST_BEST_EFFORT"):
                time.sleep(2.0)  # no acknowledgements in best effort: let the recorder switch and match
            t0 = time.perf_counter() - period
        if period:
            target = t0 + (k + 1) * period
            while time.perf_counter() < target:
                time.sleep(min(0.001, max(0.0, target - time.perf_counter())))
    for pub in pubs.values():  # reliable: stay until the subscribers have acknowledged everything
        pub.wait_for_all_acked(Duration(seconds=60))
    print(json.dumps(counts), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
