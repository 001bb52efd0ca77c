"""An outsider process for the secure-mode test: publishes a wrench on /agent_3/wrench (FORCE_X N,
stamped STAMP_S: a far-future stamp makes the simulator hold it as agent 3's latest command),
subscribes to /agent_3/velocity, and once STOPFILE exists prints as JSON which formation topics
its graph showed, how many velocities it received and how many subscribers its wrench matched.

    python secure_outsider.py NAME STOPFILE FORCE_X STAMP_S   (transport from the environment)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import rclpy
from geometry_msgs.msg import TwistStamped, WrenchStamped
from rclpy.node import Node

from formation_msgs_py.ros import qos


def main() -> None:
    name, stopfile, force_x, stamp_s = sys.argv[1], Path(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
    rclpy.init()
    node = Node(name)
    pub = node.create_publisher(WrenchStamped, "/agent_3/wrench", qos.CONTROL)
    received = [0]
    node.create_subscription(TwistStamped, "/agent_3/velocity", lambda _m: received.__setitem__(0, received[0] + 1), 10)
    msg = WrenchStamped()
    msg.header.stamp.sec = stamp_s
    msg.wrench.force.x = force_x
    seen: set[str] = set()
    while not stopfile.exists():
        pub.publish(msg)
        rclpy.spin_once(node, timeout_sec=0.05)
        seen |= {t for t, _ in node.get_topic_names_and_types() if t.startswith(("/agent_", "/formation", "/clock"))}
    seen -= {"/agent_3/wrench", "/agent_3/velocity"}  # its own endpoints
    matched = pub.get_subscription_count()
    print(json.dumps({"name": name, "seen": sorted(seen), "received": received[0], "matched": matched}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
