"""Which agents run the compiled controller (formation_agent.kernel_cache.compiled_pays)."""

from __future__ import annotations

import pytest

from formation_agent import kernel_cache
from formation_agent.kernel_cache import COMPILED_EXTRA_RSS, COMPILED_FROM_RATE, compiled_pays


@pytest.mark.parametrize("warm", [True, False])
def test_compiled_in_fast_lockstep_and_in_realtime_while_the_memory_fits(monkeypatch, warm: bool) -> None:
    monkeypatch.setattr(kernel_cache, "numba_cache_warm", lambda: warm)
    monkeypatch.setattr(kernel_cache, "available_memory", lambda: 4 * 20 * COMPILED_EXTRA_RSS)
    assert compiled_pays(COMPILED_FROM_RATE, "lockstep", 50) is warm
    assert compiled_pays(COMPILED_FROM_RATE / 2, "lockstep", 5) is False
    assert compiled_pays(100.0, "realtime", 20) is warm  # 20 agents' extra RSS: a quarter of what is available
    assert compiled_pays(100.0, "realtime", 21) is False


def test_available_memory_is_positive_and_at_most_the_machine() -> None:
    import os

    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert 0 < kernel_cache.available_memory() <= total


def test_cache_is_warm_only_for_the_sources_and_numba_as_they_are(tmp_path, monkeypatch) -> None:
    """An index written for other sources (the controller's file or a module it imports) or another numba
    is stale: agents would compile."""
    import importlib.metadata
    import pickle
    import sys

    from formation_core.numba_kernels import STAMP_IN_NAME, sources_stamp

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    package = tmp_path / "formation_kernel_cache_probe"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "gains.py").write_text("GAMMA = 1.0\n")
    source = package / "controller.py"
    source.write_text("from formation_kernel_cache_probe.gains import GAMMA\n\ndef agent_step(): return GAMMA\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    (package / "__pycache__").mkdir()
    assert not kernel_cache.numba_cache_warm(package)  # no index

    def write_index(version: str) -> None:
        stamp = sources_stamp(source)
        name = f"controller.agent_step-3-{stamp[:STAMP_IN_NAME]}.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
        with (package / "__pycache__" / name).open("wb") as f:
            pickle.dump(version, f, protocol=-1)
            f.write(pickle.dumps((stamp, {}), protocol=-1))

    write_index("0.0.1")
    assert not kernel_cache.numba_cache_warm(package)
    write_index(importlib.metadata.version("numba"))
    assert kernel_cache.numba_cache_warm(package)
    (package / "gains.py").write_text("GAMMA = 2.0\n")  # a module the kernel imports
    assert not kernel_cache.numba_cache_warm(package)
