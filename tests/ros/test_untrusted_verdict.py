"""A lockstep run with an outsider forging agent 3's wrench is never PASS (nor a FAIL blamed on the
controller): INCOMPLETE, untrusted input, the verdict block naming the outsider by node and GID."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest
from geometry_msgs.msg import TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from ros_helpers import BIN, REALTIME, ros_context

from formation_msgs_py import topics
from formation_msgs_py.ros import conversions, qos


@pytest.mark.parametrize("policy", ["report", "refuse"])
def test_lockstep_run_with_a_forged_wrench_is_untrusted(ros_env: dict[str, str], tmp_path: Path, policy: str) -> None:
    """Lockstep, 1 s: an outsider answers each of agent 3's steps with 50 N stamped like agent 3's own. Report:
    exit 4; refuse: agent 3's own wrenches are refused, so it may stop answering (exit 3); either way the
    verdict is INCOMPLETE with the untrusted input named (node, GID, topic, counts) in summary and output."""
    out = tmp_path / "out"
    cmd = [str(BIN / "formation-launch"), str(REALTIME), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--mode", "lockstep", "--duration", "1", "--physics-rate", "100", "--intruder-policy", policy]
    cmd += ["--step-timeout", "2"]  # refuse: agent 3 counts as missing after 2 s, not the default's longer wait
    launch = subprocess.Popen(
        cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    try:
        with ros_context(ros_env) as context:
            node = Node("outsider", context=context)
            pub = node.create_publisher(WrenchStamped, topics.wrench("3"), qos.CONTROL)
            wrench, twist = conversions.wrench_codec("3"), conversions.twist_codec("3")
            force = [50.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            node.create_subscription(
                TwistStamped,
                topics.velocity("3"),
                lambda data: pub.publish(wrench.encode(twist.decode(data)[0], force)),
                qos.CONTROL,
                raw=True,
            )
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            deadline = time.monotonic() + 240
            while launch.poll() is None:
                assert time.monotonic() < deadline
                executor.spin_once(timeout_sec=0.05)
            node.destroy_node()
    finally:
        if launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
            launch.wait(timeout=60)
    log = launch.stdout.read().decode(errors="replace") if launch.stdout else ""
    assert launch.returncode in ((4,) if policy == "report" else (3, 4)), log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdict"] == "INCOMPLETE", log
    assert "untrusted input: " in summary["incomplete_reason"], summary["incomplete_reason"]
    gid = next(i["gid"] for i in summary["security"]["intruders"] if i["node"] == "/outsider")
    named = rf"^  intruder: node /outsider gid {gid} on /agent_3/wrench \(\d+ applied, \d+ refused\)$"
    assert re.search(named, log, re.M), log
