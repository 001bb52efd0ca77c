"""``formation-launch FILE …`` (what ``ros2_ws/run.sh`` runs): a formation as ROS 2 processes.

Validates the file (exit 2 before any process starts) and checks OUT (writable, room for the
expected bag), then starts the simulator node and one agent process per agent through
:class:`formation_sim.launch.supervisor.Supervisor`, in the DDS environment of :mod:`formation_sim.launch.dds_env`.
Recording (the default): the simulator writes OUT/bag itself (``formation-sim --bag``: nothing
crosses DDS twice, nothing is lost). The simulator's progress is relayed from its log. The run
stops on completion, Ctrl-C, SIGTERM, SIGHUP or the death of a process (in realtime an agent's
death is reported and the run goes on: the simulator zeroes that agent's wrench); the death is
named, with the step the agent last answered (:func:`went_on_without`). With ``--discovery
server`` a Fast DDS discovery server (:mod:`formation_sim.launch.discovery_server`) is the run's
first process and every other one its client; it is stopped with the others.
After the last step, the agents are stopped while the simulator writes OUT, then
OUT/summary.json is completed with the verdict of the whole run: the simulator's, made INCOMPLETE
when a process died or the run was interrupted (FAIL if a violation came first), and with every
agent's own fault counts
(``faults_file``: resets, refused measurements, missing poses). ``OUT/logs/processes.json`` lists every
process with its exit status, CPU time and peak memory.

Over 500 lines: one process's life, from the checks before anything starts to the merged verdict
after everything stopped; the :class:`Launcher` holds the state every stage shares (the processes,
the output directory, the reserve of disk space), and the helpers around it are its stages.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from formation_agent.kernel_cache import compiled_pays
from formation_bag.foxglove_server import endpoint_problem
from formation_core import options
from formation_core.errors import FormationError
from formation_core.faults import FaultLog
from formation_core.options import Discovery, OptionParser, RunOptions
from formation_core.verdict import EXIT_STATUS_HELP, ExitCode, Incomplete, decide, guarded
from formation_deploy.publisher_watch import merge_security, security_file, untrusted_input
from formation_sim.launch import dds_env, discovery_server
from formation_sim.launch.supervisor import Child, LogFollower, Supervisor, tls_failures
from formation_sim.preflight import InvalidRunError, Prepared, launch_outputs, preflight, prepare_out_dir

if TYPE_CHECKING:
    from formation_core.formation import FormationSpec
    from formation_deploy.secure_transport import SecureRun
    from formation_sim.core.summary import LaunchReport, RunSummary

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


#: wall seconds from SIGINT to SIGKILL when the launcher stops its processes: a node process needs
#: ~10-50 ms of CPU to stop (formation_ros.shutdown), the interrupted simulator a little more to
#: write its summary and trajectory; at load 10 on 2 cores each gets about a fifth of a core
STOP_GRACE = 2.5
#: … plus this much per process beyond six stopped at once: 40 agents stopping together at load 58
#: on 2 cores are each scheduled a few percent of a core, and one of them (its faults written with
#: the others') was still destroying its node 2.5 s later (1 of 12 stress runs of 40 agents)
GRACE_PER_PROCESS = 0.1


def stop_grace(processes: int) -> float:
    """Wall s from SIGINT to SIGKILL when ``processes`` processes stop at once."""
    return STOP_GRACE + GRACE_PER_PROCESS * max(0, processes - 6)


#: wall s added to the longer of the discovery and step timeouts for the default --hang-timeout: the
#: simulator prints while it waits for discovery (every 5 s) and while it steps (every second); silent
#: longer, it is stuck (the rmw's shared-memory transport once hung it inside node creation, deaf to
#: SIGINT), and without a bound the launcher would wait for it for ever
HANG_MARGIN = 120.0
#: … and this much more once it has stepped to the end and writes OUT
WRITING_MARGIN = 600.0

#: bytes kept free on OUT's file system for the final summary.json and processes.json
RESERVE_BYTES = 2_000_000


def expected_bag_bytes(spec: FormationSpec) -> int:
    """A generous estimate of the bag of a run recorded at every control step [bytes]."""
    s = spec.simulation
    n, k = len(spec.agents), len(spec.edges)
    # CDR payloads (velocity/wrench ~80 B, relative pose ~110 B, ground truth 56 B per agent)
    # plus ~60 B of MCAP record and index per message
    per_step = n * 2 * (80 + 60) + 2 * k * (110 + 60) + (56 * n + 40 + 60)
    steps = round(s.duration * s.control_rate) + 1
    return int(per_step * steps * 1.2) + 1_000_000


def check_space(out: Path, spec: FormationSpec, record: bool) -> str | None:
    """None if OUT's file system has room for the run's outputs, else the reason (creates nothing:
    :func:`formation_sim.preflight.check_out_dir` has checked that OUT can be written)."""
    s = spec.simulation
    rows = round(s.duration * s.record_rate) + 1
    need = rows * len(spec.agents) * 24 * 8 + 5_000_000  # trajectory.npz, figures, logs
    if record:
        need += expected_bag_bytes(spec)
    base = out
    while not base.exists() and base != base.parent:
        base = base.parent
    try:
        free = shutil.disk_usage(base).free
    except OSError as exc:
        return f"{out}: {exc.strerror or exc}"
    if free < need:
        return f"{out} has {free / 1e6:.0f} MB free, the run needs about {need / 1e6:.0f} MB"
    return None


def progress_text(line: str) -> str:
    """The launcher's progress line from the simulator's (``progress t=T/D rtf=R worst_margin=M eta=S``)."""
    kv = dict(part.split("=", 1) for part in line.split()[1:] if "=" in part)
    return (
        f"  sim t={kv.get('t', '?')} s  real-time factor {kv.get('rtf', '?')}  "
        f"worst margin {kv.get('worst_margin', '?')}" + (f"  ETA {kv['eta']} s" if "eta" in kv else "")
    )


class SpaceReserve:
    """Room kept on OUT's file system for the final summary and process table, should the disk fill
    up during the run: an unnamed file (O_TMPFILE) of ``size`` bytes, released by :meth:`release`
    or by the process's end, even SIGKILL: it never appears in OUT."""

    def __init__(self, directory: Path, size: int = RESERVE_BYTES) -> None:
        self._file: Any = tempfile.TemporaryFile(dir=directory)
        try:
            self._file.write(b"\0" * size)
            self._file.flush()
            os.fsync(self._file.fileno())
        except OSError:
            self._file.close()
            raise

    @property
    def allocated(self) -> int:
        """Bytes the reserve holds on disk."""
        return os.fstat(self._file.fileno()).st_blocks * 512

    def release(self) -> None:
        self._file.close()


