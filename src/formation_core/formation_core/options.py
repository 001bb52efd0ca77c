"""The run options of formation-headless, formation-sim, formation-launch and formation-check.

Declared once (:data:`OPTIONS`): each option's flag, type, default, help, the commands that
take it, the ``simulation.*`` key it overrides and whether formation-launch passes it on to
formation-sim. From the declaration come the argparse options (:func:`build_parser`), the
typed, frozen :class:`RunOptions` the runners receive, and the child command line
(:meth:`RunOptions.child_argv`).

Every rate, duration and timeout must be a finite number > 0 (``--settle`` ≥ 0), a seed an
integer ≥ 0: anything else ends the command with exit 2 and one line naming the option and the
value, before any file is read or process started. This module imports only the standard
library (``--help`` of every command stays fast).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

HEADLESS, SIM, LAUNCH, CHECK = "headless", "sim", "launch", "check"
RUNNERS = frozenset({HEADLESS, SIM, LAUNCH})
ROS = frozenset({SIM, LAUNCH})


def _number(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"{text!r} is not finite")
    return x


def positive(text: str) -> float:
    """A finite number > 0 (rates in Hz, durations and timeouts in s)."""
    x = _number(text)
    if x <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return x


def nonnegative(text: str) -> float:
    """A finite number ≥ 0."""
    x = _number(text)
    if x < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return x


DEFAULT_HOST = "127.0.0.1"


def split_endpoint(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` as (host, port): host 127.0.0.1 when omitted; port 0 picks a free one.

    An IPv6 host is written in brackets: ``[::1]:8765``. Raises ValueError naming the value.
    """
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host = DEFAULT_HOST
    elif not host:
        raise ValueError(f"{text!r}: empty host (write PORT alone for {DEFAULT_HOST})")
    host = host.removeprefix("[").removesuffix("]")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"{text!r}: port {port_text!r} is not an integer") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"{text!r}: port {port} is not in 0..65535")
    return host, port


def endpoint(text: str) -> str:
    """``[HOST:]PORT`` (:func:`split_endpoint`), kept as given."""
    try:
        split_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def seed(text: str) -> int:
    """An integer ≥ 0 (numpy's seeds)."""
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if x < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 0")
    return x


#: the port of a discovery server given without one to sim.sh, agent.sh, … (Fast DDS's own default)
DEFAULT_DISCOVERY_PORT = 11811


@dataclass(frozen=True)
class Discovery:
    """How the DDS participants of a run find each other: ``simple`` (the ROS default: each participant
    announces itself by multicast, or to the peers the environment names) or ``server`` (each is a
    client of one Fast DDS discovery server at ``host:port``: unicast only; ``port`` None: the
    launcher picks a free one, other commands use :data:`DEFAULT_DISCOVERY_PORT`)."""

    mode: str = "simple"
    host: str = "127.0.0.1"
    port: int | None = None

    @property
    def server(self) -> bool:
        return self.mode == "server"

    def address(self) -> str:
        """``HOST:PORT`` as ``ROS_DISCOVERY_SERVER`` takes it."""
        return f"{self.host}:{self.port or DEFAULT_DISCOVERY_PORT}"

    def __str__(self) -> str:
        return f"server:{self.address()}" if self.server else "simple"


def discovery(text: str) -> Discovery:
    """``simple``, ``server`` or ``server:HOST:PORT`` (HOST an IPv4 address or a host name)."""
    if text in ("simple", "server"):
        return Discovery(text)
    host, sep, port = text.removeprefix("server:").rpartition(":")
    if not text.startswith("server:") or not sep or not host or ":" in host:
        raise argparse.ArgumentTypeError(f"{text!r}: expected simple, server or server:HOST:PORT")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"{text!r}: the port must be an integer 1-65535, got {port!r}")
    return Discovery("server", host, int(port))


def byte_count(text: str) -> int:
    """A size in bytes, an integer > 0 (``--max-bag-size``, as ``ros2 bag record -b``)."""
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer number of bytes") from None
    if x <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return x


