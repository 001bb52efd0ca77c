"""Helpers of the multi-process ROS 2 tests (imported by conftest and the tests)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
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
    trajectory: Path,
    duration: float,
    *,
    formation: Path = PAPER,
    record_rate: float = 10000.0,
    overrides: dict | None = None,
    gains: dict | None = None,
) -> dict:
    """A lockstep run of ``formation`` (default the paper preset) recorded at ``record_rate`` [Hz]
    (``trajectory.npz``) equals run_headless sampled alike, bit for bit: the agents (compiled, on
    this machine) compute on the values the run core computes on (rotations through the messages'
    quaternions, the time of the stamps), and the simulator applies their answers only when they
    equal its witness's. ``overrides`` change the file's settings as the run's options did, ``gains``
    the agents' ({id: {"delta"|"gamma": value}}, as a parameters file did). Returns the headless arrays."""
    import numpy as np

    from formation_core.spec import load_formation
    from formation_sim.cli.headless import run_headless

    ros = np.load(trajectory)
    settings = {"duration": duration, "record_rate": record_rate, **(overrides or {})}
    spec = load_formation(formation, overrides=settings).with_agent_gains(gains or {})
    ref = run_headless(spec, controller_mode="sampled").recorder.arrays()
    for key in ("t", "p", "R", "v", "u", "e", "psi"):
        np.testing.assert_array_equal(ros[key], ref[key], err_msg=key)
    return ref


def faults_besides_resends(summary: dict) -> tuple[dict, dict[str, int]]:
    """(summary.json's faults without ``resent_step``, the resends per agent). A lockstep step is sent again
    when an agent's answer is late, which a busy machine makes happen (most often at the first step, while
    the processes still start): the step is integrated with the answer only, so the trajectory is unchanged
    (docs/outputs.md), but an agent that had answered the step without a neighbour's pose answers the resend
    again and counts ``missing_pose`` once more."""
    faults, resends = {}, {}
    for agent, kinds in summary["faults"].items():
        kinds = dict(kinds)
        resent = kinds.pop("resent_step", None)
        if resent is not None:
            resends[agent] = resent["count"]
        if kinds:
            faults[agent] = kinds
    return faults, resends


