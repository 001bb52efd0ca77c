"""First contact with every command: wall time and peak memory, median of 5.

    .venv/bin/python benchmarks/entry_bench.py        # on a quiet machine; results in BENCHMARKS.md

- ``--help`` of every console script and of every ``ros2_ws/*.sh`` (goal: under 0.3 s);
- a 2.5 kB YAML alias bomb and a PNG given to every command that reads a formation file
  (goal: refused, exit 2, in under 1 s and 100 MB);
- the interpreter alone (the ROS wheels re-execute it once at start-up) and ``import`` plus
  ``load_formation`` of the presets in a fresh process (what each of 50 agent processes pays).
"""

from __future__ import annotations

import itertools
import os
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import entry_points
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = REPO / ".venv" / "bin"
RUNS = int(os.environ.get("RUNS", "5"))


def measure(cmd: list[str], expect: int = 0) -> tuple[float, float]:
    """Median wall s and median peak RSS (MB) of ``cmd``, run RUNS times; checks its exit status."""
    walls, rss = [], []
    for _ in range(RUNS):
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        _, status, usage = os.wait4(proc.pid, 0)
        walls.append(time.perf_counter() - t0)
        rss.append(usage.ru_maxrss / 1024)
        code = os.waitstatus_to_exitcode(status)
        if code != expect:
            raise SystemExit(f"{' '.join(cmd)}: exit {code}, expected {expect}")
    return statistics.median(walls), statistics.median(rss)


def console_scripts() -> list[str]:
    """The project's console scripts, as installed in .venv."""
    return sorted(e.name for e in entry_points(group="console_scripts") if e.name.startswith("formation-"))


def row(what: str, cmd: list[str], expect: int = 0) -> None:
    wall, rss = measure(cmd, expect)
    print(f"| {what} | {wall:.3f} | {rss:.0f} |", flush=True)


def main() -> None:
    print(f"| command | wall s (median of {RUNS}) | peak RSS MB |\n|---|---|---|")
    row("`python -c pass` (interpreter + the wheels' re-exec)", [str(BIN / "python"), "-c", "pass"])
    for name in console_scripts():
        row(f"`{name} --help`", [str(BIN / name), "--help"])
    for script in sorted((REPO / "ros2_ws").glob("*.sh")):
        row(f"`ros2_ws/{script.name} --help`", [str(script), "--help"])
    with tempfile.TemporaryDirectory() as tmp:
        bomb = Path(tmp) / "bomb.yaml"
        lines = ["a: &a [" + ", ".join(['"lol"'] * 40) + "]"]
        names = "abcdefghijklmnop"
        lines += [f"{b}: &{b} [" + ", ".join([f"*{a}"] * 40) + "]" for a, b in itertools.pairwise(names)]
        bomb.write_text("\n".join(lines) + "\nagents: *p\nedges: *p\n")
        png = Path(tmp) / "image.png"
        png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)) * 8)
        out = str(Path(tmp) / "out")
        commands = {  # every command that reads a formation file
            "formation-check": ["{F}"],
            "formation-headless": ["{F}", "--out", out],
            "formation-sim": ["{F}", "--out", out],
            "formation-launch": ["{F}", "--out", out],
            "formation-record": ["--out", out, "--formation", "{F}"],
            "formation-analyze": [out, "--formation", "{F}"],
            "formation-rerun": [out, "--formation", "{F}"],
            "formation-campaign": ["--sweep-rate", "{F}", "1000", "--out", out],
            "formation-compose": ["{F}", "--out", out],
            "formation-keys": ["init", out, "--formation", "{F}"],
            "formation-agent": ["--ros-args", "-p", "formation_file:={F}", "-p", "agent_id:='1'"],
        }
        for bad in (bomb, png):
            what = f"{bad.stat().st_size / 1000:.1f} kB {'alias bomb' if bad is bomb else 'PNG'}"
            for name, template in commands.items():
                row(f"`{name}` {what}", [str(BIN / name), *(a.replace("{F}", str(bad)) for a in template)], 2)
            row(f"`ros2_ws/run.sh` {what}", [str(REPO / "ros2_ws" / "run.sh"), str(bad), "--out", out], 2)
    for preset in ("paper_5agents", "realtime_50agents_50hz"):
        path = REPO / "config" / f"{preset}.yaml"
        code = f"from formation_core.spec import load_formation; load_formation({str(path)!r})"
        row(f"import + `load_formation` {preset}", [str(BIN / "python"), "-c", code])


if __name__ == "__main__":
    sys.exit(main())
