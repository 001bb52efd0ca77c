"""formation_msgs_py.compiled: a compiled process loads numba without the modules no kernel needs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

#: In a fresh compiled process: declare the kernels (imports numba and the numba modules that probe
#: coverage, scipy and cffi), list which of those got imported, then import scipy.linalg as any
#: other code of the process may.
IMPORTS = r"""
import json, sys
import formation_agent.controller
import numba.core.typing.cffi_utils, numba.np.arraymath
loaded = sorted(m for m in ("coverage", "scipy", "scipy.linalg", "cffi") if m in sys.modules)
import scipy.linalg
hidden_left = [m for m in ("coverage", "scipy", "cffi") if sys.modules.get(m, 1) is None]
print(json.dumps({"loaded": loaded, "hidden_left": hidden_left, "scipy_linalg_after": scipy.linalg.__name__}))
"""


def test_numba_loads_without_coverage_scipy_and_cffi_and_leaves_them_importable() -> None:
    env = {**os.environ, "NUMBA_DISABLE_JIT": "0"}
    out = subprocess.run(
        [sys.executable, "-c", IMPORTS], capture_output=True, text=True, check=True, env=env, timeout=120
    )
    result = json.loads(out.stdout.splitlines()[-1])
    assert result == {"loaded": [], "hidden_left": [], "scipy_linalg_after": "scipy.linalg"}