def agent_faults_file(logs: Path, agent_id: str) -> Path:
    """Where agent ``agent_id`` writes its fault counts when it stops (its ``faults_file`` parameter)."""
    return logs / f"agent_{agent_id}_faults.json"


def merge_agent_faults(summary: dict[str, Any], logs: Path, agent_ids: Sequence[str]) -> None:
    """Every agent's own fault counts (resets, refused measurements, missing poses) into ``summary["faults"]``;
    ``summary["agent_faults_unknown"]`` names the agents that wrote none (killed, or never started)."""
    faults = FaultLog()
    faults.merge(summary.get("faults") or {})
    unknown = []
    for a in agent_ids:
        try:
            faults.merge(json.loads(agent_faults_file(logs, a).read_text(encoding="utf-8")))
        except (OSError, ValueError):
            unknown.append(a)
    summary["faults"] = faults.as_dict()
    if unknown:
        summary["agent_faults_unknown"] = unknown


def merge_agent_security(summary: dict[str, Any], logs: Path, agent_ids: Sequence[str]) -> None:
    """The intruders every agent saw on its own topics into ``summary["security"]`` and the verdict:
    one that reached an agent only (the simulator's graph did not see it before the run ended)
    makes the run INCOMPLETE (untrusted input, exit 4) as one the simulator saw does; a run
    INCOMPLETE for a reason of its own keeps it, and the intruders are added to it."""
    reports: list[Mapping[str, Any] | None] = [summary.get("security")]
    for a in agent_ids:
        try:
            reports.append(json.loads(security_file(agent_faults_file(logs, a)).read_text(encoding="utf-8")))
        except (OSError, ValueError):
            continue  # an agent that wrote none: killed or never started (agent_faults_unknown says so)
    before = untrusted_input(summary.get("security"))
    merged = merge_security(reports)
    if merged is None:
        return
    summary["security"] = merged
    after = untrusted_input(merged)
    if after is None or after == before:
        return
    reason = summary.get("incomplete_reason")
    if summary.get("verdict") in ("PASS", "FAIL") or (reason and reason == before):
        summary.update(verdict="INCOMPLETE", incomplete_reason=after, exit_status=int(ExitCode.INCOMPLETE))
        summary["funnels_held"] = None
    elif before and reason and before in reason:
        summary["incomplete_reason"] = reason.replace(before, after)
    else:
        summary["incomplete_reason"] = f"{reason}; {after}" if reason else after


