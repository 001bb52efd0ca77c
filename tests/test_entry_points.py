"""Import hygiene of every command: ``--help`` and a bad input end before the heavy imports.

Each command runs in a fresh interpreter (as its console script would, through its installed
entry point) and reports which heavy modules it imported: a check of sys.modules, not of time,
so it holds on a busy machine. The timings are in BENCHMARKS.md ("Bad input").
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from formation_core.options import without_ros_args

REPO = Path(__file__).resolve().parents[1]
#: what --help must not import (numpy 0.1 s, scipy 0.2 s, rclpy 0.2 s, numba 0.7 s and ~100 MB)
HEAVY = ("numpy", "numba", "scipy", "rclpy")

# Runs the command NAME with ARGS as its console script does (sys.argv, the installed entry point)
# and prints the exit status and the heavy modules it imported as JSON on the last stderr line.
PROBE = """
import json, sys
from importlib.metadata import entry_points
name, *args = sys.argv[1:]
(ep,) = [e for e in entry_points(group="console_scripts") if e.name == name]
sys.argv = [name, *args]
try:
    code = ep.load()()
except SystemExit as exc:
    code = exc.code
heavy = sorted(m for m in HEAVY if m in sys.modules)
print(json.dumps({"code": code, "heavy": heavy}), file=sys.stderr)
"""


def console_scripts() -> list[str]:
    names = []
    for setup in sorted((REPO / "src").glob("*/setup.py")):
        for line in setup.read_text().splitlines():
            line = line.strip().strip('",')
            if " = " in line and line.startswith("formation-"):
                names.append(line.split(" = ")[0])
    return names


def probe(name: str, *args: str) -> tuple[int, list[str], subprocess.CompletedProcess[str]]:
    r = subprocess.run(
        [sys.executable, "-c", f"HEAVY = {HEAVY!r}\n{PROBE}", name, *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    report = json.loads(r.stderr.strip().splitlines()[-1])
    return report["code"], report["heavy"], r


def test_every_setup_py_script_is_probed() -> None:
    assert len(console_scripts()) >= 14


@pytest.mark.parametrize("script", console_scripts())
def test_help_imports_nothing_heavy(script: str) -> None:
    """``--help`` of every console script: exit 0 and none of numpy, numba, scipy, rclpy imported."""
    code, heavy, r = probe(script, "--help")
    assert code in (0, None), r.stderr
    assert "usage" in r.stdout.lower()
    assert heavy == [], f"{script} --help imported {heavy}"


ALIAS_BOMB = (
    "a: &a ["
    + ", ".join(['"lol"'] * 10)
    + "]\n"
    + "".join(f"{n}: &{n} [" + ", ".join([f"*{p}"] * 10) + "]\n" for p, n in zip("abcdefghi", "bcdefghij"))
    + "agents: *j\nedges: *j\n"
)


#: every command that reads a formation file, with its arguments around the file (F) and OUT (O)
FILE_COMMANDS = {
    "formation-check": ["F"],
    "formation-headless": ["F", "--out", "O"],
    "formation-sim": ["F", "--out", "O", "--ros-args", "-p", "x:=1"],
    "formation-launch": ["F", "--out", "O"],
    "formation-record": ["--out", "O", "--formation", "F"],
    "formation-analyze": ["O", "--formation", "F"],
    "formation-rerun": ["O", "--formation", "F"],
    "formation-campaign": ["--sweep-rate", "F", "1000", "--out", "O"],
    "formation-compose": ["F", "--out", "O"],
    "formation-keys": ["init", "O", "--formation", "F"],
}


@pytest.mark.parametrize("script", sorted(FILE_COMMANDS))
@pytest.mark.parametrize("case", ["bomb", "binary"])
def test_bad_file_is_refused_before_the_cores_load(tmp_path, script: str, case: str) -> None:
    """An alias bomb or a binary file: exit 2 naming FILE:LINE:COL, with neither numba, scipy nor
    rclpy imported (the loader needs numpy and yaml only), nothing written."""
    path = tmp_path / "bad.yaml"
    path.write_bytes(ALIAS_BOMB.encode() if case == "bomb" else b"\x89PNG\r\n\x1a\n\x00")
    args = [{"F": str(path), "O": str(tmp_path / "out")}.get(a, a) for a in FILE_COMMANDS[script]]
    code, heavy, r = probe(script, *args)
    assert code == 2, r.stderr
    assert re.search(rf"{re.escape(str(path))}:\d+:\d+: ", r.stderr) and "Traceback" not in r.stderr, r.stderr
    assert set(heavy) <= {"numpy"}, f"{script} imported {heavy} before refusing {case}"
    assert not (tmp_path / "out").exists()


def test_ros_arguments_are_removed_as_rclpy_does() -> None:
    """Each --ros-args section up to -- (or the end) is ROS's; what follows -- is the command's again."""
    argv = ["prog", "f.yaml", "--ros-args", "-p", "a:=1", "--", "--mode", "realtime", "--ros-args", "-r", "x:=y"]
    assert without_ros_args(argv) == ["prog", "f.yaml", "--mode", "realtime"]
    assert without_ros_args(["prog", "--quiet"]) == ["prog", "--quiet"]
