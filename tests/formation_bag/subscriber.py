"""A small rclpy subscriber for the replay tests: ``python subscriber.py TOPIC TYPE N TIMEOUT``.

Prints "ready" once subscribed, then receives N messages (or gives up after TIMEOUT s) and
prints one JSON line: the receive times (s; the rmw receive timestamps, taken by the DDS thread
when the message arrives, so Python's scheduling does not blur them), the message sizes and
header stamps.
"""

from __future__ import annotations

import importlib
import json
import struct
import sys
import time

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy


def main() -> int:
    topic, msgtype, n, timeout = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    pkg, _, name = msgtype.split("/")
    cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
    rclpy.init()
    node = rclpy.create_node("bag_test_subscriber")
    times: list[float] = []
    sizes: list[int] = []
    stamps: list[int] = []
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(cls, topic, lambda _m: None, qos, raw=True)
    print("ready", flush=True)
    deadline = time.monotonic() + timeout
    wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)
    while len(times) < n and time.monotonic() < deadline:
        wait_set.clear_entities()
        wait_set.add_subscription(sub.handle)
        wait_set.wait(50_000_000)
        while (got := sub.handle.take_message(cls, True)) is not None:
            data, info = got
            times.append(info["received_timestamp"] / 1e9)
            sizes.append(len(data))
            sec, nsec = struct.unpack_from("<iI", data, 4)  # header.stamp of a stamped message
            stamps.append(sec * 1_000_000_000 + nsec)
    print(json.dumps({"times": times, "sizes": sizes, "stamps": stamps}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