@dataclass(frozen=True)
class Death:
    """An agent that died during a realtime run, which went on without it."""

    agent_id: str
    #: how it ended, as :meth:`formation_sim.launch.supervisor.Child.describe_exit` says it
    how: str


def went_on_without(deaths: Sequence[Death], last_answer: Mapping[str, float | None] | None) -> Incomplete:
    """INCOMPLETE, a process died (exit 3), for agents that died in a realtime run that went on: each
    named with the step it last answered (``last_answer`` [s]: the simulator's summary.json
    ``last_answer_t``, None where it does not say), the run's data whole up to the earliest of them."""
    parts, whole = [], []
    for d in deaths:
        if last_answer is None or d.agent_id not in last_answer:
            parts.append(f"{d.how} (when is unknown: the simulator's summary does not say)")
            whole.append(0.0)
        elif (t := last_answer[d.agent_id]) is None:
            parts.append(f"{d.how} before it answered a step")
            whole.append(0.0)
        else:
            parts.append(f"{d.how} after answering the step of t={t:.4f} s")
            whole.append(t)
    wrench = "its wrench" if len(deaths) == 1 else "their wrenches"
    reason = f"{', '.join(parts)}; the realtime run went on with {wrench} held, then zeroed"
    return Incomplete(ExitCode.PROCESS_DIED, reason, whole_until=min(whole))


def simulator_stop(summary: Mapping[str, Any], untrusted: str | None) -> Incomplete | None:
    """The simulator's own reason its run is INCOMPLETE or stopped early (lag budget, I/O error,
    interrupted), without the untrusted input that :func:`decide` names again; None if it has none."""
    reason = summary.get("incomplete_reason")
    if summary.get("verdict") == "PASS" or not reason or reason == untrusted:
        return None
    if untrusted:
        reason = reason.removesuffix(f"; {untrusted}")
    interrupted = summary.get("exit_status") == ExitCode.INTERRUPTED
    return Incomplete(ExitCode.INTERRUPTED if interrupted else ExitCode.INCOMPLETE, reason)


def build_parser() -> OptionParser:
    return options.build_parser(
        options.LAUNCH,
        "formation-launch",
        "Run a formation through ROS 2: the simulator node and one process per agent "
        "(unless --no-record, the simulator records the run's bag). "
        "Writes OUT as docs/outputs.md (summary.json, trajectory.npz, the figures, foxglove_layout.json; "
        "recorded runs: bag/ and view.mcap, the small file of the display topics to open in Foxglove "
        "with foxglove_layout.json) with one log per process in OUT/logs. " + EXIT_STATUS_HELP + ".",
    )


def _sim_args(args: RunOptions, out: Path, spec: FormationSpec) -> list[str]:
    assert args.file is not None  # preflight loaded it
    cmd = [str(args.file.resolve()), "--out", str(out), "--force", *args.child_argv(options.SIM)]
    if args.record:
        cmd += ["--bag", str(out / "bag")]
        if args.ground_truth_rate is None:
            # the analysis checks the funnels at the recorded ground-truth samples: all of them
            cmd += ["--ground-truth-rate", repr(spec.simulation.control_rate)]
    return cmd


