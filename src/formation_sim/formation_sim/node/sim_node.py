"""The simulator node: ``formation-sim FILE [--mode lockstep|realtime] [--out DIR] …``.

Plays the world with :class:`formation_sim.core.simulation.Simulation`, the code path of the
headless runner (docs/ros2.md). Per control step k it publishes what ``Simulation.sense()``
returns (relative poses of the tree pairs within sensing radius, noisy body twists), ``/clock``
and the ground truth, and collects every agent's wrench. When to advance is decided by the
ROS-free policy of :mod:`formation_sim.node.stepping`; this module is the thin node around it.

- **lockstep**: waits for every agent's WrenchStamped whose stamp equals step k's (integer ns),
  then ``Simulation.advance(u)``. Identical to ``run_headless`` sampled at the same rate. Steps not
  answered within ``--resend`` wall seconds are published again to the missing agents; an agent
  silent for ``simulation.step_timeout`` wall seconds gets a last resend and, still silent
  ``stepping.LAST_CALL`` s later, is named: INCOMPLETE, exit 3. Every answer must agree with the
  witness (:mod:`formation_sim.node.witness`: the agent's controller run here on the bytes it was
  sent, decoded as it decodes them, at its time, in its code form, with its gains, which the node
  reads from every agent's parameters before the first step and follows on ``/parameter_events``);
  one that differs is counted (``answer_mismatch``), not applied, and the step is re-sent; the same
  refused answer to the resend names the agent: INCOMPLETE, exit 5.
- **realtime**: ticks at the control rate on the wall clock; each tick integrates the previous
  period with the latest wrench of each agent held (zero-order hold), then publishes the new
  measurements. A wrench older than ``simulation.command_timeout`` (sim time) is replaced by
  zero; every tick without an agent's answer (stale or zeroed wrench) and every late tick is a
  counted fault (summary ``faults``, formation_core.faults). A run
  lagging more than ``--lag-budget`` wall seconds behind the wall clock stops INCOMPLETE (exit 4).

Funnels are checked on ground truth at every control step inside this node; ``/clock`` and
``formation/ground_truth`` are published at ``--clock-rate`` / ``--ground-truth-rate`` (default:
the record rate, at most the control rate; ``/clock`` at most 10 Hz in realtime). The run's
outputs (docs/outputs.md) go to ``--out``, also when the run is interrupted (SIGINT/SIGTERM:
summary and trajectory, no figures, so that the stop is fast). The node never needs its stdout
to finish.

This module is the process (options, start, stop, outputs); the rclpy node is
:mod:`formation_sim.node.simulator_node`'s, the two stepping loops :mod:`formation_sim.node.runner`'s.

``--bag DIR`` (what formation-launch gives a recorded run): the simulator is the run's recorder
(:mod:`formation_sim.node.run_bag`). Every publisher the node creates writes what it sends into the
bag, the wrench and /diagnostics subscriptions what they receive (log time: simulation time in
lockstep, the wall clock of sending or receipt in realtime); a bag I/O error ends the run
INCOMPLETE (exit 4). ``--wait-recorder``: wait before the first step until a recorder
(``formation-record --formation FILE``) subscribes to the ground truth.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor

from formation_bag.contract import KEY_FORMATION_FILE, KEY_FORMATION_YAML
from formation_bag.foxglove_server import SUBPROTOCOL, LiveView, LiveViewError
from formation_core.errors import BagError
from formation_core.formation import FormationSpec
from formation_core.options import RunOptions
from formation_core.verdict import ExitCode, Incomplete, guarded
from formation_deploy.transport_check import InsecureTransportError, check_secure_transport
from formation_ros import shutdown
from formation_ros.rclpy_internals import RCLError
from formation_sim.core.links import link_summary
from formation_sim.core.summary import RunnerKeys
from formation_sim.node.display import DEFAULT_MARKER_RATE, declare_simulator_parameters
from formation_sim.node.run_bag import VIEW_FILE, RunBag
from formation_sim.node.runner import Runner, RunStoppedError, StopRequestedError
from formation_sim.node.sim_options import sim_preflight
from formation_sim.node.simulator_node import SimNode
from formation_sim.node.stepping import (
    ParticipantMissingError,
    WrongAnswerError,
)
from formation_sim.preflight import Prepared
from formation_sim.views.outputs import format_summary, write_outputs


def bag_custom_data(spec: FormationSpec, args: RunOptions) -> dict[str, str]:
    """custom_data of the run's bag: the formation file and the run's effective settings, as
    formation-record --formation FILE --meta mode=… control_rate=… duration=… stores them."""
    s = spec.simulation
    assert args.file is not None  # preflight loaded it
    return {
        "mode": args.mode or s.mode,
        "control_rate": repr(s.control_rate),
        "duration": repr(s.duration),
        KEY_FORMATION_YAML: args.file.read_text(encoding="utf-8"),
        KEY_FORMATION_FILE: args.file.name,
    }


def _interrupted(runner: Runner | None) -> Incomplete:
    t = runner.sim.t if runner is not None else 0.0
    return Incomplete(ExitCode.INTERRUPTED, f"interrupted (SIGINT/SIGTERM) at t={t:.4f} s")


class SimProcess:
    """The parts of one simulator process, made in order by :meth:`start` and released by :meth:`release`
    whatever got made (a stop can come at any point)."""

    def __init__(
        self, spec: FormationSpec, args: RunOptions, raw: list[str], bag: RunBag | None, live: LiveView | None
    ) -> None:
        self.spec, self.args, self.raw, self.bag, self.live = spec, args, raw, bag, live
        self.node: SimNode | None = None
        self.executor: Any = None
        self.runner: Runner | None = None
        self.extra: RunnerKeys = {}

    def start(self) -> Runner:
        """rclpy, the node (secure transport checked), the executor, the runner; every agent matched."""
        spec, args = self.spec, self.args
        shutdown.init(self.raw)
        self.node = node = SimNode(spec, args.measurement_qos, args.intruder_policy, self.bag)
        check_secure_transport()
        node.display = declare_simulator_parameters(node, spec, args, self.live)
        self.executor = EventsExecutor(context=node.context)
        self.executor.add_node(node)
        self.runner = runner = Runner(node, self.executor, spec, args)
        timeout = args.discovery_timeout or 30.0 + len(spec.agents)
        t_disc = time.monotonic()
        runner.wait_for_agents(timeout)
        self.extra["discovery_s"] = time.monotonic() - t_disc
        print(f"formation-sim: all {len(spec.agents)} agents matched in {self.extra['discovery_s']:.2f} s", flush=True)
        return runner

    def stopped_by(self, exc: BaseException) -> Incomplete | None:
        """How a run stopped by ``exc`` (out of :meth:`start` or the stepping) ends; None: no stop but a bug.

        A missing agent: exit 3 naming it; a run that cannot go on: its reason; an insecure transport:
        invalid input; SIGINT/SIGTERM (also a publish or wait it cut short): interrupted."""
        if isinstance(exc, (ParticipantMissingError, WrongAnswerError, RunStoppedError, InsecureTransportError)):
            print(f"formation-sim: ERROR: {exc}", file=sys.stderr, flush=True)
        if isinstance(exc, ParticipantMissingError):
            self.extra["missing"] = exc.names
            return Incomplete(ExitCode.PROCESS_DIED, str(exc))
        if isinstance(exc, WrongAnswerError):
            self.extra["wrong_answers"] = exc.names
            return Incomplete(ExitCode.WRONG_ANSWER, str(exc))
        if isinstance(exc, RunStoppedError):
            return exc.incomplete
        if isinstance(exc, InsecureTransportError):
            return Incomplete(ExitCode.INVALID, str(exc))  # before any runner: the exit status alone
        if isinstance(exc, (KeyboardInterrupt, ExternalShutdownException, StopRequestedError)):
            return _interrupted(self.runner)
        if self.node is not None and not rclpy.ok(context=self.node.context):
            return _interrupted(self.runner)  # a publish or wait cut short by SIGINT/SIGTERM
        return None

    def release(self, incomplete: Incomplete | None) -> tuple[float, Incomplete | None]:
        """Shut executor, node and rclpy down and close the bag; (stepping wall time [s], the run's
        Incomplete: a bag that failed to write makes a finished run INCOMPLETE)."""
        wall = time.monotonic() - self.runner.started if self.runner is not None else 0.0
        if self.executor is not None:
            self.executor.shutdown()  # else it keeps the node's DDS participant past destroy_node (agent_node.spin)
        if self.node is not None:
            self.node.destroy_node()
        try:
            rclpy.try_shutdown()
        except RCLError:
            pass  # rclpy's signal handler shut the context down at the same moment (SIGINT/SIGTERM)
        if self.live is not None:
            self.live.close()
        bag = self.bag
        if bag is not None:
            stopped = None if incomplete is None else (int(incomplete.code), incomplete.reason)
            sim = None if self.runner is None else self.runner.sim
            links = None if sim is None or sim.links is None else link_summary(sim.links, sim.view)
            self.extra["recorder"] = bag.close(stopped, links)
            if bag.failed is not None and incomplete is None:
                print(f"formation-sim: ERROR: {bag.failed}", file=sys.stderr, flush=True)
                incomplete = Incomplete(ExitCode.INCOMPLETE, bag.failed)
        return wall, incomplete


@guarded("formation-sim")
def main(argv: list[str] | None = None, *, prepared: Prepared | None = None) -> int:
    """The simulator process (``formation_sim.cli.sim.sim`` pre-flights ``argv`` first)."""
    raw = list(sys.argv if argv is None else [sys.argv[0], *argv])
    run = prepared or sim_preflight(raw)
    spec, out, args = run.spec, run.out, run.options
    assert out is not None  # sim_preflight names OUT (formation-sim --out, or its default)
    for msg in run.warnings:
        print(f"formation-sim: warning: {msg}", file=sys.stderr)
    s = spec.simulation
    print(
        f"formation-sim: {spec.name}, {len(spec.agents)} agents, {args.mode} at {s.control_rate:g} Hz "
        f"(physics {s.physics_rate:g} Hz), {s.duration:g} s; outputs in {out}/",
        flush=True,
    )
    live = None
    if args.foxglove is not None:  # before anything is written: a port in use is an invalid input
        try:
            live = LiveView(args.foxglove, name="formation-sim")
        except LiveViewError as exc:
            print(f"formation-sim: {exc}", file=sys.stderr, flush=True)
            return ExitCode.INVALID
        print(f"formation-sim: live view on {live.url} (Foxglove WebSocket, {SUBPROTOCOL})", flush=True)
    bag = None
    if args.bag is not None:
        try:
            realtime = args.mode == "realtime"
            bag = RunBag(
                args.bag,
                bag_custom_data(spec, args),
                wall_log_time=realtime,
                max_bytes=args.max_bag_size,
                view=out / VIEW_FILE,  # what a viewer shows, at the display rate (docs/bags.md)
                view_rate=args.marker_rate or DEFAULT_MARKER_RATE,
            )
        except (BagError, OSError) as exc:
            print(f"formation-sim: {exc}", file=sys.stderr, flush=True)
            return ExitCode.INVALID
    proc = SimProcess(spec, args, raw, bag, live)
    incomplete: Incomplete | None = None
    try:
        runner = proc.start()
        if args.mode == "lockstep":
            runner.run_lockstep()
        else:
            runner.run_realtime()
    except (Exception, KeyboardInterrupt) as exc:
        incomplete = proc.stopped_by(exc)
        if incomplete is None:
            raise
    finally:
        wall, incomplete = proc.release(incomplete)
    code: int
    if proc.runner is None:
        code = ExitCode.INCOMPLETE if incomplete is None else incomplete.code
    else:
        code = _write_outputs(proc.runner, out, args, wall, incomplete, proc.extra)
    if proc.node is None:
        return code  # stopped while starting: a node half made is released by the interpreter's finalization
    shutdown.exit_now(code, proc.node.context)


def _write_outputs(
    runner: Runner, out: Path, args: RunOptions, wall: float, incomplete: Incomplete | None, extra: RunnerKeys
) -> int:
    """Write OUT (summary, trajectory, figures unless stopped early or --no-plots), print the summary;
    the exit status."""
    summary = runner.summary(wall, incomplete, extra)
    plots = not args.no_plots and incomplete is None
    what = "summary, trajectory" + (", figures" if plots else "")
    early = "" if plots or args.no_plots else "; stopped early: no figures"
    done = f"formation-sim: stepping done: {runner.step} steps in {wall:.2f} s"
    print(f"{done}; writing {out}/ ({what}{early})", flush=True)
    t_out = time.monotonic()
    try:
        figures = write_outputs(out, runner.recorder, summary, plots=plots)
    except OSError as exc:
        print(f"formation-sim: INCOMPLETE: could not write {out}: {exc}", file=sys.stderr, flush=True)
        return ExitCode.INCOMPLETE
    figures_note = f" (figures {figures:.2f} s)" if plots else ""
    print(f"formation-sim: {out}/ written in {time.monotonic() - t_out:.2f} s{figures_note}", flush=True)
    print(format_summary(summary), flush=True)
    return summary["exit_status"]


if __name__ == "__main__":
    sys.exit(main())
