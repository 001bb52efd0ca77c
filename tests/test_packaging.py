"""Packaging: ament_python packages that colcon builds; ROS-free cores; --help everywhere."""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent.name for p in (REPO / "src").glob("*/package.xml"))
CORE_MODULES = [
    "formation_msgs_py.spec",
    "formation_msgs_py.schema",
    "formation_msgs_py.so3",
    "formation_msgs_py.funnels",
    "formation_msgs_py.topics",
    "formation_msgs_py.wire",
    "formation_agent.controller",
    "formation_sim.plant",
    "formation_sim.signals",
    "formation_sim.measurement",
    "formation_sim.simulation",
    "formation_sim.headless",
    "formation_sim.team",
    "formation_sim.report",
    "formation_sim.check",
    "formation_sim.generate",
]


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
    exe = REPO / ".venv" / "bin" / script
    res = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "usage" in res.stdout.lower()


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "ros2_ws").glob("*.sh")))
def test_every_shell_script_has_help(script: str) -> None:
    res = subprocess.run([str(REPO / "ros2_ws" / script), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip()


def test_colcon_builds_the_workspace(tmp_path: Path) -> None:
    """`colcon build` (colcon-common-extensions from PyPI) installs every package and its scripts."""
    colcon = REPO / ".venv" / "bin" / "colcon"
    assert colcon.exists(), "colcon-common-extensions is pinned in ros2_ws/requirements.txt"
    res = subprocess.run(
        [
            str(colcon),
            "build",
            "--base-paths",
            str(REPO / "src"),
            "--build-base",
            str(tmp_path / "build"),
            "--install-base",
            str(tmp_path / "install"),
            "--event-handlers",
            "console_direct-",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    for pkg in PACKAGES:
        assert (tmp_path / "install" / pkg / "share" / pkg / "package.xml").is_file()
    assert (tmp_path / "install" / "formation_sim" / "lib" / "formation_sim" / "formation-check").is_file()
    shutil.rmtree(tmp_path / "build", ignore_errors=True)
