"""Packaging: ament_python packages that colcon builds; ROS-free cores; --help everywhere."""

from __future__ import annotations

import ast
import configparser
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml
from bin_helpers import executable

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "config" / "paper_5agents.yaml"
PACKAGES = sorted(p.parent.name for p in (REPO / "src").glob("*/package.xml"))
CORE_MODULES = [
    "formation_core.spec",
    "formation_core.schema",
    "formation_core.so3",
    "formation_core.funnels",
    "formation_msgs_py.topics",
    "formation_msgs_py.codec",
    "formation_agent.controller",
    "formation_sim.core.plant",
    "formation_sim.core.disturbances",
    "formation_sim.core.measurement",
    "formation_sim.core.simulation",
    "formation_sim.cli.headless",
    "formation_sim.core.team",
    "formation_sim.core.recorder",
    "formation_sim.views.markers",
    "formation_sim.views.figures",
    "formation_sim.views.animation",
    "formation_sim.cli.check",
    "formation_sim.cli.generate",
]


#: Every module a package imports, by its rosdep key (package.xml) and, for PyPI projects, its
#: requirement name (setup.py install_requires; ROS packages are not PyPI projects under their own
#: names, so rosdep alone declares them). Each key was checked in ros/rosdistro (commit 8468e88,
#: rosdep/python.yaml; the ROS packages in jazzy/distribution.yaml). ``mcap`` has no key of its own:
#: ``mcap-ros2-support`` (a pip key) installs it, as the PyPI project mcap-ros2-support requires mcap.
DEPENDENCIES = {
    "numpy": ("python3-numpy", "numpy"),
    "scipy": ("python3-scipy", "scipy"),
    "yaml": ("python3-yaml", "PyYAML"),
    "matplotlib": ("python3-matplotlib", "matplotlib"),
    "PIL": ("python3-pil", "pillow"),
    "cryptography": ("python3-cryptography", "cryptography"),
    "numba": ("python3-numba", "numba"),
    "rosbags": ("python3-rosbags-pip", "rosbags"),
    "mcap": ("mcap-ros2-support", "mcap"),
    "mcap_ros2": ("mcap-ros2-support", "mcap-ros2-support"),
    **{
        ros: (ros, None)
        for ros in (
            "rclpy",
            "builtin_interfaces",
            "rcl_interfaces",
            "geometry_msgs",
            "rosgraph_msgs",
            "diagnostic_msgs",
            "std_msgs",
            "visualization_msgs",
            "tf2_msgs",
        )
    },
}
#: The keys a package.xml may name: the verified ones above, the workspace's packages, pytest.
KNOWN_KEYS = {key for key, _ in DEPENDENCIES.values()} | set(PACKAGES) | {"python3-pytest"}

#: Modules only an optional feature imports: declared as a setup.py extra, not in package.xml
#: (rosdistro has no key for dask's distributed nor for foxglove-sdk): module -> (extra, requirement).
OPTIONAL = {
    "distributed": ("dask", "distributed"),  # formation-campaign --scheduler
    "foxglove": ("live", "foxglove-sdk"),  # the live view, --foxglove
}


def imported_modules(pkg: str) -> set[str]:
    """Top-level names of the non-stdlib modules ``pkg``'s code imports (other formation packages
    included), also through ``importlib.import_module("NAME…")`` with a literal name."""
    names: set[str] = set()
    for path in (REPO / "src" / pkg / pkg).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
            elif (
                isinstance(node, ast.Call)
                and getattr(node.func, "attr", getattr(node.func, "id", None)) == "import_module"
                and node.args
                and isinstance(node.args[0], ast.Constant)
            ):
                names.add(node.args[0].value.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != pkg}


def setup_arguments(pkg: str) -> dict[str, object]:
    """The literal keyword arguments of ``setup(...)`` in ``pkg``'s setup.py (package_name resolved)."""
    tree = ast.parse((REPO / "src" / pkg / "setup.py").read_text(encoding="utf-8"))
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    wanted = ("install_requires", "extras_require")
    return {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords if kw.arg in wanted}


@pytest.mark.parametrize("pkg", PACKAGES)
def test_every_import_is_declared(pkg: str) -> None:
    """package.xml has a rosdep key and setup.py a requirement for every module the package imports;
    package.xml names no key that was not checked against rosdistro."""
    xml = ET.parse(REPO / "src" / pkg / "package.xml").getroot()
    keys = {d.text for tag in ("depend", "exec_depend") for d in xml.findall(tag)}
    unknown = {d.text for d in xml.iter() if d.tag.endswith("depend")} - KNOWN_KEYS
    assert not unknown, f"{pkg}/package.xml: keys not checked against rosdistro: {sorted(unknown)}"
    setup = setup_arguments(pkg)
    requires = set(setup["install_requires"])
    for module in sorted(imported_modules(pkg)):
        if module in OPTIONAL:
            extra, requirement = OPTIONAL[module]
            assert requirement in setup["extras_require"][extra], f"{pkg}/setup.py: {extra!r} lacks {requirement!r}"
            continue
        key, requirement = (module, module) if module in PACKAGES else DEPENDENCIES.get(module, (None, None))
        assert key is not None, f"{pkg} imports {module}: add it to DEPENDENCIES with its rosdistro key"
        assert key in keys, f"{pkg}/package.xml: <exec_depend>{key}</exec_depend> missing (imports {module})"
        if requirement is not None:
            assert requirement in requires, f"{pkg}/setup.py: install_requires lacks {requirement!r} ({module})"