class Launcher:
    """One run: starts the processes, relays progress, stops them, completes the summary."""

    def __init__(
        self, spec: FormationSpec, args: RunOptions, out: Path, env: dict[str, str], discovery: Discovery | None = None
    ) -> None:
        self.spec = spec
        #: the discovery server this run starts (its address with the port), or None: simple discovery
        self.discovery = discovery
        self.args = args
        self.out = out
        self.mode = args.mode or spec.simulation.mode
        self.sup = Supervisor(env, out / "logs", key_names=_KEY_NAMES, batch=args.scheduling == "batch")
        self.stop: Incomplete | None = None
        self.signalled: int | None = None
        #: realtime: agents that died while the run went on
        self.agent_died: list[Death] = []
        self._tty = sys.stdout.isatty()
        self._follow: LogFollower | None = None
        #: when the simulator's log last grew [monotonic s]
        self._heard = time.monotonic()
        self.timing: dict[str, float] = {}
        #: children sent SIGINT after the last step (their exit is no death)
        self.interrupted: set[str] = set()
        #: a --secure run: the children's logs are searched for failed TLS handshakes at the end
        self.secure = False
        #: (verdict, incomplete_reason) of the simulator's summary.json, whose figures say it
        self.simulator_verdict: tuple[Any, Any] | None = None

    def on_signal(self, signum: int, _frame: Any) -> None:
        if self.signalled is None:
            self.signalled = signum

    def start_discovery_server(self) -> None:
        """The run's discovery server, listening before any client starts (raises DiscoveryServerError)."""
        assert self.discovery is not None
        self.sup.process_env["discovery_server"] = discovery_server.server_environment(self.sup.env)
        server = self.sup.start("discovery_server", "discovery", discovery_server.server_command(self.discovery))
        discovery_server.wait_listening(server.proc, self.discovery, server.log)

    def start_all(self) -> Child:
        spec, args = self.spec, self.args
        assert args.file is not None and args.mode is not None  # preflight loaded the file and resolved the mode
        formation = str(args.file.resolve())
        sim = self.sup.start(
            "sim",
            "sim",
            [sys.executable, "-u", "-m", "formation_sim.node.sim_node", *_sim_args(args, self.out, spec)],
        )
        self._follow = LogFollower(sim.log)
        # the agents' controller: compiled or interpreted (formation_agent.kernel_cache), unless the environment says
        compiled = compiled_pays(spec.simulation.control_rate, args.mode, len(spec.agents))
        jit = self.sup.env.get("NUMBA_DISABLE_JIT") or ("0" if compiled else "1")
        # the user's parameters file first: the launcher's own -p below (the agent's id, the file) win over it
        params_file = ["--params-file", str(args.params_file.resolve())] if args.params_file is not None else []
        for a in spec.agents:
            cmd = [
                str(_bin("formation-agent")),
                "--ros-args",
                *params_file,
                "-p",
                f"formation_file:={formation}",
                "-p",
                f"agent_id:='{a.id}'",
                "-p",
                "use_sim_time:=true",
                "-p",
                f"measurement_qos:={args.measurement_qos}",
                "-p",
                f"intruder_policy:={args.intruder_policy}",
                "-p",
                f"faults_file:={agent_faults_file(self.out / 'logs', a.id)}",
            ]
            key = self.sup.key_names.get(f"agent_{a.id}", f"agent_{a.id}")
            self.sup.process_env[key] = {**self.sup.process_env.get(key, self.sup.env), "NUMBA_DISABLE_JIT": jit}
            self.sup.start(f"agent_{a.id}", "agent", cmd)
        return sim

    def hang_timeout(self) -> float:
        """Wall s of silence in the simulator's log after which the run is stopped as hung."""
        if self.args.hang_timeout is not None:
            return self.args.hang_timeout
        discovery = self.args.discovery_timeout or 30.0 + len(self.spec.agents)  # as the simulator's default
        step = self.spec.simulation.step_timeout if self.mode == "lockstep" else 0.0
        return max(discovery, step) + HANG_MARGIN

    def relay(self) -> None:
        """Show the simulator's new log lines: progress compactly, messages as they are."""
        assert self._follow is not None
        lines = self._follow.new_lines()
        if lines:
            self._heard = time.monotonic()
        for line in lines:
            if line.startswith("progress "):
                if self.args.quiet:
                    continue
                text = progress_text(line)
                print("\r" + text.ljust(78) if self._tty else text, end="" if self._tty else "\n", flush=True)
            elif line.startswith("formation-sim: all ") and "matched" in line:
                self.timing["stepping_from"] = time.monotonic()
                print(line, flush=True)
            elif line.startswith("formation-sim: stepping done"):
                self.timing["stepping_done"] = time.monotonic()
                if self._tty:
                    print()
                print(line, flush=True)
                self.stop_others()
            elif line.startswith("formation-sim: ") and " written in " in line and "(figures " in line:
                self.timing["figures_s"] = float(line.rsplit("(figures ", 1)[1].split(" s)")[0])
                print(line, flush=True)
            elif line.startswith(("formation ", "PASS", "FAIL", "INCOMPLETE", "  ")):
                continue  # the summary: printed at the end from summary.json
            elif line:
                if self._tty:
                    print()
                print(line, flush=True)

    def stop_others(self) -> None:
        """After the last step: SIGINT to the agents while the simulator writes OUT."""
        if self.interrupted or self.stop is not None:
            return  # done already, or stopping every process (interrupted, a process died)
        others = [c for c in self.sup.alive() if c.role not in ("sim", "discovery")]  # the server stops last
        for c in others:
            c.signal(signal.SIGINT)
        self.interrupted = {c.name for c in others}
        if not self.args.quiet:
            print("formation-launch: stepping done; stopping the agents", flush=True)

    def note(self, text: str) -> None:
        print(f"formation-launch: {text}", file=sys.stderr, flush=True)

    def watch(self, sim: Child) -> None:
        """Until the simulator exits, a signal arrives, a process dies or the simulator hangs."""
        self._heard = time.monotonic()
        hang = self.hang_timeout()
        while True:
            self.relay()
            # writing OUT (figures, a long trajectory) prints nothing until it is done: more time then
            limit = hang + (WRITING_MARGIN if "stepping_done" in self.timing else 0.0)
            if time.monotonic() - self._heard > limit and sim.poll() is None:
                silent = [c.name for c in self.sup.children if c.poll() is None and _log_is_empty(c.log)]
                why = f"the simulator wrote nothing for {limit:g} s (hung; --hang-timeout)"
                if silent:
                    why += f"; no output at all from {', '.join(silent)}"
                self.note(why + "; stopping every process")
                self.stop = Incomplete(ExitCode.PROCESS_DIED, why)
                return
            if self.signalled is not None:
                name = signal.Signals(self.signalled).name
                self.stop = Incomplete(ExitCode.INTERRUPTED, f"interrupted ({name})")
                self.note(f"{name}: stopping every process")
                return
            if sim.poll() is not None:
                self.relay()
                return
            for c in self.sup.newly_dead():
                if c.name in self.interrupted:
                    continue  # stopped after the last step: checked once every process has exited
                msg = f"{c.describe_exit()} (log: {c.log})"
                if c.role == "agent" and self.mode == "realtime":
                    self.note(msg + "; realtime run continues, its wrench is zeroed by the simulator")
                    self.agent_died.append(Death(c.name.removeprefix("agent_"), c.describe_exit()))
                    continue
                self.note(msg + "; stopping the run")
                code = ExitCode.INCOMPLETE if c.returncode == ExitCode.INCOMPLETE else ExitCode.PROCESS_DIED
                self.stop = Incomplete(code, c.describe_exit() + _last_error(c.log))
                return
            time.sleep(0.05)

    def run(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, self.on_signal)
        self.timing["start"] = time.monotonic()
        if self.discovery is not None:
            try:
                self.start_discovery_server()
            except discovery_server.DiscoveryServerError as exc:
                self.stop = Incomplete(ExitCode.INCOMPLETE, f"nothing started: {exc}")
                self.note(str(exc))
                self.sup.stop(self.sup.children, stop_grace(len(self.sup.children)), self.note)
                self.timing["stop_from"] = self.timing["stopped"] = time.monotonic()
                return
        sim = self.start_all()
        self.watch(sim)
        self.timing["stop_from"] = time.monotonic()
        if sim.poll() is None:
            grace = stop_grace(len(self.sup.children))
            self.sup.stop(self.sup.children, grace, self.note)  # the simulator writes OUT on SIGINT
        else:
            if sim.returncode not in tuple(ExitCode) and self.stop is None:
                self.stop = Incomplete(ExitCode.PROCESS_DIED, sim.describe_exit() + _last_error(sim.log))
                self.note(f"{sim.describe_exit()} (log: {sim.log})")
            self.stop_others()
            grace = stop_grace(len(self.sup.children))
            self.sup.stop(self.sup.alive(), grace, self.note, interrupted=self.interrupted)
        self.relay()
        self.timing["stopped"] = time.monotonic()

    def _tls_failures(self, summary: dict[str, Any]) -> str | None:
        """A secure run's failed TLS handshakes, found in its processes' logs (Fast DDS reports them
        nowhere else), into ``summary["security"]``; the reason's text naming them, or None."""
        from formation_sim.views.outputs import tls_reason

        failures = _tls_failures_of(self.sup.children) if self.secure else {}
        if not failures:
            return None
        security = summary.get("security")
        summary["security"] = {**(security if isinstance(security, dict) else {}), "tls_handshake_failures": failures}
        return tls_reason(summary["security"])

    def summary(self) -> dict[str, Any]:
        """The simulator's summary, completed with what only the launcher knows.

        JSON another process wrote, taken as it is (or, when it wrote none, a stub with the verdict's
        keys only): a :class:`formation_sim.core.summary.RunSummary` once the simulator wrote one."""
        path = self.out / "summary.json"
        try:
            summary = json.loads(path.read_text(encoding="utf-8"))
            self.simulator_verdict = (summary.get("verdict"), summary.get("incomplete_reason"))
        except (OSError, ValueError):
            summary = {
                "formation": self.spec.name,
                "mode": f"ros2-{self.mode}",
                "verdict": "INCOMPLETE",
                "first_violation": None,
                "duration": None,
                "worst_margin": None,
                "faults": {},
                "outputs": [],
            }
            if self.stop is None:
                sim = next(c for c in self.sup.children if c.role == "sim")
                # a simulator that stopped INCOMPLETE (a full disk) or interrupted says so with its status
                code = sim.returncode if sim.returncode in (ExitCode.INCOMPLETE, ExitCode.INTERRUPTED) else None
                self.stop = Incomplete(
                    ExitCode(code or ExitCode.PROCESS_DIED),
                    f"{sim.describe_exit()}: no summary written" + _last_error(sim.log),
                )
        merge_agent_faults(summary, self.out / "logs", self.spec.agent_ids)
        merge_agent_security(summary, self.out / "logs", self.spec.agent_ids)
        tls = self._tls_failures(summary)
        untrusted = untrusted_input(summary.get("security"))
        incomplete = self.stop
        if self.agent_died:
            # the deaths came first; then whatever stopped the run, if anything did
            died = went_on_without(self.agent_died, summary.get("last_answer_t"))
            stopped = incomplete or simulator_stop(summary, untrusted)
            if stopped is not None:
                code = ExitCode.INTERRUPTED if stopped.code == ExitCode.INTERRUPTED else ExitCode.PROCESS_DIED
                died = Incomplete(code, f"{died.reason}; {stopped.reason}", died.whole_until)
            incomplete = died
        if incomplete is not None:
            # the simulator's own verdict counts its intruders already; this one replaces it
            fv = summary.get("first_violation")
            result = decide(fv is not None, incomplete, untrusted, None if fv is None else fv.get("t"))
            summary.update(
                verdict=result.verdict.value,
                incomplete_reason=result.reason,
                exit_status=int(result.exit_code),
                funnels_held={"PASS": True, "FAIL": False}.get(result.verdict.value),
            )
        if tls and summary.get("verdict") == "INCOMPLETE":
            summary["incomplete_reason"] = f"{summary.get('incomplete_reason')}; {tls}"
        t = self.timing
        done = min(t.get("stepping_done", t["stop_from"]), t["stop_from"])  # stepped to the end, or stopped
        launch: LaunchReport = {
            "ros_domain_id": int(self.sup.env["ROS_DOMAIN_ID"]),
            "discovery_range": self.sup.env["ROS_AUTOMATIC_DISCOVERY_RANGE"],
            "transport": dds_env.transport_name(self.sup.env),
            "discovery": str(self.discovery or Discovery()),
            "network_namespace": dds_env.in_netns(),
            "processes": len(self.sup.children),
            "scheduling": self.args.scheduling,
            "wall_start_s": t.get("stepping_from", t["stop_from"]) - t["start"],
            "wall_stepping_s": done - t.get("stepping_from", done),
            # after the last step: the simulator writes OUT, then the agents stop
            "wall_stop_s": t["stopped"] - done,
            "wall_sim_outputs_s": t["stop_from"] - done if "stepping_done" in t else None,
            "wall_figures_s": t.get("figures_s"),  # part of wall_stop_s
        }
        summary["launch"] = launch
        return summary


