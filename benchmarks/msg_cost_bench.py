"""The cost of one message end through rclpy and Fast DDS on this machine.

    .venv/bin/python benchmarks/msg_cost_bench.py [--rounds 2000] [--only NAME,...] [--json FILE]

Two processes play one lockstep exchange, as the simulator and an agent do: per round the
*ping* process publishes ``m`` pre-serialised PoseStamped messages (one topic each) and waits
for one WrenchStamped answer; the *pong* process takes the ``m`` messages and publishes the answer.
Each process measures its own CPU time (user + system, every thread: ``getrusage``) over the
rounds after a warm-up, so the figures do not depend much on the machine's load (wall time does).
Two runs per configuration, ``m = 1`` and ``m = 8``, separate the cost that grows with the messages
from the cost per round (wake-ups, the answer):

- ``publish``: the ping's CPU per extra message, (cpu(8) − cpu(1)) / 7: one publish, plus what
  the writer does afterwards (acknowledgements, heartbeats) on its DDS threads;
- ``take``: the pong's CPU per extra message: the DDS receive thread, the wait-set or executor
  wake-ups it causes and the take into Python bytes;
- ``round``: the two processes' CPU of a round with ``m = 1``: one message each way (two publishes,
  two takes) and at least one wake-up each.

Configurations (each changes one thing from ``baseline``; ``lean`` combines the chosen ones):
receive loop (rclpy EventsExecutor ``spin_once``, SingleThreadedExecutor ``spin_once``, a plain
wait-set loop with raw takes, :func:`waitset_spin`), transport (Fast DDS shared memory and UDP,
the rmw's LOCALHOST; or UDP on 127.0.0.1 only, ``formation_msgs_py/fastdds_loopback.xml`` under
SYSTEM_DEFAULT, with that profile's writer settings: ``shipped``, what a run uses), publish mode
(synchronous, asynchronous), reliability (reliable, best effort), and the writer settings of the
profile the project ships (``formation_msgs_py/fastdds_profile.xml``). Under LOCALHOST
``FASTDDS_BUILTIN_TRANSPORTS`` changes nothing (the rmw sets its transports itself), so the
transport is chosen by the profile. Nothing is asserted; results in BENCHMARKS.md ("Cost of a
message").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "src" / "formation_msgs_py" / "formation_msgs_py" / "fastdds_profile.xml"
LOOPBACK = PROFILE.with_name("fastdds_loopback.xml")

#: name -> (receive loop, transports: DEFAULT (LOCALHOST) or loopback, RMW_FASTRTPS_PUBLICATION_MODE,
#: reliability, profile)
CONFIGS: dict[str, tuple[str, str, str, str, bool]] = {
    "baseline": ("events", "DEFAULT", "SYNCHRONOUS", "reliable", False),
    "single": ("single", "DEFAULT", "SYNCHRONOUS", "reliable", False),
    "waitset": ("waitset", "DEFAULT", "SYNCHRONOUS", "reliable", False),
    "shipped": ("events", "loopback", "SYNCHRONOUS", "reliable", True),
    "async": ("events", "DEFAULT", "ASYNCHRONOUS", "reliable", False),
    "best-effort": ("events", "DEFAULT", "SYNCHRONOUS", "best-effort", False),
    "profile": ("events", "DEFAULT", "SYNCHRONOUS", "reliable", True),
    "lean": ("waitset", "DEFAULT", "SYNCHRONOUS", "reliable", True),
    "lean-best-effort": ("waitset", "DEFAULT", "SYNCHRONOUS", "best-effort", True),
}


def waitset_spin(context: Any, subscriptions: list[Any]) -> Any:
    """A plain wait-set loop: wait up to ``timeout`` s, then take every message of every ready
    subscription as CDR bytes (no executor)."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

    ws = _rclpy.WaitSet(len(subscriptions), 0, 0, 0, 0, 0, context.handle)

    def spin(timeout: float) -> None:
        ws.clear_entities()
        for sub in subscriptions:
            ws.add_subscription(sub.handle)
        ws.wait(int(timeout * 1e9))
        ready = ws.get_ready_entities("subscription")
        for sub in subscriptions:
            if sub.handle.pointer in ready:
                while (taken := sub.handle.take_message(sub.msg_type, True)) is not None:
                    sub.callback(taken[0])

    return spin


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


