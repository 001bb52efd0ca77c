"""``formation-launch FILE …`` (what ``ros2_ws/run.sh`` runs): a formation as ROS 2 processes.

Validates the file (exit 2 before any process starts), then starts the simulator node and one
agent process per agent (and, with ``--record``, ``formation-record``), each in its own process
group and session with its own log file in ``OUT/logs/``. The simulator waits for discovery and
prints progress, which is relayed here. Everything is stopped on completion, Ctrl-C, SIGTERM,
SIGHUP, or the death of a process (in realtime mode an agent's death is reported and the run
goes on: the simulator zeroes that agent's wrench). Children are stopped with SIGINT, then
SIGTERM, and SIGKILL only after a grace period; they also get SIGTERM if this process dies
(PR_SET_PDEATHSIG). ``OUT/logs/processes.json`` lists every process with its exit status, CPU
time and peak memory.

Discovery stays on this host: ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless set, and a
free ``ROS_DOMAIN_ID`` is picked when unset. Fast DDS matches only about 32 participants per
host under LOCALHOST; larger runs re-execute inside a private network namespace (``unshare -n``
with its own loopback, multicast enabled on it): nothing can leave the machine there.

Exit status: 0 every funnel held; 1 a funnel was violated or a fault reported; 2 invalid file or
settings; 3 a process died, or an agent was missing; 130 interrupted.
"""

from __future__ import annotations

import ctypes
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from formation_msgs_py import options
from formation_msgs_py.errors import FormationError
from formation_msgs_py.hotloop import FASTDDS_PROFILE
from formation_msgs_py.options import OptionParser, RunOptions
from formation_msgs_py.spec import FormationSpec
from formation_sim.preflight import preflight
from formation_sim.report import format_summary, report_animation

EXIT_OK, EXIT_VIOLATION, EXIT_INVALID, EXIT_PROCESS, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
#: Above this many DDS participants, run in a private network namespace (Fast DDS LOCALHOST limit).
NETNS_THRESHOLD = 30
_IN_NETNS = "FORMATION_IN_NETNS"
_PR_SET_PDEATHSIG = 1
#: child name -> formation-keys process name, where they differ
_KEY_NAMES = {"sim": "simulator"}


def _bin(name: str) -> Path:
    """A console script: in a sourced colcon/ament install (``<prefix>/lib/<package>/NAME`` for a
    prefix of AMENT_PREFIX_PATH, where ``ros2 run`` finds it), next to this interpreter (the
    project's ``.venv/bin``), or on PATH; the ``.venv/bin`` path when none exists."""
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        found = sorted(Path(prefix).glob(f"lib/*/{name}"))
        if found:
            return found[0]
    here = Path(sys.executable).parent / name
    which = shutil.which(name)
    return Path(which) if which and not here.exists() else here


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class Child:
    """One started process: its name, command, log file and (once reaped) its accounting."""

    name: str
    proc: subprocess.Popen
    log: Path
    role: str
    returncode: int | None = None
    rusage: dict[str, float] = field(default_factory=dict)
    reported: bool = False

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status, ru = os.wait4(self.proc.pid, os.WNOHANG)
            except ChildProcessError:
                self.returncode = self.proc.returncode if self.proc.returncode is not None else -1
                return self.returncode
            if pid == 0:
                return None
            self.returncode = os.waitstatus_to_exitcode(status)
            self.proc.returncode = self.returncode
            self.rusage = {
                "cpu_user_s": ru.ru_utime,
                "cpu_system_s": ru.ru_stime,
                "max_rss_mb": ru.ru_maxrss / 1024.0,
            }
        return self.returncode

    def signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)  # its own process group (start_new_session)
            except ProcessLookupError:
                pass