def _tls_failures_of(children: list[Child]) -> dict[str, dict[str, Any]]:
    """{child name: {"count", "last"}} of the children whose logs hold failed TLS handshakes."""
    found = {c.name: tls_failures(c.log) for c in children}
    return {name: {"count": f.count, "last": f.last} for name, f in found.items() if f is not None}


def _last_error(log: Path) -> str:
    """': <the last line of a log that reads like an error>' or ''."""
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    for line in reversed(lines[-20:]):
        if "error" in line.lower() or "disk" in line.lower():
            return f": {line.strip()[:200]}"
    return ""


def _netns(run: Prepared, argv: list[str], given_out: Path | None) -> None:
    """Re-execute this command in a private network namespace when the run needs one (does not
    return), or InvalidRunError when it needs one and none can be made."""
    args = run.options
    participants = len(run.spec.agents) + 1
    # a discovery server's clients do not announce themselves to one another: no per-host limit to avoid
    crowded = participants > dds_env.NETNS_THRESHOLD and not args.discovery.server
    want = args.netns == "on" or (args.netns == "auto" and crowded)
    if want and args.foxglove is not None:
        raise InvalidRunError(
            f"--foxglove: {participants} DDS participants run in a private network namespace, whose ports "
            'this host cannot reach; use --netns off (docs/ros2.md, "Live view")'
        )
    if dds_env.in_netns() or not want:
        return
    reason = dds_env.netns_available()
    if reason is not None:
        raise InvalidRunError(
            f"{participants} DDS participants need a private network namespace "
            f"(Fast DDS matches about 32 per host under LOCALHOST discovery), but {reason}. "
            "Run as root, or use --netns off with a discovery server / ROS_STATIC_PEERS (docs/ros2.md)"
        )
    if given_out is None:  # fix the output directory before re-executing
        argv = [*argv, "--out", str(run.out)]
    dds_env.reexec_in_netns("formation_sim.launch.launcher", argv)


