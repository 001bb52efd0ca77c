"""Which agents run the compiled controller (formation_agent.process.compiled_pays)."""

from __future__ import annotations

from formation_agent.process import COMPILED_FROM_RATE, compiled_pays, numba_cache_warm


def test_compiled_in_realtime_and_in_fast_lockstep_only_with_a_warm_cache() -> None:
    warm = numba_cache_warm()
    assert compiled_pays(100.0, "realtime") is warm
    assert compiled_pays(COMPILED_FROM_RATE, "lockstep") is warm
    assert compiled_pays(COMPILED_FROM_RATE / 2, "lockstep") is False
