"""Discovery probe for the multi-host tests: ``talk`` publishes, ``listen`` waits for messages.

    python pingpong.py talk --listeners N [--timeout S]
    python pingpong.py listen [--count N] [--timeout S]

``talk`` publishes on ``/multihost/ping`` until N subscribers are matched and then 2 s more;
``listen`` exits 0 after N messages and --linger seconds more (so that the talker sees every
listener at once). Both exit 1 on time-out, with the reason on stderr.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String

TOPIC = "/multihost/ping"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("role", choices=["talk", "listen"])
    p.add_argument("--listeners", type=int, default=1, help="talk: subscribers to wait for")
    p.add_argument("--count", type=int, default=3, help="listen: messages to receive")
    p.add_argument("--timeout", type=float, default=30.0, help="give up after this many seconds")
    p.add_argument("--linger", type=float, default=3.0, help="listen: keep subscribed this long after the last message")
    args = p.parse_args(argv)
    rclpy.init()
    host = socket.gethostname()
    node = rclpy.create_node(f"pingpong_{args.role}")
    got: list[str] = []
    deadline = time.monotonic() + args.timeout
    try:
        if args.role == "talk":
            pub = node.create_publisher(String, TOPIC, 10)
            matched_at = None
            i = 0
            while time.monotonic() < deadline:
                pub.publish(String(data=f"ping {i} from {host}"))
                i += 1
                rclpy.spin_once(node, timeout_sec=0.05)
                if matched_at is None and pub.get_subscription_count() >= args.listeners:
                    matched_at = time.monotonic()
                    print(f"talk: {args.listeners} subscriber(s) matched", flush=True)
                if matched_at is not None and time.monotonic() - matched_at > 2.0:
                    return 0
            print(f"talk: only {pub.get_subscription_count()} of {args.listeners} subscribers", file=sys.stderr)
            return 1
        node.create_subscription(String, TOPIC, lambda m: got.append(m.data), 10)
        while time.monotonic() < deadline and len(got) < args.count:
            rclpy.spin_once(node, timeout_sec=0.1)
        if len(got) >= args.count:
            print(f"listen: got {got[-1]!r}", flush=True)
            linger = time.monotonic() + args.linger
            while time.monotonic() < linger:
                rclpy.spin_once(node, timeout_sec=0.1)
            return 0
        print(f"listen: {len(got)} of {args.count} messages before the time-out", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