def _secure(run: Prepared, env: dict[str, str]) -> SecureRun | None:
    """Secure mode's per-process environments, once every certificate and key passed its check
    (InvalidRunError naming the file otherwise); None without --secure."""
    if not run.options.secure:
        return None
    from formation_deploy.secure_transport import SecureRun, SecureTransportError, single_host_port_start

    try:
        port_start = single_host_port_start(int(env["ROS_DOMAIN_ID"]))
        return SecureRun.prepare(
            run.spec.agent_ids,
            env,
            keys=run.options.keys,
            port_start=port_start,
            duration_s=run.spec.simulation.duration,
        )
    except (SecureTransportError, OSError) as exc:
        raise InvalidRunError(f"--secure: {exc}") from None


def _announce(run: Prepared, env: dict[str, str], secure: SecureRun | None, discovery: Discovery | None) -> None:
    spec, args, s = run.spec, run.options, run.spec.simulation
    transport = f"secure: TLS over TCP ports {secure.describe()['ports']}" if secure else None
    print(
        f"formation-launch: {spec.name}: simulator + {len(spec.agents)} agent processes"
        f"{', recorded' if args.record else ''}, {args.mode} at {s.control_rate:g} Hz for {s.duration:g} s; "
        f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']}, "
        f"{transport or _discovery_text(discovery, env)}"
        f"{' in a private network namespace' if dds_env.in_netns() else ''}; logs in {run.out}/logs/",
        flush=True,
    )


