"""Helpers of the multi-process ROS 2 tests (imported by conftest and the tests)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from bin_helpers import executable
from process_hygiene import kill_hard, remove_segments, shm_segments  # noqa: F401 (re-exported)

REPO = Path(__file__).resolve().parents[2]
RUN_SH = REPO / "ros2_ws" / "run.sh"
PAPER = REPO / "config" / "paper_5agents.yaml"
REALTIME = REPO / "config" / "realtime_5agents_100hz.yaml"


def assert_equals_headless(
    trajectory: Path, duration: float, *, formation: Path = PAPER, record_rate: float = 10000.0
) -> dict:
    """A lockstep run of ``formation`` (default the paper preset) recorded at ``record_rate`` [Hz]
    (``trajectory.npz``) equals run_headless sampled alike: the same sample times, |Δe|, |Δψ| ≤ 1e-9
    (float round-off of the relative rotations' quaternion round trip, ~1e-13 in practice). Returns
    the headless arrays."""
    import numpy as np

    from formation_msgs_py.spec import load_formation
    from formation_sim.cli.headless import run_headless

    ros = np.load(trajectory)
    spec = load_formation(formation, overrides={"duration": duration, "record_rate": record_rate})
    ref = run_headless(spec, controller_mode="sampled").recorder.arrays()
    np.testing.assert_array_equal(ros["t"], ref["t"])
    assert np.max(np.abs(ros["e"] - ref["e"])) <= 1e-9
    assert np.max(np.abs(ros["psi"] - ref["psi"])) <= 1e-9
    return ref


@contextmanager
def ros_context(ros_env: dict[str, str], ros_args: Sequence[str] = ()) -> Iterator:
    """An rclpy context of the test itself in the test's domain (this host only), with ``ros_args``
    (e.g. ``-p name:=value`` for every node of the context); shut down and the environment restored
    on exit."""
    import rclpy

    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update({k: ros_env[k] for k in saved})
    context = rclpy.Context()
    rclpy.init(args=["test", "--ros-args", *ros_args] if ros_args else None, context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
        for k, value in saved.items():
            if value is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = value


#: the wrench an outsider forges in the intruder tests: 50 N along the body x axis
FORGED = (50.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def launch_beside_a_forger(cmd: Sequence[str], ros_env: dict[str, str], agent: str = "3") -> tuple[int, str, int]:
    """Run ``cmd`` (a formation-launch command line) while an outsider node answers each of ``agent``'s
    steps with :data:`FORGED` on its wrench topic, stamped like the step's velocity (the pending
    step's stamp, mostly before the agent answers). Returns (exit status, output, wrenches forged);
    the launch is stopped by its process group if it outlives the test's deadline."""
    from geometry_msgs.msg import TwistStamped, WrenchStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from formation_msgs_py import topics
    from formation_msgs_py.ros import conversions, qos

    launch = subprocess.Popen(
        list(cmd), env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    forged = 0
    try:
        with ros_context(ros_env) as context:
            node = Node("outsider", context=context)
            pub = node.create_publisher(WrenchStamped, topics.wrench(agent), qos.CONTROL)
            wrench, twist = conversions.wrench_codec(agent), conversions.twist_codec(agent)

            def forge(data: bytes) -> None:
                nonlocal forged
                pub.publish(wrench.encode(twist.decode(data)[0], FORGED))
                forged += 1

            node.create_subscription(TwistStamped, topics.velocity(agent), forge, qos.CONTROL, raw=True)
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
    return launch.returncode, log, forged


@dataclass
class Procs:
    """Processes started by one test; :meth:`stop_all` signals each PID's own process group."""

    env: dict[str, str]
    logdir: Path
    started: list[subprocess.Popen] = field(default_factory=list)

    def start(self, name: str, cmd: list[str], **kw) -> subprocess.Popen:
        log = open(self.logdir / f"{name}.log", "wb")
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True, **kw)
        log.close()
        proc.log_path = self.logdir / f"{name}.log"  # type: ignore[attr-defined]
        self.started.append(proc)
        return proc

    def agent(self, formation: Path, agent_id: str, *params: str) -> subprocess.Popen:
        """An agent process; ``params`` are more ``NAME:=VALUE`` parameters."""
        cmd = [executable("formation-agent"), "--ros-args", "-p", f"formation_file:={formation}"]
        cmd += ["-p", f"agent_id:='{agent_id}'", *(x for p in params for x in ("-p", p))]
        return self.start(f"agent_{agent_id}", cmd)

    def sim(self, formation: Path, out: Path, *extra: str) -> subprocess.Popen:
        return self.start("sim", [executable("formation-sim"), str(formation), "--out", str(out), "--no-plots", *extra])

    def stop_all(self) -> None:
        alive = [p for p in self.started if p.poll() is None]
        for sig, grace in ((signal.SIGINT, 5.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            for p in alive:
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + grace
            while time.monotonic() < deadline and any(p.poll() is None for p in alive):
                time.sleep(0.05)
            alive = [p for p in alive if p.poll() is None]
            if not alive:
                return


def read_log(proc: subprocess.Popen) -> str:
    return Path(proc.log_path).read_text(errors="replace")  # type: ignore[attr-defined]


def wait_for_line(proc: subprocess.Popen, needle: str, timeout: float) -> bool:
    """True once ``needle`` appears in the process's log (False on timeout or exit)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if needle in read_log(proc):
            return True
        if proc.poll() is not None:
            return needle in read_log(proc)
        time.sleep(0.1)
    return False


def processes_mentioning(text: str) -> list[int]:
    """PIDs of live processes whose command line contains ``text`` (used to find leftovers)."""
    found = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmdline = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (d / "stat").read_text().split(")")[-1].split()[0]
        except OSError:
            continue
        if text in cmdline and state != "Z":
            found.append(int(d.name))
    return found


def children_by_node(parent: int) -> dict[str, int]:
    """{agent_<id>: pid} of the agent processes started by ``parent`` (``-p agent_id:=ID``, from /proc)."""
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) != parent:
            continue
        for arg in cmd:
            if arg.startswith(b"agent_id:="):
                found["agent_" + arg.split(b":=", 1)[1].decode().strip("'\"")] = int(d.name)
    return found
