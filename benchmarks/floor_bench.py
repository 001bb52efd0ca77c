"""The floor of a lockstep or realtime step: the formation's messages with no work.

    .venv/bin/python benchmarks/floor_bench.py [FORMATION] [--steps 5000] [--warmup 500]
        [--rate HZ] [--clock-every 10] [--ground-truth] [--json FILE]

One *simulator* process and one process per agent, as a run starts them, exchange exactly the
messages of a run of FORMATION (default ``config/paper_5agents.yaml``), with the same topics, QoS,
CDR bytes, Fast DDS profile and executor (rclpy's EventsExecutor, one ``spin_once`` per callback)
as formation-sim and formation-agent, and nothing else: per step the simulator publishes, agent by
agent, the relative pose of each tree neighbour and then the agent's velocity (and ``/clock``
every ``--clock-every`` steps, which every agent takes through rclpy's time source as in a run;
``--ground-truth``: the ground truth at every step, with no subscriber). An agent answers with its
wrench once all of its step's messages are in. No dynamics, no controller, no checks, no bag.

- lockstep (default): the simulator waits for the five wrenches before the next step;
- ``--rate HZ``: realtime: the simulator steps on the wall clock at HZ and counts the steps whose
  every wrench was in before the next tick, which itself came within half a period of its time
  (the summary's ``on_time_fraction_all``).

Each process measures its own CPU (``getrusage``, every thread) over ``--steps`` steps after
``--warmup``; the figure is their sum per step, which is what the lockstep acceptance figure measures
for a whole run (``OUT/logs/processes.json``), minus everything a run computes. Nothing is
asserted; results in BENCHMARKS.md ("Lockstep ROS 2 runs", "Realtime ROS 2 runs").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DEFAULT_FORMATION = REPO / "config" / "paper_5agents.yaml"
#: an agent that hears no step for this long (wall s) ends: its simulator is gone
IDLE_TIMEOUT_S = 300.0


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _node(name: str, namespace: str = "", sim_time: bool = False) -> Any:
    import rclpy
    from rclpy.parameter import Parameter

    rclpy.init()
    overrides = [Parameter("use_sim_time", Parameter.Type.BOOL, True)] if sim_time else []
    return rclpy.create_node(name, namespace=namespace, parameter_overrides=overrides)


def agent(formation: Path, agent_id: str, steps: int, warmup: int, clock: bool) -> dict[str, Any]:
    """Take the step's messages; answer the wrench once all are in; CPU over ``steps`` steps."""
    from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
    from rclpy.experimental import EventsExecutor

    from formation_core.formation import agent_view
    from formation_core.spec import load_formation
    from formation_msgs_py import topics
    from formation_msgs_py.codec import stamp_of
    from formation_msgs_py.ros import conversions, qos

    view = agent_view(load_formation(formation), agent_id)
    node = _node(f"floor_agent_{agent_id}", sim_time=clock)
    wrench = conversions.wrench_codec(agent_id)
    pub = node.create_publisher(WrenchStamped, topics.wrench(agent_id), qos.CONTROL)
    need = len(view.neighbours) + 1
    state = {"ns": -1, "got": 0, "steps": 0, "cpu0": 0.0, "wall0": 0.0}
    zero = (0.0,) * 6

    def on_message(data: bytes) -> None:
        ns = stamp_of(data)
        if ns != state["ns"]:
            state["ns"], state["got"] = ns, 0
        state["got"] += 1
        if state["got"] == need:
            pub.publish(wrench.encode(ns, zero))
            state["steps"] += 1
            if state["steps"] == warmup:
                state["cpu0"], state["wall0"] = cpu_s(), time.monotonic()

    subs = [node.create_subscription(TwistStamped, topics.velocity(agent_id), on_message, qos.CONTROL, raw=True)]
    for j in view.neighbours:
        subs.append(
            node.create_subscription(PoseStamped, topics.relative_pose(agent_id, j), on_message, qos.CONTROL, raw=True)
        )
    executor = EventsExecutor(context=node.context)
    executor.add_node(node)
    last = time.monotonic()
    while state["steps"] < warmup + steps:
        seen = state["steps"]
        executor.spin_once(timeout_sec=1.0)
        if state["steps"] != seen:
            last = time.monotonic()
        elif not node.context.ok() or time.monotonic() - last > IDLE_TIMEOUT_S:
            raise RuntimeError(f"agent {agent_id}: stopped, or no step for {IDLE_TIMEOUT_S:g} s (no simulator)")
    cpu, wall = cpu_s() - state["cpu0"], time.monotonic() - state["wall0"]
    time.sleep(0.5)  # the simulator's last takes before the writer goes
    executor.shutdown()
    node.destroy_node()
    return {"cpu_s": cpu, "wall_s": wall}


