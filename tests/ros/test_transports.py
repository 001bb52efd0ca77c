"""A run's processes talk UDP only: no Fast DDS shared memory, whatever the discovery (docs/ros2.md,
"Transports"). A default launch maps no /dev/shm file and equals the headless run; a process of the
rmw's own LOCALHOST (shared memory and UDP) still receives the run's messages."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

from process_hygiene import live_descendants, shm_segments
from ros_helpers import PAPER, REPO, assert_equals_headless, executable, ros_context

REALTIME = REPO / "config" / "realtime_5agents_100hz.yaml"


def test_a_default_launch_uses_no_shared_memory_and_equals_headless(ros_env: dict[str, str], tmp_path: Path) -> None:
    """LOCALHOST (the tests' range) becomes UDP on 127.0.0.1: while the paper run steps, none of its
    processes maps a /dev/shm file; summary.json names the transport; the trajectory is the headless one."""
    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--duration", "0.08", "--record-rate", "10000"]
    launch = subprocess.Popen(
        cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    seen: set[str] = set()
    watched: set[int] = set()
    stop = threading.Event()

    def watch() -> None:
        while not stop.wait(0.1):
            pids = list(live_descendants(launch.pid))
            watched.update(pids)
            seen.update(str(f) for pid in pids for f in shm_segments(pid, ports=True))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        text = launch.communicate(timeout=240)[0].decode()
    finally:
        stop.set()
        watcher.join()
        if launch.poll() is None:
            os.killpg(launch.pid, signal.SIGINT)
            launch.wait(timeout=30)
    assert launch.returncode == 0, text
    assert len(watched) >= 6  # the simulator and the five agents were among the processes looked at
    assert seen == set()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["launch"]["transport"] == "UDP on 127.0.0.1 only (fastdds_loopback.xml)"
    assert summary["launch"]["discovery_range"] == "SYSTEM_DEFAULT"
    assert_equals_headless(out / "trajectory.npz", 0.08)


def test_a_plain_localhost_process_hears_a_realtime_run(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A subscriber of the rmw's own LOCALHOST (this test process: shared memory and UDP) receives the
    velocities of a run whose processes use the loopback profile."""
    from geometry_msgs.msg import TwistStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    out = tmp_path / "out"
    cmd = [executable("formation-launch"), str(REALTIME), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--duration", "4"]
    heard: list[float] = []
    with ros_context(ros_env) as context:
        node = Node("localhost_listener", context=context)
        node.create_subscription(TwistStamped, "/agent_1/velocity", lambda m: heard.append(m.twist.linear.x), 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        launch = subprocess.Popen(
            cmd, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            deadline = time.monotonic() + 180
            while launch.poll() is None and len(heard) < 20 and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.1)
        finally:
            executor.shutdown()
            node.destroy_node()
            if launch.poll() is None:
                os.killpg(launch.pid, signal.SIGINT)
            text = launch.communicate(timeout=60)[0].decode()
    assert len(heard) >= 20, text
