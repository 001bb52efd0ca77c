"""The compiled run core is never stale: an edit of a callee in another file than the kernel's
recompiles it (numba alone keys its disk cache on the kernel's own file).

Slow-ish: the run core is compiled twice, into a copy of the sources (~15-25 s each on two idle cores).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).parents[2]
#: the wrench u_i = −γ_i ρ_v⁻¹ r_v T_v of formation_agent/controller.py, and the same with its sign flipped
WRENCH = "out[U + c] = -gains[GAMMA] / rho_v"
FLIPPED = "out[U + c] = gains[GAMMA] / rho_v"
#: whether numba's cache holds the controller's kernel for the sources as they are (no numba imported)
WARM = "from formation_agent.kernel_cache import numba_cache_warm; print(numba_cache_warm())"


def test_a_changed_controller_term_changes_the_next_headless_run(tmp_path) -> None:
    """In a copy of src/ (on PYTHONPATH, numba's cache beside the copied sources): run, flip the sign
    of the controller's wrench (controller.py, compiled into loop.py's kernel), run again: the wrench
    of every agent at t = 0 is the negated one, not the stale one; the agents' cache check agrees."""
    src = tmp_path / "src"
    shutil.copytree(REPO / "src", src, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", ".*"))
    packages = sorted(d for d in src.iterdir() if (d / d.name / "__init__.py").is_file())
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | {"NUMBA_DISABLE_JIT": "0"}
    env["PYTHONPATH"] = os.pathsep.join(str(d) for d in packages)

    def python(*args: str) -> str:
        return subprocess.run(
            [sys.executable, *args], capture_output=True, text=True, check=True, env=env, cwd=tmp_path, timeout=900
        ).stdout

    def headless(out: Path) -> np.ndarray:
        python(
            "-m", "formation_sim.cli.headless", str(REPO / "config" / "paper_5agents.yaml"),
            "--duration", "0.002", "--no-plots", "--quiet", "--force", "--out", str(out),
        )  # fmt: skip
        return np.load(out / "trajectory.npz")["u"]

    assert python("-c", "import formation_agent.controller as c; print(c.__file__)").startswith(str(src))
    u_before = headless(tmp_path / "before")
    assert list((src / "formation_sim" / "formation_sim" / "core" / "__pycache__").glob("loop.run_sampled-*.nbi"))
    assert python("-c", WARM).strip() == "True"
    controller = src / "formation_agent" / "formation_agent" / "controller.py"
    text = controller.read_text()
    assert text.count(WRENCH) == 1
    controller.write_text(text.replace(WRENCH, FLIPPED))
    assert python("-c", WARM).strip() == "False"
    u_after = headless(tmp_path / "after")
    assert np.all(np.abs(u_before[0]) > 0)
    np.testing.assert_array_equal(u_after[0], -u_before[0])  # the limit scales both alike: exactly negated
    assert python("-c", WARM).strip() == "True"
