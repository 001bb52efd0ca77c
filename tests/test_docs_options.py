"""Every option the README and docs/ show on a command line is one the command accepts.

Commands are the console scripts (``formation-bag SUBCOMMAND``: the subcommand) and the ros2_ws shell scripts; what
a command accepts is what its ``--help`` lists (a shell script's help lists its own options and,
once installed, those of the command it runs). Command lines are read from code: fenced blocks and
inline code spans, split at pipes, ``;`` and ``&&``; an option belongs to the last command named
before it on that line.
"""

from __future__ import annotations

import functools
import re
import subprocess
from pathlib import Path

import pytest
from bin_helpers import executable
from test_entry_points import console_scripts

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHELL = {p.name: p for p in (REPO / "ros2_ws").glob("*.sh")}
#: commands whose options are their subcommands' (argparse subparsers)
SUBCOMMANDS = {"formation-bag": ("info", "check", "repair"), "formation-keys": ("init", "check", "profile")}
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: rclpy's own arguments, which every node takes after --ros-args
ROS_ARGS = {"--ros-args", "--params-file", "--remap", "--param", "--log-level", "--enclave"}
FENCE = re.compile(r"```[^\n]*\n(.*?)```", re.S)
SPAN = re.compile(r"`([^`\n]+)`")


@functools.cache
def accepted(command: str) -> frozenset[str]:
    """The long options ``command --help`` lists (``formation-bag check``: the subcommand's)."""
    if command in SHELL:
        argv = [str(SHELL[command]), "--help"]
    elif " " in command:
        name, sub = command.split()
        argv = [str(executable(name)), sub, "--help"]
    else:
        argv = [str(executable(command)), "--help"]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"{command} --help: exit {r.returncode}: {r.stderr}"
    return frozenset(OPTION.findall(r.stdout)) | {"--help"}


def _commands() -> set[str]:
    return {*console_scripts(), *SHELL}


def command_lines(text: str) -> list[str]:
    """The command lines of a page: its code blocks' lines (``\\`` continuations joined) and inline spans."""
    lines: list[str] = []
    for block in FENCE.findall(text):
        lines.extend(block.replace("\\\n", " ").splitlines())
    prose = FENCE.sub("", text)
    lines.extend(SPAN.findall(prose))
    return [part for line in lines for part in re.split(r"\||;|&&", line)]


def uses(page: Path) -> list[tuple[str, str, str]]:
    """(command, option, the line) for every option shown after one of our commands on a line."""
    names = _commands()
    found = []
    for line in command_lines(page.read_text(encoding="utf-8")):
        command = None
        tokens = line.split()
        for k, token in enumerate(tokens):
            word = token.strip("`'\"()[],")
            base = word.rsplit("/", 1)[-1]
            if base in names:
                command = base
                if k + 1 < len(tokens) and tokens[k + 1] in SUBCOMMANDS.get(base, ()):
                    command = f"{base} {tokens[k + 1]}"
                continue
            if command is None:
                continue
            if word == "--ros-args":
                command = None  # rclpy's arguments from here on
                continue
            for option in OPTION.findall(word):
                if option not in ROS_ARGS:
                    found.append((command, option, line.strip()))
    return found


def test_the_reader_finds_commands_and_their_options() -> None:
    """The extraction itself: a block line, a span with a pipe, a subcommand, --ros-args skipped."""
    text = (
        "```bash\nros2_ws/run.sh config/x.yaml --out o \\\n  --duration 2\n```\n"
        "Then `formation-analyze o/bag --no-plots | head -1` or `formation-bag check --json B`;"
        " `agent.sh F 1 --ros-args -p gamma:=2 --params-file p.yaml` and `--force` alone."
    )
    page = REPO / "tests" / "_probe_page.md"
    try:
        page.write_text(text, encoding="utf-8")
        got = [(c, o) for c, o, _ in uses(page)]
    finally:
        page.unlink()
    assert got == [
        ("run.sh", "--out"),
        ("run.sh", "--duration"),
        ("formation-analyze", "--no-plots"),
        ("formation-bag check", "--json"),
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_option_shown_is_accepted(page: Path) -> None:
    """Each option a page shows after one of our commands is in that command's --help."""
    wrong = sorted({(c, o, line) for c, o, line in uses(page) if o not in accepted(c)})
    assert not wrong, "\n".join(f"{page.name}: {c} has no {o}: {line}" for c, o, line in wrong)


def _help_text(command: str) -> str:
    argv = [str(SHELL[command])] if command in SHELL else [str(executable(command))]
    r = subprocess.run([*argv, "--help"], capture_output=True, text=True, timeout=120)
    return " ".join(r.stdout.split())  # argparse wraps lines anywhere


@pytest.mark.parametrize("command", ["formation-headless", "formation-analyze", "run.sh"])
def test_every_output_file_is_named_in_the_help_and_the_docs(command: str) -> None:
    """Every figure and file a run (and an analysis) writes is named in the command's --help and in
    docs/outputs.md (an analysis's own files in docs/bags.md)."""
    from formation_sim.offline.analysis import ANALYSIS_OUTPUTS
    from formation_sim.views.figures import FIGURES
    from formation_sim.views.foxglove_layout import LAYOUT_NAME

    files = {*FIGURES, "summary.json", "trajectory.npz", LAYOUT_NAME}
    if command == "run.sh":
        files |= {"view.mcap", "bag/"}
    text = _help_text(command)
    missing = sorted(f for f in files if f.rstrip("/") not in text)
    assert not missing, f"{command} --help does not name {missing}"
    outputs_doc = (REPO / "docs" / "outputs.md").read_text(encoding="utf-8")
    assert not [f for f in files if f.rstrip("/") not in outputs_doc], "docs/outputs.md"
    if command == "formation-analyze":
        bags_doc = (REPO / "docs" / "bags.md").read_text(encoding="utf-8")
        assert not [f for f in ANALYSIS_OUTPUTS if f not in text], "formation-analyze --help"
        assert not [f for f in ANALYSIS_OUTPUTS if f not in bags_doc], "docs/bags.md"