def _remove_created(out: Path, existed: bool) -> None:
    """Undo what the launcher made in OUT before any process started: logs/, and OUT if it made it."""
    shutil.rmtree(out / "logs", ignore_errors=True)
    if not existed:
        try:
            out.rmdir()  # only if empty: never what was there before
        except OSError:
            pass


def _finish(launcher: Launcher, secure: SecureRun | None) -> int:
    """Complete and write summary.json and processes.json, print the verdict; the exit status."""
    from formation_core.faults import write_json
    from formation_sim.views.outputs import (  # numba: not for --help
        format_summary,
        redraw_figures,
        report_animation,
        verdict_line,
    )

    out, args = launcher.out, launcher.args
    summary = launcher.summary()
    if secure is not None:
        summary["launch"]["secure"] = secure.describe()
        summary["launch"]["transport"] = "TLS over TCP only (a profile per process)"
    code = int(summary.get("exit_status", ExitCode.INCOMPLETE))
    try:
        write_json(out / "logs" / "processes.json", launcher.sup.process_table(out))
        write_json(out / "summary.json", summary)
    except OSError as exc:
        print(f"formation-launch: INCOMPLETE: could not write {out}: {exc}", file=sys.stderr)
        code = ExitCode.INCOMPLETE
    # the simulator's summary, completed; without "edges" the simulator wrote none, and the launcher's
    # stub holds the keys verdict_line reads
    typed = cast("RunSummary", summary)
    if launcher.simulator_verdict not in (None, (summary.get("verdict"), summary.get("incomplete_reason"))):
        try:  # the simulator's figures are captioned with its verdict, which the launcher's replaces
            redraw_figures(out, launcher.spec, typed)
        except OSError as exc:
            print(f"formation-launch: the figures still show the simulator's verdict: {exc}", file=sys.stderr)
    print(format_summary(typed) if "edges" in summary else verdict_line(typed), flush=True)
    if args.animate and (out / "trajectory.npz").exists():
        import numpy as np

        with np.load(out / "trajectory.npz") as data:
            report_animation(out, launcher.spec, dict(data))
    print(f"outputs in {out}/ (exit status {code})", flush=True)
    return code


