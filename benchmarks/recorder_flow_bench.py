"""Lossless lockstep recording measured two ways (issue 8, "measure and choose"); results in BENCHMARKS.md.

    .venv/bin/python benchmarks/recorder_flow_bench.py [--design ack blocking] [--load N] [--durations 0.05 0.55]

- ``ack`` (what formation-launch does): ``formation-sim --wait-recorder``; the recorder publishes
  ``formation/recorder_ack`` (the stamp up to which it holds every velocity and wrench) and the
  simulator does not step more than one step past it.
- ``blocking``: no acknowledgement; flow control instead. Every DDS writer and reader is reliable,
  KEEP_ALL, with at most ``--samples`` samples (a Fast DDS profile written here, applied with
  ``RMW_FASTRTPS_USE_QOS_FROM_XML=1``; positive acknowledgements on), so a writer whose reader (the
  recorder) has not taken its samples blocks in ``publish()`` (up to 30 s) instead of dropping.

Each run is the paper preset through formation-launch with recording (``--no-plots --quiet``).
Printed per design and duration: the CPU of every process (``logs/processes.json``), messages
written and not recorded (summary.json ``recorder``), the wall split and the load; then the CPU
per step, (CPU of the longest − CPU of the shortest duration) / steps between them. ``--load N``
adds N busy-loop processes (started and stopped here, by PID); ``--pause-recorder S`` stops the
recorder (SIGSTOP) for S wall seconds once stepping has begun: a lossless design must wait for it.
Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PYTHON = REPO / ".venv" / "bin" / "python"
PAPER = REPO / "config" / "paper_5agents.yaml"

#: formation-launch without --wait-recorder (the simulator then steps without the recorder)
NO_ACK_LAUNCH = """
import sys
import formation_sim.launch as launch
plain = launch._sim_args
launch._sim_args = lambda *a: [x for x in plain(*a) if x != "--wait-recorder"] + ["--settle", "2"]
sys.exit(launch.main(sys.argv[1:]))
"""

#: one DDS endpoint kind (data_writer or data_reader): reliable, KEEP_ALL, at most {n} samples
ENDPOINT = """  <{kind} profile_name="blocking_{kind}" is_default_profile="true">
    <topic>
      <historyQos><kind>KEEP_ALL</kind></historyQos>
      <resourceLimitsQos>
        <max_samples>{n}</max_samples><max_instances>1</max_instances>
        <max_samples_per_instance>{n}</max_samples_per_instance><allocated_samples>{n}</allocated_samples>
      </resourceLimitsQos>
    </topic>
    <qos>
      <reliability><kind>RELIABLE</kind>{blocking}</reliability>
      <durability><kind>VOLATILE</kind></durability>
    </qos>
  </{kind}>
"""


def blocking_profile(n: int) -> str:
    """The Fast DDS profile of the ``blocking`` design: a full writer blocks up to 30 s in publish()."""
    wait = "<max_blocking_time><sec>30</sec></max_blocking_time>"
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">\n'
        + ENDPOINT.format(kind="data_writer", n=n, blocking=wait)
        + ENDPOINT.format(kind="data_reader", n=n, blocking="")
        + "</profiles>\n"
    )


def _recorder_pid(out: Path) -> int | None:
    for d in Path("/proc").iterdir():
        try:
            cmd = (d / "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if "formation-record" in cmd and str(out) in cmd:
            return int(d.name)
    return None


def _pause_recorder(out: Path, seconds: float, proc: subprocess.Popen) -> None:
    """SIGSTOP the run's recorder for ``seconds`` once the simulator steps (then SIGCONT)."""
    log = out / "logs" / "sim.log"
    while proc.poll() is None and not (log.exists() and "progress" in log.read_text(errors="replace")):
        time.sleep(0.05)
    pid = _recorder_pid(out)
    if pid is None or proc.poll() is not None:
        return
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def run(design: str, duration: float, out: Path, samples: int, pause: float = 0.0) -> dict[str, Any]:
    env = dict(os.environ)
    argv = [str(PAPER), "--duration", repr(duration), "--no-plots", "--quiet", "--force", "--out", str(out)]
    if design == "ack":
        cmd = [str(PYTHON), "-m", "formation_sim.launch", *argv]
    else:
        profile = out.parent / f"blocking_{samples}.xml"
        profile.write_text(blocking_profile(samples))
        env.update(FASTRTPS_DEFAULT_PROFILES_FILE=str(profile), RMW_FASTRTPS_USE_QOS_FROM_XML="1")
        cmd = [str(PYTHON), "-c", NO_ACK_LAUNCH, *argv]
    load = os.getloadavg()
    t0 = time.monotonic()
    with open(out.parent / f"{out.name}.log", "w") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        if pause:
            _pause_recorder(out, pause, proc)
        code = proc.wait(timeout=1800)
    wall = time.monotonic() - t0
    try:
        summary = json.loads((out / "summary.json").read_text())
        table = json.loads((out / "logs" / "processes.json").read_text())
    except (OSError, ValueError):
        print((out.parent / f"{out.name}.log").read_text()[-3000:], file=sys.stderr)
        raise
    cpu = {row["name"]: row["cpu_user_s"] + row["cpu_system_s"] for row in table}
    return {
        "design": design,
        "duration": duration,
        "exit": code,
        "recorder_paused_s": pause,
        "verdict": summary["verdict"],
        "reason": summary.get("incomplete_reason"),
        "wall_s": round(wall, 2),
        "launch": {k: round(v, 2) for k, v in summary["launch"].items() if k.startswith("wall_") and v is not None},
        "recorder": {k: summary["recorder"].get(k) for k in ("written", "not_recorded", "missed_start")},
        "cpu_s": {k: round(v, 3) for k, v in cpu.items()},
        "load": [round(x, 2) for x in (*load, *os.getloadavg())],
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--design", nargs="+", choices=("ack", "blocking"), default=["ack", "blocking"])
    p.add_argument("--durations", nargs="+", type=float, default=[0.05, 0.55])
    p.add_argument("--load", type=int, default=0, help="busy-loop processes added meanwhile")
    p.add_argument("--samples", type=int, default=64, help="blocking: KEEP_ALL resource limit per topic")
    p.add_argument("--pause-recorder", type=float, default=0.0, help="SIGSTOP the recorder this long while stepping")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    base = args.out or Path(tempfile.mkdtemp(prefix="recorder_flow_"))
    base.mkdir(parents=True, exist_ok=True)
    busy = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(args.load)
    ]
    results = []
    try:
        for design in args.design:
            for d in args.durations:
                res = run(design, d, base / f"{design}-{d:g}", args.samples, args.pause_recorder)
                print(json.dumps(res), flush=True)
                results.append(res)
    finally:
        for b in busy:
            b.kill()
            b.wait()
    lo, hi = min(args.durations), max(args.durations)
    for design in args.design if hi > lo else ():
        a, b = (next(r for r in results if r["design"] == design and r["duration"] == d) for d in (lo, hi))
        steps = round((hi - lo) * 10_000)
        per = {k: (b["cpu_s"][k] - a["cpu_s"].get(k, 0.0)) / steps * 1e3 for k in b["cpu_s"]}
        print(
            f"{design}: CPU per step {sum(per.values()):.2f} ms (sim {per.get('sim', 0):.2f}, recorder "
            f"{per.get('recorder', 0):.2f}, agents {sum(v for k, v in per.items() if k.startswith('agent')):.2f}); "
            f"not recorded {b['recorder']['not_recorded']}, stepping {b['launch'].get('wall_stepping_s')} s "
            f"(load {args.load} busy loops added)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