def simulator(
    formation: Path, steps: int, warmup: int, rate: float, clock_every: int, ground_truth: bool, control_rate: float
) -> dict[str, Any]:
    """Publish each step's measurements agent by agent; lockstep (rate 0) or on the wall clock."""
    from geometry_msgs.msg import PoseArray, PoseStamped, TwistStamped, WrenchStamped
    from rclpy.experimental import EventsExecutor
    from rosgraph_msgs.msg import Clock

    from formation_core.formation import agent_view
    from formation_core.spec import load_formation
    from formation_msgs_py import topics
    from formation_msgs_py.codec import stamp_of
    from formation_msgs_py.ros import conversions, qos

    spec = load_formation(formation)
    node = _node("floor_sim")
    ids = [a.id for a in spec.agents]
    out: list[tuple[Any, Any, tuple[float, ...]]] = []  # publisher, codec, values, in the order a run sends them
    pose_values = (1.0, 0.5, 0.25, 0.0, 0.0, 0.0, 1.0)
    for i in ids:
        for j in agent_view(spec, i).neighbours:
            pub = node.create_publisher(PoseStamped, topics.relative_pose(i, j), qos.CONTROL)
            out.append((pub, conversions.relative_pose_codec(i), pose_values))
        out.append(
            (
                node.create_publisher(TwistStamped, topics.velocity(i), qos.CONTROL),
                conversions.twist_codec(i),
                (0.0,) * 6,
            )
        )
    clock_pub = node.create_publisher(Clock, topics.CLOCK, qos.CLOCK)
    gt_pub = node.create_publisher(PoseArray, topics.GROUND_TRUTH, qos.GROUND_TRUTH) if ground_truth else None
    answered: dict[int, int] = {}

    def on_wrench(data: bytes) -> None:
        ns = stamp_of(data)
        answered[ns] = answered.get(ns, 0) + 1

    for i in ids:
        node.create_subscription(WrenchStamped, topics.wrench(i), on_wrench, qos.CONTROL, raw=True)
    executor = EventsExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + 120.0
    while any(p.get_subscription_count() == 0 for p, _, _ in out) or node.count_publishers(topics.wrench(ids[-1])) == 0:
        if time.monotonic() > deadline:
            raise RuntimeError("simulator: the agents did not match within 120 s")
        executor.spin_once(timeout_sec=0.05)
    time.sleep(1.0)  # the agents' side of discovery
    p = [[0.0, 0.0, 0.0]] * len(ids)
    R = [[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]] * len(ids)
    dt_ns = round(1e9 / control_rate)
    period = 1.0 / rate if rate else 0.0
    n, on_time, cpu0, wall0, t0 = len(ids), 0, 0.0, 0.0, time.monotonic()
    for k in range(warmup + steps + 1):
        ns = (k + 1) * dt_ns
        if period:  # realtime: tick k at t0 + k·period; step k-1 on time if answered and this tick not late
            tick = t0 + k * period
            while (now := time.monotonic()) < tick:
                executor.spin_once(timeout_sec=tick - now)
                if not node.context.ok():
                    raise RuntimeError("simulator: stopped")
            if k > warmup and answered.get(ns - dt_ns, 0) == n and now - tick < period / 2:
                on_time += 1
        if k == warmup:
            cpu0, wall0 = cpu_s(), time.monotonic()
            print("WARM", flush=True)  # the parent samples the CPU of processes that do not report theirs
        if k == warmup + steps:
            print("DONE", flush=True)
            break
        for pub, codec, values in out:
            pub.publish(codec.encode(ns, values))
        if k % clock_every == 0:
            clock_pub.publish(conversions.clock_bytes(ns))
        if gt_pub is not None:
            gt_pub.publish(conversions.ground_truth_bytes(ns, p, R))
        if not period:
            while answered.get(ns, 0) < n:
                executor.spin_once(timeout_sec=1.0)
                if not node.context.ok() or time.monotonic() > deadline + 600.0:
                    raise RuntimeError(f"simulator: stopped, or step {k} unanswered")
        answered.pop(ns - 2 * dt_ns, None)
    cpu, wall = cpu_s() - cpu0, time.monotonic() - wall0
    time.sleep(0.5)
    executor.shutdown()
    node.destroy_node()
    res: dict[str, Any] = {"cpu_s": cpu, "wall_s": wall}
    if period:
        res["on_time_fraction"] = on_time / steps
    return res


