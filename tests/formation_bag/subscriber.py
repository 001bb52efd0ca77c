"""A small rclpy subscriber for the replay tests: ``python subscriber.py TOPIC TYPE N TIMEOUT``.

Prints "ready" once subscribed, then receives N messages (or gives up after TIMEOUT s) and
prints one JSON line: the receive times (s, time.perf_counter) and the raw message sizes.
"""

from __future__ import annotations

import importlib
import json
import sys
import time

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy


def main() -> int:
    topic, msgtype, n, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    pkg, _, name = msgtype.split("/")
    cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
    rclpy.init()
    node = rclpy.create_node("bag_test_subscriber")
    times: list[float] = []
    sizes: list[int] = []

    def callback(data: bytes) -> None:
        times.append(time.perf_counter())
        sizes.append(len(data))

    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(cls, topic, callback, qos, raw=True)
    print("ready", flush=True)
    deadline = time.monotonic() + timeout
    while len(times) < n and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({"times": times, "sizes": sizes}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