@dataclass(frozen=True)
class Option:
    """One command-line option: ``kind`` is a converter, ``flag`` (store_true), or ``bool`` (--x/--no-x)."""

    flag: str
    help: str
    commands: frozenset[str]
    kind: Callable[[str], Any] | str = "flag"
    default: Any = None
    choices: tuple[str, ...] = ()
    #: the ``simulation.*`` key this option overrides
    overrides: str | None = None
    #: formation-launch passes it on to formation-sim
    forward: bool = False

    @property
    def dest(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")


OPTIONS: tuple[Option, ...] = (
    Option("--out", "output directory (default: out/<formation>-<runner>…)", RUNNERS, Path),
    Option("--controller", "override simulation.controller", frozenset({HEADLESS}), str, None,
           ("sampled", "continuous"), overrides="controller"),
    Option("--mode", "override simulation.mode", ROS, str, None, ("lockstep", "realtime"), overrides="mode",
           forward=True),
    Option("--duration", "override simulation.duration [s]", RUNNERS | {CHECK}, positive, overrides="duration",
           forward=True),
    Option("--control-rate", "override simulation.control_rate [Hz]", RUNNERS | {CHECK}, positive,
           overrides="control_rate", forward=True),
    Option("--physics-rate", "override simulation.physics_rate [Hz] (default: kept if a multiple of the control "
           "rate, else equal to it)", RUNNERS, positive, overrides="physics_rate", forward=True),
    Option("--record-rate", "override simulation.record_rate [Hz]", RUNNERS, positive, overrides="record_rate",
           forward=True),
    Option("--seed", "override simulation.seed (integer >= 0)", RUNNERS, seed, overrides="seed", forward=True),
    Option("--step-timeout", "override simulation.step_timeout [wall s] (lockstep)", ROS, positive,
           overrides="step_timeout", forward=True),
    Option("--command-timeout", "override simulation.command_timeout [sim s] (realtime)", ROS, positive,
           overrides="command_timeout", forward=True),
    Option("--params-file", "a ROS 2 parameters file (YAML) for the agents: formation-launch hands it to every agent "
           "(--ros-args --params-file FILE, as one file serves a whole ROS system); the gains it sets (delta, gamma of "
           "/agent_<id>/formation_agent, wildcards as ROS reads them) are checked before anything starts and used by "
           "formation-headless and formation-check as the agents use them", frozenset({HEADLESS, LAUNCH, CHECK}), Path),
    Option("--spanning-tree", "reduce a cyclic sensing graph to a spanning tree (prints the dropped edges)",
           frozenset({CHECK})),
    Option("--discovery-timeout", "wall s to wait for the agents (default 30 + 1/agent)", ROS, positive,
           forward=True),
    Option("--hang-timeout", "wall s the simulator may write nothing to its log before the run is stopped as "
           "hung, exit 3 (default: the longer of the discovery and step timeouts, plus 120 s; 600 s more while it "
           "writes OUT)", frozenset({LAUNCH}), positive),
    Option("--settle", "wall s to wait after discovery", frozenset({SIM}), nonnegative, 0.3),
    Option("--resend", "lockstep: re-send an unanswered step after [wall s]", frozenset({SIM}), positive, 0.25),
    Option("--bag", "write the run's bag into DIR (must not exist) in this process: every message the simulator "
           "publishes, every wrench and /diagnostics it receives; log time = simulation time in lockstep, the wall "
           "clock in realtime (what formation-launch does when it records); and OUT/view.mcap, the display "
           "topics for viewers", frozenset({SIM}), Path),
    Option("--max-bag-size", "split the run's bag into files of at most about this many bytes, as ros2 bag record "
           "-b (default: one file, which a viewer opens whole)", ROS, byte_count, forward=True),
    Option("--wait-recorder", "wait until a bag recorder (formation-record --formation FILE) subscribes before the "
           "first step", frozenset({SIM})),
    Option("--lag-budget", "realtime: stop INCOMPLETE (exit 4) when a tick lags more than this many wall s behind "
           "the wall clock", ROS, nonnegative, 1.0, forward=True),
    Option("--ground-truth-rate", "ground-truth publication rate [Hz, sim time] (default: the record rate, at "
           "most the control rate; while recording: the control rate)", ROS, positive, forward=True),
    Option("--clock-rate", "/clock publication rate [Hz, sim time]", ROS, positive, forward=True),
    Option("--measurement-qos", "QoS of relative poses and velocities; best-effort (realtime only) costs less CPU "
           "per message (agents need -p measurement_qos:=best-effort)", ROS, str, "reliable",
           ("reliable", "best-effort"), forward=True),
    Option("--intruder-policy", "a publisher the formation does not expect on its topics: report it (default), or "
           "also refuse that topic's messages while it is there, in the simulator and every agent (docs/security.md)",
           ROS, str, "report", ("report", "refuse"), forward=True),
    Option("--secure", "every process over TCP with mutual TLS only (no UDP, no shared memory): a process without a "
           "certificate of the run's CA can neither publish nor subscribe (docs/security.md)", frozenset({LAUNCH})),
    Option("--keys", "with --secure: key directory of formation-keys init (default: a CA and keys for this run only)",
           frozenset({LAUNCH}), Path),
    Option("--marker-rate", "display rate of /formation/markers, /formation/funnels (and /tf) [Hz, sim time; 0: off]; "
           "also the live parameter marker_rate", ROS, nonnegative, 30.0, forward=True),
    Option("--foxglove", "live view: serve /formation/markers, /formation/funnels, /diagnostics and /clock at the "
           "display rate over the Foxglove WebSocket protocol (subprotocol foxglove.sdk.v1) on [HOST:]PORT; host "
           "127.0.0.1 unless given, port 0 picks a free one (docs/ros2.md, \"Live view\")", ROS, endpoint,
           forward=True),
    Option("--record", "record a bag into OUT/bag (default: on; --no-record to skip), written by the simulator "
           "(formation-sim --bag). While recording, ground truth is published at every control step unless "
           "--ground-truth-rate is given, so that formation-analyze OUT/bag reproduces the run's summary",
           frozenset({LAUNCH}), "bool", True),
    Option("--netns", "private network namespace: auto = when more than 30 DDS participants under simple discovery",
           frozenset({LAUNCH}), str, "auto", ("auto", "on", "off")),
    Option("--discovery", "simple (default: Fast DDS's announcements, multicast or LOCALHOST) or server[:HOST:PORT]: "
           "the launcher starts a Fast DDS discovery server on HOST:PORT (default 127.0.0.1 and a free port) and "
           "every process is its client: unicast only, no network namespace above 30 processes; not with --secure "
           "(docs/ros2.md)", frozenset({LAUNCH}), discovery, Discovery()),
    Option("--scheduling", "Linux scheduling policy of the run's processes: normal (default) or batch: a process "
           "woken by a message waits for a free core instead of preempting the one running. On an otherwise idle "
           "machine batch costs ~11 %% less CPU per lockstep step; beside other busy processes it runs about "
           "half as fast (docs/ros2.md). Each process's policy is in OUT/logs/processes.json",
           frozenset({LAUNCH}), str, "normal", ("normal", "batch")),
    Option("--contact", "override simulation.contact: two bodies touching is reported, or also fails the run",
           RUNNERS, str, None, ("report", "fail"), overrides="contact", forward=True),
    Option("--allow-low-rate", "run even if the control rate is below what the velocity loop needs (warn)",
           RUNNERS, forward=True),
    Option("--stop-on-violation", "stop at the first funnel violation", frozenset({HEADLESS})),
    Option("--progress-period", "wall s between progress lines", frozenset({SIM}), positive, 1.0),
    Option("--no-plots", "skip the figures", RUNNERS, forward=True),
    Option("--animate", "also write OUT/animation.gif: the formation in 3D and its funnel margins (~15 s for 5 s)",
           frozenset({HEADLESS, LAUNCH})),
    Option("--force", "write into an existing non-empty output directory, removing an earlier run's outputs first "
           "(summary, trajectory, bag, logs, figures; other files stay)", RUNNERS),
    Option("--quiet", "no progress lines", RUNNERS | {CHECK}),
)  # fmt: skip


@dataclass(frozen=True)
class RunOptions:
    """What a command was asked to do: the formation file and every option (None: not given)."""

    command: str
    file: Path | None = None
    out: Path | None = None
    controller: str | None = None
    mode: str | None = None
    duration: float | None = None
    control_rate: float | None = None
    physics_rate: float | None = None
    record_rate: float | None = None
    seed: int | None = None
    step_timeout: float | None = None
    command_timeout: float | None = None
    params_file: Path | None = None
    spanning_tree: bool = False
    discovery_timeout: float | None = None
    hang_timeout: float | None = None
    settle: float = 0.3
    resend: float = 0.25
    bag: Path | None = None
    max_bag_size: int | None = None
    wait_recorder: bool = False
    lag_budget: float = 1.0
    ground_truth_rate: float | None = None
    clock_rate: float | None = None
    measurement_qos: str = "reliable"
    intruder_policy: str = "report"
    marker_rate: float = 30.0
    foxglove: str | None = None
    secure: bool = False
    keys: Path | None = None
    record: bool = True
    netns: str = "auto"
    discovery: Discovery = Discovery()
    scheduling: str = "normal"
    contact: str | None = None
    allow_low_rate: bool = False
    stop_on_violation: bool = False
    progress_period: float = 1.0
    no_plots: bool = False
    animate: bool = False
    force: bool = False
    quiet: bool = False
    schema: bool = False

    @classmethod
    def from_namespace(cls, command: str, ns: argparse.Namespace) -> RunOptions:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(command=command, **{k: v for k, v in vars(ns).items() if k in names})

    def replace(self, **changes: Any) -> RunOptions:
        return dataclasses.replace(self, **changes)

    def overrides(self) -> dict[str, Any]:
        """The ``simulation.*`` keys this command line overrides."""
        out = {}
        for o in OPTIONS:
            value = getattr(self, o.dest)
            if o.overrides and self.command in o.commands and value is not None:
                out[o.overrides] = value
        if self.spanning_tree:
            out["spanning_tree"] = True
        return out

    def child_argv(self, command: str) -> list[str]:
        """The options this command passes on to ``command`` (formation-launch → formation-sim)."""
        argv: list[str] = []
        for o in OPTIONS:
            if not o.forward or command not in o.commands or self.command not in o.commands:
                continue
            value = getattr(self, o.dest)
            if o.kind == "flag":
                if value:
                    argv.append(o.flag)
            elif value is not None:
                argv += [o.flag, repr(value) if isinstance(value, float) else str(value)]
        return argv


class OptionParser(argparse.ArgumentParser):
    """argparse whose errors are one line (``PROG: error: …``) and exit 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message} (see --help)\n")
        sys.exit(2)


def build_parser(command: str, prog: str, description: str, *, file_required: bool = True) -> OptionParser:
    """The parser of ``command`` with every option declared for it in :data:`OPTIONS`."""
    p = OptionParser(prog=prog, description=description)
    p.add_argument("file", type=Path, nargs=None if file_required else "?", help="formation file (YAML)")
    for o in OPTIONS:
        if command not in o.commands:
            continue
        if o.kind == "flag":
            p.add_argument(o.flag, action="store_true", help=o.help)
        elif o.kind == "bool":
            p.add_argument(o.flag, action=argparse.BooleanOptionalAction, default=o.default, help=o.help)
        else:
            extra: dict[str, Any] = {"choices": o.choices} if o.choices else {}
            p.add_argument(o.flag, type=o.kind, default=o.default, help=o.help, **extra)
    return p


def without_ros_args(argv: Sequence[str]) -> list[str]:
    """``argv`` without its ROS arguments (each ``--ros-args`` up to ``--`` or the end), as
    ``rclpy.utilities.remove_ros_args`` does, without importing rclpy."""
    out: list[str] = []
    ros = False
    for arg in argv:
        if arg == "--ros-args":
            ros = True
        elif ros and arg == "--":
            ros = False
        elif not ros:
            out.append(arg)
    return out


def parse(command: str, parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> RunOptions:
    """Parse ``argv`` (exit 2 with one line on a bad option) into :class:`RunOptions`."""
    return RunOptions.from_namespace(command, parser.parse_args(argv))
