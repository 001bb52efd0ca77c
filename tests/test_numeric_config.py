"""The second numeric configuration of ./ros2_ws/test.sh (tests/numeric_config.py) takes effect."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from numeric_config import environment

pytestmark = pytest.mark.numeric

SCRIPT = Path(__file__).with_name("numeric_config.py")


def test_second_configuration_changes_what_decides_the_bits() -> None:
    """Under its environment numpy dispatches to none of the groups it names and numba targets a generic
    CPU, and the numeric platform's fingerprint differs from this process's own (so tests exact on one
    platform take their other-platform branch)."""
    second = dict(
        line.split("=", 1)
        for line in subprocess.check_output([sys.executable, str(SCRIPT)], text=True).split("\n")
        if line
    )
    assert second["NUMBA_CPU_NAME"] == "generic"
    probe = (
        "import sys, numba.core.config as c\n"
        "from numpy._core._multiarray_umath import __cpu_features__ as f\n"
        "from formation_core.numba_kernels import numeric_platform\n"
        "print(c.CPU_NAME, [g for g in sys.argv[1:] if f.get(g)], numeric_platform())\n"
    )
    groups = second.get("NPY_DISABLE_CPU_FEATURES", "").split()
    env = {**os.environ, **second}
    name, enabled, platform = subprocess.check_output([sys.executable, "-c", probe, *groups], env=env, text=True).split(
        " ", 2
    )
    assert name == "generic" and enabled == "[]"
    if os.environ.get("NUMBA_CPU_NAME") != "generic":  # this process runs the first configuration
        from formation_core.numba_kernels import numeric_platform

        assert platform.strip() != numeric_platform()


def test_it_disables_every_group_numpy_dispatches_to_here() -> None:
    """On a CPU where numpy dispatches to SIMD groups above its baseline, all of them are named."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    if os.environ.get("NPY_DISABLE_CPU_FEATURES"):
        pytest.skip("running under a configuration that already disables numpy's groups")
    enabled = [g for g in __cpu_dispatch__ if __cpu_features__.get(g)]
    assert environment().get("NPY_DISABLE_CPU_FEATURES", "").split() == enabled
