"""Stopping a lockstep run: a simulator stopped mid-run, and Ctrl-C to formation-launch.

    .venv/bin/python benchmarks/stop_bench.py stopped-sim [--runs 8]
    .venv/bin/python benchmarks/stop_bench.py ctrl-c [--runs 5] [--busy 2]

``stopped-sim``: `formation-launch config/paper_5agents.yaml --duration 0.4 --step-timeout 2
--no-record`; 1 s after the simulator's first progress line it is SIGSTOPped for 3 s, then
continued; prints the exit status, verdict, resends and reason of each run.
``ctrl-c``: the default run (`formation-launch config/paper_5agents.yaml`); SIGINT to the launcher
3 s after the simulator's first progress line; prints the exit status, the wall time from SIGINT
to the launcher's exit [s], the verdict and whether trajectory.npz was written, and each process's
exit status (logs/processes.json).
``--busy N`` runs N busy loops beside the runs. Every process is started in its own session and
stopped by its PID; the runs use ROS_DOMAIN_ID 81 and discovery on this host only.
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

REPO = Path(__file__).resolve().parents[1]
ENV = {
    **os.environ,
    "PATH": f"{REPO / '.venv' / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}",
    "ROS_DOMAIN_ID": "81",
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
}


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc's children lists)."""
    found, todo = [], [pid]
    while todo:
        parent = todo.pop()
        try:
            tids = os.listdir(f"/proc/{parent}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{parent}/task/{tid}/children") as f:
                    kids = [int(x) for x in f.read().split()]
            except OSError:
                continue
            found += kids
            todo += kids
    return found


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def wait_for(path: Path, needle: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and needle in path.read_text(errors="replace"):
            return
        time.sleep(0.05)
    raise SystemExit(f"stop_bench: no {needle!r} in {path} within {timeout:g} s")


def launch(out: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        ["formation-launch", "config/paper_5agents.yaml", "--out", str(out), "--force", *args],
        cwd=REPO, env=ENV, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip


def stopped_sim(out: Path) -> str:
    proc = launch(out, "--duration", "0.4", "--step-timeout", "2", "--no-record")
    try:
        wait_for(out / "logs" / "sim.log", "progress", 120)
        time.sleep(1.0)
        sim = next(p for p in descendants(proc.pid) if "formation_sim.node.sim_node" in cmdline(p))
        os.kill(sim, signal.SIGSTOP)
        time.sleep(3.0)
        os.kill(sim, signal.SIGCONT)
        proc.wait(300)
    finally:
        if proc.poll() is None:
            proc.kill()
    s = json.loads((out / "summary.json").read_text())
    return f"exit {proc.returncode}, {s['verdict']}, resends {s.get('resends')}, {s.get('incomplete_reason')}"


def ctrl_c(out: Path) -> str:
    proc = launch(out)
    try:
        wait_for(out / "logs" / "sim.log", "progress", 120)
        time.sleep(3.0)
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        proc.wait(120)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    s = json.loads((out / "summary.json").read_text())
    table = json.loads((out / "logs" / "processes.json").read_text())
    exits = {r["name"]: r["returncode"] for r in table}
    npz = (out / "trajectory.npz").exists()
    verdict = f"{s['verdict']} ({s.get('incomplete_reason')})"
    return f"exit {proc.returncode} after {took:.3f} s, {verdict}, trajectory.npz {npz}, exit statuses {exits}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("stopped-sim", "ctrl-c"))
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--busy", type=int, default=0, help="busy loops beside the runs")
    a = p.parse_args()
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(a.busy)]
    try:
        with tempfile.TemporaryDirectory(prefix="stop-bench-") as tmp:
            for i in range(a.runs):
                load = " ".join(Path("/proc/loadavg").read_text().split()[:3])
                result = (stopped_sim if a.what == "stopped-sim" else ctrl_c)(Path(tmp) / f"run{i}")
                print(f"{time.strftime('%H:%M:%S')} load {load}: {result}", flush=True)
    finally:
        for b in busy:
            b.kill()
            b.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