def run(args: argparse.Namespace) -> dict[str, Any]:
    from formation_core.spec import load_formation
    from formation_sim.launch.dds_env import run_environment
    from formation_sim.launch.supervisor import die_with_parent

    spec = load_formation(args.formation)
    log_dir = Path(os.environ.get("ROS_LOG_DIR") or "/tmp/floor_bench_logs")
    env = run_environment(dict(os.environ), log_dir=log_dir)
    common = [sys.executable, __file__, str(args.formation), "--steps", str(args.steps), "--warmup", str(args.warmup)]
    procs: dict[str, subprocess.Popen[str]] = {}
    try:
        for a in spec.agents:
            cmd = [*common, "--child", f"agent:{a.id}"] + (
                ["--clock-every", str(args.clock_every)] if args.clock_every else []
            )
            if args.real_agents:  # formation-agent as the launcher starts it (compiled controller at >= 1 kHz)
                cmd = [
                    str(Path(sys.executable).with_name("formation-agent")),
                    "--ros-args",
                    "-p",
                    f"formation_file:={args.formation.resolve()}",
                    "-p",
                    f"agent_id:='{a.id}'",
                    "-p",
                    "use_sim_time:=true",
                ]
            procs[f"agent_{a.id}"] = subprocess.Popen(
                cmd,
                env=dict(env, NUMBA_DISABLE_JIT="0"),
                stdout=subprocess.PIPE if not args.real_agents else subprocess.DEVNULL,
                stderr=subprocess.PIPE if not args.real_agents else subprocess.DEVNULL,
                text=True,
                start_new_session=True,
                preexec_fn=die_with_parent,
            )
        cmd = [*common, "--child", "sim", "--rate", str(args.rate), "--clock-every", str(args.clock_every)]
        cmd += ["--control-rate", str(args.rate or spec.simulation.control_rate)]
        if args.ground_truth:
            cmd.append("--ground-truth")
        procs["sim"] = subprocess.Popen(
            cmd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=die_with_parent,
        )
        results: dict[str, Any] = {}
        if args.real_agents:
            agents = {n: p for n, p in procs.items() if n != "sim"}
            marks = []
            assert procs["sim"].stdout is not None
            for line in procs["sim"].stdout:
                if line.strip() in ("WARM", "DONE"):
                    marks.append({n: _proc_cpu(p.pid) for n, p in agents.items()})
                    if len(marks) == 2:
                        break
            for n, p in agents.items():
                p.send_signal(signal.SIGINT)
                p.wait(timeout=30)
                results[n] = {"cpu_s": marks[1][n] - marks[0][n]}
            procs = {"sim": procs["sim"]}
        for name, p in sorted(procs.items(), key=lambda item: item[0] != "sim"):  # the simulator's error first
            stdout, stderr = p.communicate(timeout=3600)
            if p.returncode != 0:
                raise RuntimeError(f"{name}: exit {p.returncode}: {stderr[-800:]}")
            results[name] = json.loads(stdout.strip().splitlines()[-1])
    finally:  # only ours, by PID: SIGINT (a clean stop frees Fast DDS's /dev/shm segments), then SIGKILL
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    total = sum(r["cpu_s"] for r in results.values())
    sim = results["sim"]
    summary = {
        "formation": str(args.formation),
        "agents": len(spec.agents),
        "mode": f"realtime {args.rate:g} Hz" if args.rate else "lockstep",
        "steps": args.steps,
        "cpu_per_step_ms": 1e3 * total / args.steps,
        "sim_cpu_per_step_ms": 1e3 * sim["cpu_s"] / args.steps,
        "agents_cpu_per_step_ms": 1e3 * (total - sim["cpu_s"]) / args.steps,
        "wall_per_step_ms": 1e3 * sim["wall_s"] / args.steps,
        "load_1min": os.getloadavg()[0],
        "processes": results,
    }
    if args.rate:
        summary["on_time_fraction"] = sim["on_time_fraction"]
    else:
        summary["real_time_factor_at_control_rate"] = 1.0 / (spec.simulation.control_rate * sim["wall_s"] / args.steps)
    return summary


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("formation", nargs="?", type=Path, default=DEFAULT_FORMATION)
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--warmup", type=int, default=500)
    p.add_argument("--rate", type=float, default=0.0, help="realtime at this rate [Hz]; 0: lockstep")
    p.add_argument("--clock-every", type=int, default=10, help="/clock every this many steps (0: none, no time source)")
    p.add_argument("--ground-truth", action="store_true", help="publish the ground truth at every step (no subscriber)")
    p.add_argument("--real-agents", action="store_true", help="formation-agent processes instead of the floor's")
    p.add_argument("--json", type=Path, help="write the figures here")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--control-rate", type=float, default=0.0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        if args.child == "sim":
            res = simulator(
                args.formation,
                args.steps,
                args.warmup,
                args.rate,
                args.clock_every or 1 << 62,
                args.ground_truth,
                args.control_rate,
            )
        else:
            res = agent(args.formation, args.child.split(":", 1)[1], args.steps, args.warmup, bool(args.clock_every))
        print(json.dumps(res))
        return 0
    s = run(args)
    line = (
        f"{s['mode']}, {s['agents']} agents: {s['cpu_per_step_ms']:.2f} ms of CPU per step "
        f"(simulator {s['sim_cpu_per_step_ms']:.2f}, agents {s['agents_cpu_per_step_ms']:.2f}), "
        f"wall {s['wall_per_step_ms']:.2f} ms per step"
    )
    if "on_time_fraction" in s:
        line += f", on time {100 * s['on_time_fraction']:.1f} %"
    else:
        line += f", real-time factor {s['real_time_factor_at_control_rate']:.3f}"
    print(f"{line}; load {s['load_1min']:.1f}")
    if args.json:
        args.json.write_text(json.dumps(s, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
