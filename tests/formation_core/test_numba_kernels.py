"""formation_core.numba_kernels: a compiled process loads numba without the modules no kernel needs, and a
kernel's disk cache is keyed on every source compiled into it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.numeric

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


def _write_package(root: Path, name: str, files: dict[str, str]) -> None:
    """A package ``name`` under ``root`` with the given modules (file name -> source)."""
    package = root / name
    package.mkdir(parents=True, exist_ok=True)
    (package / "__init__.py").write_text("")
    for file, source in files.items():
        (package / file).write_text(source)


def test_sources_stamp_changes_with_a_module_imported_transitively_and_only_with_those(tmp_path, monkeypatch) -> None:
    """The kernel's key follows its imports across files (entry -> middle -> callee), not unrelated modules."""
    from formation_core import numba_kernels

    name = "formation_stamp_probe"
    _write_package(
        tmp_path,
        name,
        {
            "entry.py": f"from {name}.middle import step  # the kernel's callee\n",
            "middle.py": f"from {name} import (\n    callee,\n)\n\nstep = callee.term\n",
            "callee.py": "def term(x):\n    return 2.0 * x\n",
            "unrelated.py": "X = 1\n",
        },
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    entry = tmp_path / name / "entry.py"
    before = numba_kernels.sources_stamp(entry)
    assert numba_kernels.sources_stamp(entry) == before  # a function of the files' contents
    (tmp_path / name / "unrelated.py").write_text("X = 2\n")
    assert numba_kernels.sources_stamp(entry) == before
    (tmp_path / name / "callee.py").write_text("def term(x):\n    return -2.0 * x\n")
    assert numba_kernels.sources_stamp(entry) != before


#: In a fresh compiled process: a kernel's numba cache is the one keyed on its sources, through the
#: private numba API numba_kernels.py relies on (numba.core.caching), and cache_index_glob finds its index.
CACHE_API = r"""
import fnmatch, json, sys
from numba.core import caching
from numba.core.dispatcher import Dispatcher
from formation_core import numba_kernels
from formation_agent import controller

impl = caching.CompileResultCacheImpl
checks = {
    "locator_base": all(
        hasattr(caching._CacheLocator, m) for m in ("get_source_stamp", "get_disambiguator", "from_function")
    ),
    "locator_classes": [c.__name__ for c in impl._locator_classes][:3],
    "mixin": all(issubclass(c, caching._SourceFileBackedLocatorMixin) for c in impl._locator_classes[:3]),
    "zip_locator": issubclass(caching.ZipCacheLocator, caching._SourceFileBackedLocatorMixin),
    "function_cache": caching.FunctionCache._impl_class is impl,
}
kernel = controller.agent_step
cache = kernel._cache
locator = cache._impl.locator
stamp = numba_kernels.sources_stamp(controller.__file__)
checks["dispatcher"] = isinstance(kernel, Dispatcher)
checks["cache_class"] = type(cache).__name__
checks["locator_file"] = locator._py_file == controller.__file__
checks["stamp"] = cache._cache_file._source_stamp == stamp
index = cache._cache_file._index_path
checks["index_named_by_stamp"] = stamp[: numba_kernels.STAMP_IN_NAME] in index
# numba's first choice (NUMBA_CACHE_DIR if set, else __pycache__ beside the source) is the first pattern
glob = numba_kernels.cache_index_glob(controller.__file__, "agent_step")
checks["index_found"] = fnmatch.fnmatch(index, str(glob[0]))
checks["in_cache_dir"] = index.startswith(sys.argv[1]) if len(sys.argv) > 1 else "/__pycache__/" in index
print(json.dumps(checks))
"""


@pytest.mark.parametrize("cache_dir", [False, True], ids=["in-tree", "NUMBA_CACHE_DIR"])
def test_kernel_cache_is_keyed_on_its_sources_through_numbas_private_cache_api(tmp_path, cache_dir: bool) -> None:
    """Fails when numba changes the private caching API numba_kernels.py builds on (locators, cache impl,
    index file), or when cache_index_glob (read without numba) no longer names the index numba uses."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | {"NUMBA_DISABLE_JIT": "0"}
    args = [sys.executable, "-c", CACHE_API]
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = str(tmp_path)
        args.append(str(tmp_path))
    out = subprocess.run(args, capture_output=True, text=True, check=True, env=env, timeout=120)
    assert json.loads(out.stdout.splitlines()[-1]) == {
        "locator_base": True,
        "locator_classes": ["UserProvidedCacheLocator", "InTreeCacheLocator", "UserWideCacheLocator"],
        "mixin": True,
        "zip_locator": True,
        "function_cache": True,
        "dispatcher": True,
        "cache_class": "SourcesFunctionCache",
        "locator_file": True,
        "stamp": True,
        "index_named_by_stamp": True,
        "index_found": True,
        "in_cache_dir": True,
    }


#: Run the probe kernel once, printing its result and whether it came from the cache.
PROBE_RUN = r"""
import json
from formation_cache_probe.entry import run
print(json.dumps({"value": run(1.0), "hits": sum(run.stats.cache_hits.values())}))
"""


def test_a_changed_callee_in_another_file_recompiles_the_kernel(tmp_path) -> None:
    """A kernel whose formula comes from another file: after an edit of that file, the kernel runs the new
    formula (numba alone would load the stale machine code: its key is the kernel's own file)."""
    name = "formation_cache_probe"
    formula = "from formation_core.numba_kernels import formula\n\n\n@formula\ndef term(x):\n    return {} * x\n"
    _write_package(
        tmp_path,
        name,
        {
            "callee.py": formula.format("2.0"),
            "entry.py": (
                "from formation_core.numba_kernels import kernel\n"
                f"from {name}.callee import term\n\n\n@kernel\ndef run(x):\n    return term(x) + 1.0\n"
            ),
        },
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"} | {"NUMBA_DISABLE_JIT": "0"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])

    def run() -> dict:
        out = subprocess.run(
            [sys.executable, "-c", PROBE_RUN], capture_output=True, text=True, check=True, env=env, timeout=300
        )
        return json.loads(out.stdout.splitlines()[-1])

    assert run() == {"value": 3.0, "hits": 0}  # compiled
    assert run() == {"value": 3.0, "hits": 1}  # loaded from the cache beside the sources
    assert list((tmp_path / name / "__pycache__").glob("entry.run-*.nbi"))
    (tmp_path / name / "callee.py").write_text(formula.format("-2.0"))
    assert run() == {"value": -1.0, "hits": 0}  # compiled again, not the stale 3.0
    assert run() == {"value": -1.0, "hits": 1}
