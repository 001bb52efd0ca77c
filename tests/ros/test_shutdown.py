"""formation_ros.shutdown in a process of its own: SIGINT shuts the rclpy context down without a
KeyboardInterrupt, and exit_now ends the process with its code, skipping interpreter finalization
but not the closing of rclpy's log file."""

from __future__ import annotations

import sys
from pathlib import Path

from ros_helpers import read_log

PROBE = """
import atexit, os, signal, time
import rclpy
import rclpy.logging
from formation_ros import shutdown

shutdown.init(["probe"])
context = rclpy.get_default_context()
rclpy.logging.get_logger("probe").info("logged before the stop")
atexit.register(print, "finalized")  # interpreter finalization would print it
os.kill(os.getpid(), signal.SIGINT)
deadline = time.monotonic() + 30
while rclpy.ok() and time.monotonic() < deadline:
    time.sleep(0.01)  # Python runs its part of SIGINT here: no KeyboardInterrupt
print("context shut down:", not rclpy.ok(), flush=True)
shutdown.exit_now(7, context)
"""


def test_sigint_shuts_the_context_down_and_exit_now_skips_finalization(procs, ros_env: dict[str, str]) -> None:
    probe = procs.start("probe", [sys.executable, "-c", PROBE])
    assert probe.wait(timeout=60) == 7, read_log(probe)
    log = read_log(probe)
    assert "context shut down: True" in log, log
    assert "KeyboardInterrupt" not in log and "Traceback" not in log and "finalized" not in log, log
    ros_logs = [p.read_text() for p in Path(ros_env["ROS_LOG_DIR"]).glob("*.log")]
    assert len(ros_logs) == 1 and "logged before the stop" in ros_logs[0], ros_logs