def run(cmd: Sequence[str], env: dict[str, str], timeout: float = 300.0) -> tuple[int, str]:
    """(exit status, stdout and stderr) of ``cmd`` started in its own process group; on a timeout the
    whole group it started is stopped (SIGINT, then SIGKILL) and the test fails naming the command."""
    proc = subprocess.Popen(
        list(cmd), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        for sig in (signal.SIGINT, signal.SIGKILL):
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                out, _ = proc.communicate(timeout=10)
                break
            except subprocess.TimeoutExpired:
                continue
        raise AssertionError(f"{cmd[0]} did not end within {timeout:g} s") from None
    return proc.returncode, out


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

    def start(self, name: str, cmd: list[str], env: dict[str, str] | None = None, **kw) -> subprocess.Popen:
        """``cmd`` in its own process group, its output in ``name``.log; ``env`` adds to the test's environment."""
        log = open(self.logdir / f"{name}.log", "wb")
        environment = {**self.env, **(env or {})}
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=environment, start_new_session=True, **kw
        )
        log.close()
        proc.log_path = self.logdir / f"{name}.log"  # type: ignore[attr-defined]
        self.started.append(proc)
        return proc

    def agent(
        self, formation: Path, agent_id: str, *params: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        """An agent process; ``params`` are more ``NAME:=VALUE`` parameters, ``env`` more environment. It runs
        the compiled controller, as formation-launch starts agents at 1 kHz and above (alone, an agent runs
        interpreted: its answers then equal an interpreted witness's, not the compiled headless run's)."""
        cmd = [executable("formation-agent"), "--ros-args", "-p", f"formation_file:={formation}"]
        cmd += ["-p", f"agent_id:='{agent_id}'", *(x for p in params for x in ("-p", p))]
        return self.start(f"agent_{agent_id}", cmd, {"NUMBA_DISABLE_JIT": "0", **(env or {})})

    def sim(self, formation: Path, out: Path, *extra: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        """The simulator; ``extra`` more options, ``env`` more environment."""
        cmd = [executable("formation-sim"), str(formation), "--out", str(out), "--no-plots", *extra]
        return self.start("sim", cmd, env)

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


def stacks(pid: int) -> str:
    """Every thread's native stack of process ``pid`` (gdb, where installed): what a process that
    does not end is waiting on. With PYTHONFAULTHANDLER=1 in its environment, SIGABRT afterwards
    adds its Python stacks to its log."""
    if shutil.which("gdb") is None:
        return "gdb is not installed: no stacks\n"
    cmd = ["gdb", "-p", str(pid), "-batch", "-nx", "-ex", "thread apply all bt"]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return f"gdb -p {pid}: no answer within 120 s\n"
    return r.stdout + r.stderr


# --- the intermittent failures (tests/ros/test_intermittent.py runs each many times) -----------------

#: how long a killed agent may take to be named: the step timeout (2 s), the last call and the writing of OUT
KILLED_AGENT_BOUND = 2 + 8


@dataclass
class KilledAgentRun:
    """One paper lockstep run (5 s, step timeout 2 s) in which agent ``victim`` was SIGKILLed mid-run."""

    victim: str
    #: the simulator's exit status; None: no progress before the kill, or still running 30 s after it
    code: int | None
    #: wall s from the kill to the simulator's exit (or to the end of the wait)
    elapsed: float
    log: str
    summary_written: bool
    started: bool

    def failures(self) -> list[str]:
        """What went wrong, one ``kind: detail`` item each (empty: the simulator named the agent in time)."""
        if not self.started:
            return ["no progress: the simulator printed no progress line within 90 s"]
        if self.code is None:
            return [f"timeout: the simulator still ran {self.elapsed:.1f} s after the kill"]
        found = []
        if self.code != 3:
            found.append(f"exit {self.code}: not 3")
        if f"no answer from agent {self.victim} " not in self.log:
            named = [line for line in self.log.splitlines() if "no answer" in line or "ERROR" in line]
            found.append(f"not named: {named[-1] if named else 'no ERROR line'}")
        if self.elapsed >= KILLED_AGENT_BOUND:
            found.append(f"slow: exit {self.elapsed:.1f} s after the kill (bound {KILLED_AGENT_BOUND} s)")
        if not self.summary_written:
            found.append("no summary: OUT/summary.json missing")
        return found


def lockstep_with_a_killed_agent(procs: Procs, out: Path, victim: str = "3") -> KilledAgentRun:
    """Start the paper formation's agents and simulator (lockstep, 5 s, step timeout 2 s), SIGKILL
    agent ``victim`` once the simulator reports progress and wait up to 30 s for the simulator; every
    process stopped afterwards. A simulator still running then leaves its native stacks in the log
    directory (stacks.txt) and is stopped by SIGABRT first."""
    from formation_core.spec import load_formation

    agents = {a.id: procs.agent(PAPER, a.id) for a in load_formation(PAPER).agents}
    sim = procs.sim(PAPER, out, "--duration", "5", "--step-timeout", "2", "--progress-period", "0.2")
    if not wait_for_line(sim, "progress t=", 90):
        return KilledAgentRun(victim, sim.poll(), 0.0, read_log(sim), False, started=False)
    left = kill_hard(agents[victim].pid)
    killed = time.monotonic()
    code: int | None
    try:
        code = sim.wait(timeout=30)
    except subprocess.TimeoutExpired:
        code = None
        (procs.logdir / "stacks.txt").write_text(stacks(sim.pid))
        os.kill(sim.pid, signal.SIGABRT)  # its Python stacks into its log, where PYTHONFAULTHANDLER is set
    elapsed = time.monotonic() - killed
    procs.stop_all()  # the other agents too: then nothing maps the victim's segments any more
    remove_segments(left)
    return KilledAgentRun(victim, code, elapsed, read_log(sim), (out / "summary.json").is_file(), started=True)


#: brings the namespace's loopback up, then runs the rest of the command line
_LO_UP = 'ip link set lo up && exec "$@"'
#: how long secure_driver.py may take: its launch's 240 s, then the stacks of a launch still running
SECURE_DRIVER_TIMEOUT = 420.0


@dataclass
class SecureOutsidersRun:
    """One run of tests/ros/secure_driver.py (a secure realtime launch beside four outsiders) in a
    private network namespace; its files (driver.log, launch.log, out/, stacks/ of a hung launch) in ``work``."""

    work: Path
    #: the driver's exit status; None: it did not end within SECURE_DRIVER_TIMEOUT
    code: int | None
    stdout: str
    stderr: str
    elapsed: float

    def result(self) -> dict | None:
        """The driver's JSON line (None if it printed none)."""
        import json

        lines = self.stdout.strip().splitlines()
        try:
            return json.loads(lines[-1]) if lines else None
        except json.JSONDecodeError:
            return None

    def describe(self) -> str:
        log = self.work / "launch.log"
        text = log.read_text(errors="replace") if log.is_file() else "(none)"
        return f"{self.stdout}{self.stderr}\n--- launch.log\n{text}"

    def failures(self) -> list[str]:
        """What went wrong, one ``kind: detail`` item each (empty: outsiders saw and commanded nothing,
        the member was connected and reported, and the run ended untrusted input, exit 4)."""
        import json

        import numpy as np

        from formation_core.spec import load_formation

        if self.code is None:
            return [f"driver timeout: still running {self.elapsed:.0f} s after its start"]
        result = self.result()
        if self.code != 0 or result is None:
            return [f"driver exit {self.code}: {(self.stderr or self.stdout).strip().splitlines()[-1:]}"]
        if result["launch"] is None:
            return [f"launch timeout: running at the driver's timeout: {sorted(result.get('hung', {}).values())}"]
        found = []
        if result["launch"] != 4:
            # the member's wrench publisher is an intruder: untrusted input, exit 4 (also over a funnel left
            # under heavy load); a process that died or an agent missing (3) is a failure
            found.append(f"launch exit {result['launch']}: not 4")
        for kind in ("plain", "nocert", "otherca"):
            report = result["outsiders"][kind]
            if report != {"name": f"outsider_{kind}", "seen": [], "received": 0, "matched": 0}:
                found.append(f"outsider {kind} reached the run: {report}")
        # the control: a member of the CA joins (sees the run's graph; the simulator reports its wrench
        # publisher below). How many velocities it got depends on when, under load, it finished joining.
        member = result["outsiders"]["member"]
        if member is None or "/agent_3/relative_pose/agent_1" not in member["seen"]:
            found.append(f"member not joined: {member}")
        summary_file = self.work / "out" / "summary.json"
        if not summary_file.is_file():
            return [*found, "no summary: out/summary.json missing"]
        summary = json.loads(summary_file.read_text())
        intruders = {(i["topic"], i["node"]) for i in (summary.get("security") or {}).get("intruders", [])}
        if intruders != {("/agent_3/wrench", "/outsider_member")}:
            # which agents' logs name the member: the summary merges the simulator's and the agents' reports
            logs = sorted((self.work / "out" / "logs").glob("agent_*.log"))
            seen_by = [log.stem for log in logs if "node /outsider_member" in log.read_text(errors="replace")]
            found.append(f"intruders: {sorted(intruders)} in the summary; the member in the logs of {seen_by}")
        reason = summary.get("incomplete_reason") or ""
        if not reason.startswith("untrusted input: 1 intruder(s)") or "node /outsider_member gid " not in reason:
            found.append(f"reason: {reason[:200]}")
        u = np.load(self.work / "out" / "trajectory.npz")["u"]
        agent3 = load_formation(REALTIME).agent_ids.index("3")
        if np.any(u[:, agent3, 0] == 50.0):
            found.append("forged wrench applied: u of agent 3 held an outsider's 50 N")
        return found


def secure_run_beside_outsiders(work: Path, domain: int) -> SecureOutsidersRun:
    """Run tests/ros/secure_driver.py WORK DOMAIN in a private network namespace (``unshare -n``: only a
    loopback, nothing leaves the machine); the driver is killed if it outlives SECURE_DRIVER_TIMEOUT."""
    driver = REPO / "tests" / "ros" / "secure_driver.py"
    cmd = ["unshare", "-n", "sh", "-c", _LO_UP, "sh", sys.executable, str(driver), str(work), str(domain)]
    started = time.monotonic()
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=SECURE_DRIVER_TIMEOUT, start_new_session=True)
    except subprocess.TimeoutExpired as exc:
        out, err = (x.decode(errors="replace") if isinstance(x, bytes) else x or "" for x in (exc.stdout, exc.stderr))
        run = SecureOutsidersRun(work, None, out, err, time.monotonic() - started)
    else:
        run = SecureOutsidersRun(work, r.returncode, r.stdout, r.stderr, time.monotonic() - started)
    (work / "driver.log").write_text(run.stdout + run.stderr)  # its JSON line: the outsiders' reports
    return run


@dataclass
class FortyAgentsRun:
    """One lockstep run of the random 40-agent formation at 1 kHz (0.05 s) in discovery-server mode,
    no network namespace: 42 processes (the server, the simulator, 40 agents) on one host."""

    formation: Path
    out: Path
    code: int | None
    text: str

    def failures(self) -> list[str]:
        """What went wrong, one ``kind: detail`` item each (empty: exit 0, every process ended by itself)."""
        if self.code is None:
            return ["timeout: formation-launch still ran after 600 s"]
        found = [] if self.code == 0 else [f"exit {self.code}: " + self.text.strip().splitlines()[-1][:200]]
        try:
            rows = json.loads((self.out / "logs" / "processes.json").read_text())
        except (OSError, ValueError):
            return [*found, "no processes.json"]
        killed = sorted(r["name"] for r in rows if r["returncode"] == -signal.SIGKILL)
        if killed:
            found.append(f"sigkill: {', '.join(killed)} did not stop within the grace")
        return found


def forty_agents_through_a_discovery_server(env: dict[str, str], work: Path) -> FortyAgentsRun:
    """Generate the random 40-agent formation into ``work`` and launch it (lockstep, 0.05 s, recorded
    at every step) with ``--discovery server --netns off``."""
    formation = work / "random40.yaml"
    gen = [executable("formation-generate"), "40", "--topology", "random", "--out", str(formation)]
    subprocess.run(gen, capture_output=True, text=True, timeout=120, check=True)
    out = work / "out"
    cmd = [executable("formation-launch"), str(formation), "--out", str(out), "--no-plots", "--quiet", "--no-record"]
    cmd += ["--discovery", "server", "--duration", "0.05", "--record-rate", "1000", "--netns", "off"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        text = proc.communicate(timeout=600)[0].decode(errors="replace")
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGINT)  # the launcher stops its own processes
        text = proc.communicate(timeout=60)[0].decode(errors="replace")
        return FortyAgentsRun(formation, out, None, text)
    return FortyAgentsRun(formation, out, proc.returncode, text)