def test_core_packages_exist() -> None:
    assert {"formation_msgs_py", "formation_agent", "formation_sim"} <= set(PACKAGES)


@pytest.mark.parametrize("pkg", PACKAGES)
def test_ament_python_layout(pkg: str) -> None:
    """package.xml (format 3, ament_python), setup.py, setup.cfg script dir, resource marker."""
    root = REPO / "src" / pkg
    xml = ET.parse(root / "package.xml").getroot()
    assert xml.get("format") == "3"
    assert xml.findtext("name") == pkg
    assert xml.find("export/build_type").text == "ament_python"
    assert (root / "resource" / pkg).is_file()
    assert f"script_dir=$base/lib/{pkg}" in (root / "setup.cfg").read_text()
    setup = (root / "setup.py").read_text()
    assert '"resource/" + package_name' in setup and '"package.xml"' in setup


def test_cores_never_import_rclpy() -> None:
    """The controller, plant, measurements, validation and reports import without ROS."""
    code = (
        "import sys; sys.modules['rclpy'] = None\n"
        + "".join(f"import {m}\n" for m in CORE_MODULES)
        + "bad = [m for m in sys.modules if m.split('.')[0] in ('rclpy', 'geometry_msgs', 'rosgraph_msgs')"
        + " and sys.modules[m] is not None]\nassert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def console_scripts() -> list[str]:
    names = []
    for pkg in PACKAGES:
        for line in (REPO / "src" / pkg / "setup.py").read_text().splitlines():
            line = line.strip().strip('",')
            if " = " in line and ":" in line and line.split(" = ")[0].startswith("formation-"):
                names.append(line.split(" = ")[0])
    return names


@pytest.mark.parametrize("script", console_scripts())
def test_every_console_script_has_help(script: str) -> None:
    exe = executable(script)
    res = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "usage" in res.stdout.lower()


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "ros2_ws").glob("*.sh")))
def test_every_shell_script_has_help(script: str) -> None:
    res = subprocess.run([str(REPO / "ros2_ws" / script), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip()


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "ros2_ws").glob("*.sh")))
def test_shell_script_help_installs_nothing(script: str, tmp_path: Path) -> None:
    """--help of every script in a fresh clone (no .venv): prints, creates no environment, and a script
    that runs a command says how to see that command's options."""
    shutil.copytree(REPO / "ros2_ws", tmp_path / "ros2_ws", symlinks=True, ignore=shutil.ignore_patterns("src"))
    res = subprocess.run([str(tmp_path / "ros2_ws" / script), "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() and not (tmp_path / ".venv").exists(), res.stdout + res.stderr
    if script in ("run.sh", "sim.sh", "record.sh", "replay.sh"):
        assert "once the project is installed: ros2_ws/setup.sh" in res.stdout, res.stdout


def colcon(tmp_path: Path, *args: str, symlink: bool = False, from_workspace: bool = False) -> str:
    """colcon build into ``tmp_path`` of the packages under src/ (``from_workspace``: found as a user
    finds them, from ros2_ws/ with no base path); its output."""
    where = [] if from_workspace else ["--base-paths", str(REPO / "src")]
    res = subprocess.run(
        [
            str(REPO / ".venv" / "bin" / "colcon"),
            "--log-base",
            str(tmp_path / "log"),
            "build",
            *where,
            "--build-base",
            str(tmp_path / "build"),
            "--install-base",
            str(tmp_path / "install"),
            "--event-handlers",
            "console_direct-",
            *(["--symlink-install"] if symlink else []),
            *args,
        ],
        cwd=REPO / "ros2_ws" if from_workspace else tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return res.stdout + res.stderr


def test_colcon_test_covers_every_test_directory() -> None:
    """`colcon test` runs pytest in each package's directory with its setup.cfg testpaths: together they
    hold every directory of tests/ (this file, the workspace's own test, runs with test.sh)."""
    covered = set()
    for pkg in PACKAGES:
        cfg = configparser.ConfigParser()
        cfg.read(REPO / "src" / pkg / "setup.cfg")
        covered |= {(REPO / "src" / pkg / p).resolve() for p in cfg["tool:pytest"]["testpaths"].split()}
    wanted = {d for d in (REPO / "tests").iterdir() if d.is_dir() and any(d.glob("test_*.py"))}
    assert wanted == covered, (sorted(map(str, wanted - covered)), sorted(map(str, covered - wanted)))


def test_colcon_symlink_install_builds_every_package_from_ros2_ws(tmp_path: Path) -> None:
    """`cd ros2_ws && colcon build --symlink-install` finds the packages (ros2_ws/src links to ../src) and
    builds all of them with the pinned setuptools (below 80: develop --editable)."""
    assert (REPO / "ros2_ws" / "src").resolve() == REPO / "src"
    output = colcon(tmp_path, symlink=True, from_workspace=True)
    assert f"Summary: {len(PACKAGES)} packages finished" in output, output[-3000:]
    for pkg in PACKAGES:
        installed = tmp_path / "install" / pkg / "share" / pkg / "package.xml"
        assert installed.is_symlink() and installed.resolve() == REPO / "src" / pkg / "package.xml"


def test_colcon_install_runs_a_formation(tmp_path: Path, ros_domain_id: int) -> None:
    """`colcon build` installs every package; formation-launch from the sourced install space runs a
    short recorded formation whose agents are the install space's, and whose simulator writes its bag
    with the install space's bag writer (formation_bag.writer)."""
    colcon(tmp_path)
    install = tmp_path / "install"
    for pkg in PACKAGES:
        assert (install / pkg / "share" / pkg / "package.xml").is_file()
    launch = install / "formation_sim" / "lib" / "formation_sim" / "formation-launch"
    out = tmp_path / "run"
    env = {k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "PYTHONPATH")}
    env.update(ROS_DOMAIN_ID=str(ros_domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    # a fresh install space has no numba cache: six processes compiling at once on a busy machine
    # outlast any step timeout, and what this test checks is the packaging, not the compiler
    env.update(FASTDDS_BUILTIN_TRANSPORTS="UDPv4", NUMBA_DISABLE_JIT="1")
    run = f'"{launch}" "{PAPER}" --duration 0.005 --step-timeout 60 --out "{out}" --quiet'
    script = f'. "{install}/setup.sh" && exec {run}'
    res = subprocess.run(["bash", "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    table = (out / "logs" / "processes.json").read_text()
    assert str(install / "formation_agent" / "lib" / "formation_agent" / "formation-agent") in table
    assert (out / "summary.json").is_file()
    info = yaml.safe_load((out / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    assert counts["/formation/ground_truth"] == counts["/agent_1/wrench"] == 51  # 0.005 s at 10 kHz


def test_every_doc_link_and_help_pointer_exists() -> None:
    """Markdown links (README, docs/, tests/, BENCHMARKS) and ``docs/*.md`` named in code and scripts
    exist; nothing points at the design contract (DESIGN.md), which is not in the repository."""
    missing = []
    docs = [REPO / "README.md", REPO / "BENCHMARKS.md", REPO / "tests" / "README.md", *(REPO / "docs").glob("*.md")]
    for md in docs:
        for target in re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", md.read_text(encoding="utf-8")):
            if "://" not in target and not (md.parent / target).exists():
                missing.append(f"{md.relative_to(REPO)} -> {target}")
    sources = [*(REPO / "src").rglob("*.py"), *(REPO / "ros2_ws").glob("*.sh")]
    for path in sources:
        for target in set(re.findall(r"\b(docs/[\w./-]+\.md|tests/README\.md)", path.read_text(encoding="utf-8"))):
            if not (REPO / target).exists():
                missing.append(f"{path.relative_to(REPO)} -> {target}")
    missing += [f"{p.relative_to(REPO)} -> DESIGN.md" for p in [*docs, *sources] if "DESIGN.md" in p.read_text("utf-8")]
    assert not missing, missing


def test_tests_find_scripts_in_the_install_that_runs_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """tests/bin_helpers.py: FORMATION_BIN first, then the interpreter's directory, then a sourced
    install space (AMENT_PREFIX_PATH/lib/<package>/NAME), then PATH, then the repository's .venv/bin."""
    import bin_helpers

    def script(directory: Path) -> Path:
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "formation-launch").write_text("#!/bin/sh\n")
        (directory / "formation-launch").chmod(0o755)
        return directory / "formation-launch"

    forced, interpreter = script(tmp_path / "forced"), script(tmp_path / "venv" / "bin")
    installed = script(tmp_path / "install" / "formation_sim" / "lib" / "formation_sim")
    on_path = script(tmp_path / "path")
    monkeypatch.setattr(sys, "executable", str(interpreter.parent / "python"))
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "install" / "formation_sim"))
    monkeypatch.setenv("PATH", str(on_path.parent))
    monkeypatch.setenv("FORMATION_BIN", f"{tmp_path / 'empty'}:{forced.parent}")
    assert bin_helpers.executable("formation-launch") == str(forced)
    monkeypatch.delenv("FORMATION_BIN")
    assert bin_helpers.executable("formation-launch") == str(interpreter)
    monkeypatch.setattr(sys, "executable", str(tmp_path / "python"))
    assert bin_helpers.executable("formation-launch") == str(installed)
    monkeypatch.delenv("AMENT_PREFIX_PATH")
    assert bin_helpers.executable("formation-launch") == str(on_path)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert bin_helpers.executable("formation-launch") == str(REPO / ".venv" / "bin" / "formation-launch")