def used_domain_ids() -> set[int]:
    """Domain ids whose Fast DDS port block (7400 + 250·id …) has a bound UDP socket here."""
    used: set[int] = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            port = int(line.split()[1].rsplit(":", 1)[1], 16)
            if port >= 7400:
                used.add((port - 7400) // 250)
    return used


def pick_domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..101 that no local DDS participant uses (random start)."""
    used = used_domain_ids()
    start = random.Random(os.getpid() ^ time.time_ns()).randrange(101)
    for k in range(101):
        d = 1 + (start + k) % 101
        if d not in used:
            return d
    raise RuntimeError("every ROS_DOMAIN_ID in 1..101 is in use on this host; set ROS_DOMAIN_ID")


def netns_available() -> str | None:
    """None if ``unshare -n`` works here, else the reason."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip (util-linux, iproute2) not found"
    r = subprocess.run(["unshare", "-n", "ip", "link", "set", "lo", "up"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"unshare -n not permitted: {r.stderr.strip() or r.returncode} (needs root or CAP_SYS_ADMIN)"
    return None


def reexec_in_netns(argv: list[str]) -> None:
    """Replace this process by itself inside a new network namespace with only a loopback."""
    env = dict(os.environ, **{_IN_NETNS: "1"})
    script = 'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec "$@"'
    cmd = ["unshare", "-n", "sh", "-c", script, "sh", sys.executable, "-m", "formation_sim.launch", *argv]
    sys.stdout.flush()
    sys.stderr.flush()
    os.execvpe("unshare", cmd, env)


def build_parser() -> OptionParser:
    return options.build_parser(
        options.LAUNCH,
        "formation-launch",
        "Run a formation through ROS 2: the simulator node and one process per agent "
        "(and, unless --no-record, a bag recorder). Writes OUT as docs/outputs.md with one log per process in "
        "OUT/logs. Exit status: 0 every funnel held, 1 violated or fault, 2 invalid, 3 a process died or an "
        "agent was missing, 130 interrupted.",
    )


def _sim_args(args: RunOptions, out: Path, spec: FormationSpec) -> list[str]:
    cmd = [str(args.file.resolve()), "--out", str(out), "--force", *args.child_argv(options.SIM)]
    if args.record:
        cmd.append("--wait-recorder")
        if args.ground_truth_rate is None:
            # the analysis checks the funnels at the recorded ground-truth samples: all of them
            cmd += ["--ground-truth-rate", repr(spec.simulation.control_rate)]
    return cmd


class Launcher:
    """Starts, watches and stops the processes of one run."""

    def __init__(self, spec: FormationSpec, args: RunOptions, out: Path, env: dict[str, str]) -> None:
        self.spec = spec
        self.args = args
        self.out = out
        self.logs = out / "logs"
        self.env = env
        self.children: list[Child] = []
        self.stop_reason: str | None = None
        self.signalled: int | None = None
        self.code = EXIT_OK
        self.agent_died = False
        self._relay: threading.Thread | None = None
        self._tty = sys.stdout.isatty()
        #: per-process environments (secure mode: each its own certificate and port), by key name
        self.process_env: dict[str, dict[str, str]] = {}

    def start(self, name: str, role: str, cmd: list[str], *, pipe: bool = False) -> Child:
        log = self.logs / f"{name}.log"
        fh: IO[bytes] = open(log, "wb")
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE if pipe else fh,
            stderr=subprocess.STDOUT,
            env=self.process_env.get(_KEY_NAMES.get(name, name), self.env),
            start_new_session=True,
            preexec_fn=_die_with_parent,
        )
        fh_keep = fh
        child = Child(name, proc, log, role)
        self.children.append(child)
        if pipe:
            self._relay = threading.Thread(target=self._relay_output, args=(proc, fh_keep), daemon=True)
            self._relay.start()
        else:
            fh.close()
        return child

    def _relay_output(self, proc: subprocess.Popen, fh: IO[bytes]) -> None:
        """Copy the simulator's output to its log; show progress lines compactly."""
        assert proc.stdout is not None
        for raw in proc.stdout:
            fh.write(raw)
            fh.flush()
            line = raw.decode("utf-8", "replace").rstrip("\n")
            if line.startswith("progress "):
                if self.args.quiet:
                    continue
                kv = dict(part.split("=", 1) for part in line.split()[1:] if "=" in part)
                text = (
                    f"  sim t={kv.get('t', '?')} s  real-time factor {kv.get('rtf', '?')}  "
                    f"worst margin {kv.get('worst_margin', '?')}"
                )
                if self._tty:
                    print("\r" + text.ljust(78), end="", flush=True)
                else:
                    print(text, flush=True)
            elif line.startswith(("formation ", "PASS", "FAIL", "  ")):
                continue  # the summary: printed at the end from summary.json
            else:
                if self._tty:
                    print()
                print(line, flush=True)
        fh.close()

    def on_signal(self, signum: int, _frame: Any) -> None:
        if self.signalled is None:
            self.signalled = signum
            self.stop_reason = f"received {signal.Signals(signum).name}"

    def run(self) -> int:
        spec, args = self.spec, self.args
        mode = args.mode or spec.simulation.mode
        venv_python = sys.executable
        formation = str(args.file.resolve())
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, self.on_signal)
        if args.record:
            self.start(
                "recorder",
                "recorder",
                [
                    str(_bin("formation-record")),
                    "--out",
                    str(self.out / "bag"),
                    "--formation",
                    formation,
                    "--quiet",
                    "--meta",
                    f"mode={mode}",
                    f"control_rate={spec.simulation.control_rate!r}",
                    f"duration={spec.simulation.duration!r}",
                ],
            )
        sim = self.start(
            "sim",
            "sim",
            [venv_python, "-u", "-m", "formation_sim.sim_node", *_sim_args(args, self.out, spec)],
            pipe=True,
        )
        for a in spec.agents:
            cmd = [
                str(_bin("formation-agent")),
                "--ros-args",
                "-p",
                f"formation_file:={formation}",
                "-p",
                f"agent_id:='{a.id}'",
                "-p",
                "use_sim_time:=true",
                "-p",
                f"measurement_qos:={args.measurement_qos}",
                "-p",
                f"executor:={args.executor}",
                "-p",
                f"intruder_policy:={args.intruder_policy}",
            ]
            self.start(f"agent_{a.id}", "agent", cmd)
        while True:
            if self.signalled is not None:
                self.code = EXIT_INTERRUPTED
                break
            rc = sim.poll()
            if rc is not None:
                self.code = {0: EXIT_OK, 1: EXIT_VIOLATION, 2: EXIT_INVALID}.get(rc, EXIT_PROCESS if rc != 130 else rc)
                break
            dead = [c for c in self.children if c is not sim and not c.reported and c.poll() is not None]
            for c in dead:
                c.reported = True
                msg = f"formation-launch: {c.name} exited with status {c.returncode} (log: {c.log})"
                if c.role == "agent" and mode == "realtime":
                    print(msg + "; realtime run continues, its wrench is zeroed by the simulator", flush=True)
                    self.agent_died = True
                    continue
                print(msg + "; stopping the run", file=sys.stderr, flush=True)
                self.stop_reason = f"{c.name} exited"
                self.code = EXIT_PROCESS
            if self.stop_reason is not None:
                break
            time.sleep(0.05)
        self.stop_all(sim)
        if self.agent_died and self.code in (EXIT_OK, EXIT_VIOLATION):
            self.code = EXIT_PROCESS
        return self.code

    def stop_all(self, sim: Child) -> None:
        """Simulator first (it writes OUT), then the recorder, then the agents: INT, TERM, KILL."""
        if sim.poll() is None:
            sim.signal(signal.SIGINT)
            self._wait([sim], 20.0)
        recorders = [c for c in self.children if c.role == "recorder"]
        for c in recorders:
            c.signal(signal.SIGINT)
        self._wait(recorders, 15.0)
        rest = [c for c in self.children if c.poll() is None]
        for c in rest:
            c.signal(signal.SIGINT)
        self._wait(rest, 5.0)
        for sig, grace in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
            left = [c for c in self.children if c.poll() is None]
            if not left:
                break
            print(
                f"formation-launch: {', '.join(c.name for c in left)} still running: {signal.Signals(sig).name}",
                file=sys.stderr,
            )
            for c in left:
                c.signal(sig)
            self._wait(left, grace)
        if self._relay is not None:
            self._relay.join(timeout=5.0)

    @staticmethod
    def _wait(children: list[Child], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(c.poll() is None for c in children):
            time.sleep(0.02)

    def write_process_table(self) -> None:
        rows = [
            {
                "name": c.name,
                "pid": c.proc.pid,
                "role": c.role,
                "executable": str(c.proc.args[0]),
                "returncode": c.returncode,
                "log": str(c.log.relative_to(self.out)),
                **c.rusage,
            }
            for c in self.children
        ]
        (self.logs / "processes.json").write_text(json.dumps(rows, indent=2) + "\n", encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    opts = options.parse(options.LAUNCH, build_parser(), argv)
    try:
        run = preflight(opts, lambda spec, o: _default_out(spec, o.mode))
    except FormationError as exc:
        print(f"formation-launch: INVALID: {exc}", file=sys.stderr)
        return EXIT_INVALID
    spec, out, args = run.spec, run.out, run.options
    mode = args.mode
    for msg in run.warnings:
        print(f"formation-launch: warning: {msg}", file=sys.stderr)
    if args.record and not _bin("formation-record").exists():
        print(
            f"formation-launch: --record needs {_bin('formation-record')} (package formation_bag), which is not "
            "installed in this environment",
            file=sys.stderr,
        )
        return EXIT_INVALID
    participants = len(spec.agents) + 1 + int(args.record)
    in_netns = os.environ.get(_IN_NETNS) == "1"
    if not in_netns and (args.netns == "on" or (args.netns == "auto" and participants > NETNS_THRESHOLD)):
        reason = netns_available()
        if reason is not None:
            print(
                f"formation-launch: {participants} DDS participants need a private network namespace "
                f"(Fast DDS matches about 32 per host under LOCALHOST discovery), but {reason}. "
                "Run as root, or use --netns off with a discovery server / ROS_STATIC_PEERS (docs/ros2.md).",
                file=sys.stderr,
            )
            return EXIT_INVALID
        if opts.out is None:  # fix the output directory before re-executing
            argv += ["--out", str(out)]
        if not os.environ.get("ROS_DOMAIN_ID"):
            # picked here, where the host's DDS ports are visible: /dev/shm is shared with the host
            os.environ["ROS_DOMAIN_ID"] = str(pick_domain_id())
        reexec_in_netns(argv)
    out = out.resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env["ROS_LOG_DIR"] = str(out / "logs" / "ros")
    if in_netns:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"  # multicast on the namespace's own loopback only
        # UDP on the namespace's loopback only: Fast DDS's shared-memory transport would use /dev/shm,
        # which the namespace shares with the host (port files of other runs: "open_and_lock_file failed")
        env.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")
    else:
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))  # secure mode sets its own per process
    if not env.get("ROS_DOMAIN_ID"):
        env["ROS_DOMAIN_ID"] = str(pick_domain_id())
    secure = None
    if args.secure:
        from formation_deploy.secure_transport import SecureRun, SecureTransportError, single_host_port_start

        try:
            port_start = single_host_port_start(int(env["ROS_DOMAIN_ID"]))
            secure = SecureRun.prepare(spec.agent_ids, env, keys=args.keys, port_start=port_start)
        except (SecureTransportError, OSError) as exc:
            print(f"formation-launch: --secure: {exc}", file=sys.stderr)
            return EXIT_INVALID
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    s = spec.simulation
    transport = f"secure: TLS over TCP ports {secure.describe()['ports']}" if secure else None
    print(
        f"formation-launch: {spec.name}: simulator + {len(spec.agents)} agent processes"
        f"{' + recorder' if args.record else ''}, {mode} at {s.control_rate:g} Hz for {s.duration:g} s; "
        f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, "
        f"{transport or 'discovery ' + env['ROS_AUTOMATIC_DISCOVERY_RANGE']}"
        f"{' in a private network namespace' if in_netns else ''}; logs in {out / 'logs'}/",
        flush=True,
    )
    launcher = Launcher(spec, args, out, env)
    if secure is not None:
        launcher.process_env = secure.environments
    started = time.monotonic()
    try:
        code = launcher.run()
    finally:
        if secure is not None:
            secure.close()
    launcher.write_process_table()
    summary_path = out / "summary.json"
    if launcher._tty:
        print()
    if summary_path.exists():
        summary = json.loads(summary_path.read_text(encoding="utf-8"))
        summary["launch"] = {
            "ros_domain_id": int(env["ROS_DOMAIN_ID"]),
            "discovery_range": env["ROS_AUTOMATIC_DISCOVERY_RANGE"],
            "network_namespace": in_netns,
            "secure": secure.describe() if secure else None,
            "processes": len(launcher.children),
            "wall_time_total": time.monotonic() - started,
        }
        summary_path.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        print(format_summary(summary))
        if code == EXIT_OK and not summary["funnels_held"]:
            code = EXIT_VIOLATION
        if summary.get("faults"):
            print("faults: " + "; ".join(f"agent {a}: {m}" for a, m in summary["faults"].items()))
        if args.animate and (out / "trajectory.npz").exists():
            import numpy as np

            with np.load(out / "trajectory.npz") as data:
                report_animation(out, spec, dict(data))
    if launcher.stop_reason:
        print(f"formation-launch: stopped: {launcher.stop_reason}", file=sys.stderr)
    print(f"outputs in {out}/ (exit status {code})")
    return code


def _default_out(spec: FormationSpec, mode: str) -> Path:
    return Path("out") / f"{spec.name}-ros2-{mode}-{time.strftime('%Y%m%d-%H%M%S')}"


if __name__ == "__main__":
    sys.exit(main())