# --- the two processes ------------------------------------------------------------------------


def child(role: str, loop: str, reliability: str, m: int, rounds: int, warmup: int) -> dict[str, Any]:
    """One side of the exchange; returns its CPU per round over ``rounds`` after ``warmup``."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped

    from formation_msgs_py.ros import conversions, qos

    rclpy.init()
    node = rclpy.create_node(f"bench_{role}")
    meas_qos = qos.measurements(reliability)
    pose = conversions.relative_pose_codec("1").encode(10**9, (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0))
    wrench = conversions.wrench_codec("1").encode(10**9, (0.0,) * 6)
    state = {"got": 0, "round": 0, "wakes": 0, "cpu0": 0.0, "wall0": 0.0}
    total = warmup + rounds

    def start_clock() -> None:
        state["cpu0"], state["wall0"], state["wakes"] = cpu_s(), time.monotonic(), 0

    if role == "ping":
        pubs = [node.create_publisher(PoseStamped, f"bench/pose_{k}", meas_qos) for k in range(m)]

        def on_answer(_data: bytes) -> None:
            state["got"] += 1

        subs = [(node.create_subscription(WrenchStamped, "bench/answer", on_answer, qos.CONTROL, raw=True), on_answer)]
    else:
        answer = node.create_publisher(WrenchStamped, "bench/answer", qos.CONTROL)
        pubs = [answer]

        def on_pose(_data: bytes) -> None:
            state["got"] += 1
            if state["got"] == m:
                state["got"] = 0
                answer.publish(wrench)
                state["round"] += 1
                if state["round"] == warmup:
                    start_clock()

        subs = [
            (node.create_subscription(PoseStamped, f"bench/pose_{k}", on_pose, meas_qos, raw=True), on_pose)
            for k in range(m)
        ]
    if loop == "waitset":
        spin_waitset = waitset_spin(node.context, [s for s, _ in subs])

        def spin(timeout: float) -> None:
            state["wakes"] += 1
            spin_waitset(timeout)
    else:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.experimental import EventsExecutor

        executor = EventsExecutor() if loop == "events" else SingleThreadedExecutor()
        executor.add_node(node)

        def spin(timeout: float) -> None:
            state["wakes"] += 1
            executor.spin_once(timeout_sec=timeout)

    deadline = time.monotonic() + 60.0
    if role == "ping":
        while any(p.get_subscription_count() == 0 for p in pubs) or subs[0][0].get_publisher_count() == 0:
            if time.monotonic() > deadline:
                raise RuntimeError("ping: no pong matched within 60 s")
            spin(0.05)
        time.sleep(0.5)  # the pong's side of discovery
        for k in range(total):
            if k == warmup:
                start_clock()
            for p in pubs:
                p.publish(pose)
            while state["got"] <= k:
                spin(1.0)
                if time.monotonic() > deadline + 120.0:
                    raise RuntimeError(f"ping: no answer to round {k}")
    else:
        while state["round"] < total:
            spin(1.0)
            if time.monotonic() > deadline + 120.0:
                raise RuntimeError(f"pong: stalled at round {state['round']}")
        time.sleep(0.3)  # let the last acknowledgements go out before the node goes
    cpu = cpu_s() - state["cpu0"]
    wall = time.monotonic() - state["wall0"]
    node.destroy_node()
    rclpy.try_shutdown()
    return {
        "cpu_per_round_us": 1e6 * cpu / rounds,
        "wall_per_round_us": 1e6 * wall / rounds,
        "wakes_per_round": state["wakes"] / rounds,
    }


# --- the orchestration ------------------------------------------------------------------------


def run_pair(name: str, m: int, rounds: int, warmup: int, domain: int, profile_file: Path) -> dict[str, Any]:
    loop, transports, mode, reliability, profile = CONFIGS[name]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("FASTDDS_BUILTIN_TRANSPORTS", None)
    env["RMW_FASTRTPS_PUBLICATION_MODE"] = mode
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    if profile:
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile_file)
    if transports == "loopback":  # UDP on 127.0.0.1 only, with the profile's writers
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="SYSTEM_DEFAULT", FASTRTPS_DEFAULT_PROFILES_FILE=str(LOOPBACK))
    args = [
        sys.executable,
        __file__,
        "--child",
        "",
        "--loop",
        loop,
        "--reliability",
        reliability,
        "--m",
        str(m),
        "--rounds",
        str(rounds),
        "--warmup",
        str(warmup),
    ]
    procs = {}
    for role in ("pong", "ping"):
        a = list(args)
        a[3] = role
        procs[role] = subprocess.Popen(
            a, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
        )
    out: dict[str, Any] = {}
    for role, p in procs.items():
        try:
            stdout, stderr = p.communicate(timeout=300)
        except subprocess.TimeoutExpired:
            p.kill()
            stdout, stderr = p.communicate()
        if p.returncode != 0:
            raise RuntimeError(f"{name} m={m} {role}: exit {p.returncode}: {stderr[-800:]}")
        out[role] = json.loads(stdout.strip().splitlines()[-1])
    return out


def measure(name: str, rounds: int, warmup: int, domain: int, profile_file: Path) -> dict[str, Any]:
    load = os.getloadavg()[0]
    one = run_pair(name, 1, rounds, warmup, domain, profile_file)
    eight = run_pair(name, 8, rounds, warmup, domain, profile_file)
    return {
        "config": dict(zip(("loop", "transports", "publish_mode", "reliability", "profile"), CONFIGS[name])),
        "publish_us": (eight["ping"]["cpu_per_round_us"] - one["ping"]["cpu_per_round_us"]) / 7,
        "take_us": (eight["pong"]["cpu_per_round_us"] - one["pong"]["cpu_per_round_us"]) / 7,
        "round_us": one["ping"]["cpu_per_round_us"] + one["pong"]["cpu_per_round_us"],
        "round_wall_us": one["ping"]["wall_per_round_us"],
        "pong_wakes_m8": eight["pong"]["wakes_per_round"],
        "load_1min": load,
        "runs": {"m1": one, "m8": eight},
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=2000)
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--only", help=f"comma-separated subset of {', '.join(CONFIGS)}")
    p.add_argument("--json", type=Path, help="write every figure here")
    p.add_argument("--profile", type=Path, default=PROFILE, help="Fast DDS profile of the 'profile' and 'lean' runs")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--loop", default="events", help=argparse.SUPPRESS)
    p.add_argument("--reliability", default="reliable", help=argparse.SUPPRESS)
    p.add_argument("--m", type=int, default=1, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.loop, args.reliability, args.m, args.rounds, args.warmup)))
        return 0
    from formation_sim.launch.dds_env import reserve_domain_id

    domain = int(os.environ.get("ROS_DOMAIN_ID") or reserve_domain_id())
    names = args.only.split(",") if args.only else list(CONFIGS)
    results = {}
    print(
        f"{'config':<18} {'publish µs':>10} {'take µs':>8} {'round µs':>9} {'wall/round µs':>13} "
        f"{'wakes (m=8)':>11} {'load':>5}"
    )
    for name in names:
        r = measure(name, args.rounds, args.warmup, domain, args.profile)
        results[name] = r
        print(
            f"{name:<18} {r['publish_us']:>10.1f} {r['take_us']:>8.1f} {r['round_us']:>9.1f} "
            f"{r['round_wall_us']:>13.1f} {r['pong_wakes_m8']:>11.2f} {r['load_1min']:>5.1f}",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