def _log_is_empty(log: Path) -> bool:
    try:
        return log.stat().st_size == 0
    except OSError:
        return True


def _discovery_text(discovery: Discovery | None, env: dict[str, str]) -> str:
    if discovery is None:
        if env.get("FASTRTPS_DEFAULT_PROFILES_FILE") == str(dds_env.FASTDDS_LOOPBACK_PROFILE):
            return "discovery on this host (UDP on 127.0.0.1)"
        return f"discovery {env['ROS_AUTOMATIC_DISCOVERY_RANGE']}"
    return f"discovery server {discovery.address()} ({discovery_server.SERVER})"


class RefusedError(Exception):
    """The run does not start: the exit status and the one line that says why."""

    def __init__(self, code: ExitCode, message: str) -> None:
        super().__init__(message)
        self.code = code


def _checked(
    opts: RunOptions, argv: list[str]
) -> tuple[Prepared, dict[str, str], SecureRun | None, SpaceReserve, Discovery | None]:
    """Every check of the run (file, options, network namespace, room, certificates) before OUT is
    prepared; then OUT, its logs/ and the space reserve. Raises :class:`RefusedError`, leaving nothing behind."""
    secure = None
    try:
        run = preflight(opts, lambda spec, o: _default_out(spec, o.mode or spec.simulation.mode), prepare=False)
        for msg in run.warnings:
            print(f"formation-launch: warning: {msg}", file=sys.stderr)
        if run.options.discovery.server and run.options.secure:
            raise InvalidRunError(
                "--discovery server with --secure: the secure transport is TLS over TCP with every other "
                "transport off, and the discovery server listens on UDP; a client would either reach it in "
                "clear text or not at all (docs/security.md). Use one or the other"
            )
        _netns(run, argv, opts.out)
        assert run.out is not None
        out = run.out.resolve()
        problem = check_space(out, run.spec, run.options.record)
        if problem is not None:
            raise RefusedError(ExitCode.INCOMPLETE, f"INCOMPLETE: nothing started: {problem}")
        if run.options.foxglove is not None and (problem := endpoint_problem(run.options.foxglove)) is not None:
            raise RefusedError(ExitCode.INVALID, f"INVALID: nothing started: {problem}")
        env = dds_env.run_environment(dict(os.environ), log_dir=out / "logs" / "ros")
        discovery = None
        if run.options.discovery.server:
            discovery = discovery_server.with_port(run.options.discovery)
            env = dds_env.discovery_client_environment(env, discovery)
        secure = _secure(run, env)
        existed = out.exists()
        prepare_out_dir(out, run.options.force, launch_outputs(run.options))
    except BaseException as exc:
        if secure is not None:
            secure.close()  # its temporary keys and profiles
        if isinstance(exc, FormationError):
            raise RefusedError(ExitCode.INVALID, f"INVALID: {exc}") from None
        raise
    try:
        (out / "logs").mkdir(exist_ok=True)
        reserve = SpaceReserve(out)
    except BaseException as exc:
        _remove_created(out, existed)
        if secure is not None:
            secure.close()
        if isinstance(exc, OSError):
            message = f"INCOMPLETE: nothing started: {out}: {exc.strerror or exc}"
            raise RefusedError(ExitCode.INCOMPLETE, message) from None
        raise
    if secure is not None:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    return replace(run, out=out), env, secure, reserve, discovery


@guarded("formation-launch")
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    opts = options.parse(options.LAUNCH, build_parser(), argv)
    try:
        run, env, secure, reserve, discovery = _checked(opts, argv)
    except RefusedError as exc:
        print(f"formation-launch: {exc}", file=sys.stderr)
        return exc.code
    assert run.out is not None
    _announce(run, env, secure, discovery)
    launcher = Launcher(run.spec, run.options, run.out, env, discovery)
    if secure is not None:
        launcher.sup.process_env = secure.environments
        launcher.secure = True
    try:
        launcher.run()
    finally:
        reserve.release()  # room for summary.json and processes.json
        if secure is not None:
            secure.close()
    return _finish(launcher, secure)


def _default_out(spec: FormationSpec, mode: str) -> Path:
    return Path("out") / f"{spec.name}-ros2-{mode}-{time.strftime('%Y%m%d-%H%M%S')}"


if __name__ == "__main__":
    sys.exit(main())
