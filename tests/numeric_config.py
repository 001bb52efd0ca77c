"""A second numeric configuration: this machine made to stand for another CPU.

``./ros2_ws/test.sh`` runs the tests marked ``numeric`` (the controller, the judge, the witness, the
golden runs) a second time with the environment this prints, one ``NAME=VALUE`` per line:

- ``NPY_DISABLE_CPU_FEATURES``: every SIMD group above its baseline that numpy dispatches to on this
  CPU (on an AVX-512 machine ``X86_V3 X86_V4 AVX512_ICL …``), so numpy's exp, log and the rest take
  the code paths of an older CPU;
- ``NUMBA_CPU_NAME=generic``: the compiled kernels are generated for a generic CPU of this
  architecture, not for this one's instruction set.

Neither reproduces another machine's libm or compiler; that is why every numeric tolerance states
its reason. ``numeric_platform()`` (formation_core.numba_kernels) differs under this environment, so
tests that are exact on one platform take their other-platform branch here.
"""

from __future__ import annotations

import sys


def environment() -> dict[str, str]:
    """The variables of the second configuration for this machine."""
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    groups = [g for g in __cpu_dispatch__ if __cpu_features__.get(g)]
    env = {"NUMBA_CPU_NAME": "generic"}
    if groups:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(groups)
    return env


def main() -> int:
    for name, value in environment().items():
        print(f"{name}={value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
