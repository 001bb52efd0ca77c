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


def test_cache_is_warm_only_for_the_source_and_numba_as_they_are(tmp_path) -> None:
    """An index written for another controller.py (or another numba) is stale: agents would compile."""
    import hashlib
    import importlib.metadata
    import pickle

    source = tmp_path / "controller.py"
    source.write_text("def agent_step(): pass\n")
    (tmp_path / "__pycache__").mkdir()
    index = tmp_path / "__pycache__" / "controller.agent_step-265.py311.nbi"
    assert not kernel_cache.numba_cache_warm(tmp_path)  # no index

    def write_index(version: str, text: bytes) -> None:
        with index.open("wb") as f:
            pickle.dump(version, f, protocol=-1)
            f.write(pickle.dumps((hashlib.sha256(text).digest(), {}), protocol=-1))

    numba_version = importlib.metadata.version("numba")
    write_index(numba_version, source.read_bytes())
    assert kernel_cache.numba_cache_warm(tmp_path)
    write_index("0.0.1", source.read_bytes())
    assert not kernel_cache.numba_cache_warm(tmp_path)
    write_index(numba_version, b"def agent_step(): return 1\n")
    assert not kernel_cache.numba_cache_warm(tmp_path)
