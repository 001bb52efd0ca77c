"""``formation-agent``: one agent process, and whether its controller runs compiled.

An agent evaluates one controller per control step. Interpreted, a call costs ~0.1 ms; compiled
(numba, loaded from the on-disk cache) ~0.02 ms, but the process then loads numba and the cached
kernels: ~1.4 s more CPU at start and ~120 MB more RSS (BENCHMARKS.md, "Cost of a message").
That pays back after ~10 000 steps, so :func:`compiled_pays` chooses the compiled form from
:data:`COMPILED_FROM_RATE` on (the paper preset's 10 kHz lockstep), the interpreted one for
realtime formations at tens to hundreds of Hz (50 such processes share a host). The launcher
passes the choice as ``NUMBA_DISABLE_JIT``; an agent started alone (agent.sh) runs interpreted
unless its environment says ``NUMBA_DISABLE_JIT=0``.
"""

from __future__ import annotations

import os
from pathlib import Path

#: control rate [Hz] from which the launcher starts agents with the compiled controller
COMPILED_FROM_RATE = 1000.0


def numba_cache_warm() -> bool:
    """Whether numba's on-disk cache holds the controller's kernel (a first run compiles it in the
    simulator; an agent compiling at its first step would miss the lockstep step timeout)."""
    return any(Path(__file__).parent.glob("__pycache__/controller.agent_step-*.nbi"))


def compiled_pays(control_rate: float) -> bool:
    """Whether agents of a run at ``control_rate`` [Hz] should run the compiled controller."""
    return control_rate >= COMPILED_FROM_RATE and numba_cache_warm()


def main(args: list[str] | None = None) -> int:
    os.environ.setdefault("NUMBA_DISABLE_JIT", "1")
    from formation_agent.agent_node import main as node_main

    return node_main(args)
