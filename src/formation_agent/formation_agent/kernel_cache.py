"""Whether an agent's controller runs compiled, and its kernel warmed from numba's cache.

An agent evaluates one controller per control step. Interpreted, a call costs ~0.1 ms; compiled
(numba, loaded from the on-disk cache) ~0.02 ms, but the process then loads numba and the cached
kernels: ~1.4 s more CPU at start and ~120 MB more RSS (BENCHMARKS.md, "Cost of a message").
:func:`compiled_pays` chooses the compiled form

- in lockstep from :data:`COMPILED_FROM_RATE` on (the paper preset's 10 kHz: it pays back after
  ~10 000 steps), interpreted below;
- in realtime when the agents' extra memory fits (:data:`COMPILED_EXTRA_RSS` each within a quarter
  of the memory available): there the CPU a step costs while every agent answers the same tick is
  what decides whether the answers are on time, and the start-up cost is paid before the first
  step (20 agents at 100 Hz: 42 % of the steps answered in time compiled against 17 %
  interpreted, quiet); 50 compiled agents would hold ~10 GB instead of ~4 GB.

The launcher passes the choice as ``NUMBA_DISABLE_JIT``; an agent started alone (agent.sh) runs
interpreted unless its environment says ``NUMBA_DISABLE_JIT=0``.
"""

from __future__ import annotations

import importlib.metadata
import os
import pickle
from pathlib import Path
from typing import TYPE_CHECKING

from formation_core.numba_kernels import cache_index_glob

if TYPE_CHECKING:  # the agent's view: not imported for --help
    from formation_core.formation import AgentView

#: lockstep control rate [Hz] from which the launcher starts agents with the compiled controller
COMPILED_FROM_RATE = 1000.0
#: RSS a compiled agent holds more than an interpreted one (numba, llvmlite, the cached kernels) [bytes]
COMPILED_EXTRA_RSS = 125 * 2**20


def numba_cache_warm(package: Path = Path(__file__).parent) -> bool:
    """Whether numba's on-disk cache holds the controller's kernel for the sources as they are now.

    The simulator compiles it (its shadow controllers call it) at a first run or after a change of
    ``controller.py`` or of a module it imports; agents that found no fresh entry would each compile
    it at start (~10 s of CPU each: 20 of them miss the discovery timeout). The entry's file name
    holds :func:`formation_core.numba_kernels.sources_stamp` (every source compiled into the kernel)
    and the index starts with numba's version: both are checked here without importing numba
    (the index is not unpickled past its version).
    """
    try:
        patterns = cache_index_glob(package / "controller.py", "agent_step")
        version = importlib.metadata.version("numba")
    except (OSError, importlib.metadata.PackageNotFoundError):
        return False
    for pattern in patterns:
        for index in pattern.parent.glob(pattern.name):
            try:
                with index.open("rb") as f:
                    if pickle.load(f) == version:
                        return True
            except (OSError, pickle.UnpicklingError, EOFError):
                continue
    return False


def warm_up(view: AgentView) -> None:
    """One controller step of agent ``view`` on made-up measurements: loads the kernel from numba's
    cache (or compiles and caches it) before a node subscribes, not at its first step. The simulator
    calls it too, so that a run after a change of ``controller.py`` leaves a fresh cache for the
    agents of the next (its own agents then run interpreted: :func:`numba_cache_warm` said stale)."""
    from formation_agent.controller import AgentController

    identity = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    AgentController(view).compute(0.0, {j: ((1.0, 0.0, 0.0), identity) for j in view.neighbours}, (0.0,) * 6)


def available_memory() -> int:
    """Memory available to new processes [bytes] (MemAvailable of /proc/meminfo; else all of it)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def compiled_pays(control_rate: float, mode: str, n_agents: int) -> bool:
    """Whether the ``n_agents`` agents of a ``mode`` (lockstep, realtime) run at ``control_rate``
    [Hz] should run the compiled controller (only with numba's cache warm)."""
    if not numba_cache_warm():
        return False
    if mode == "realtime":
        return n_agents * COMPILED_EXTRA_RSS <= available_memory() // 4
    return control_rate >= COMPILED_FROM_RATE
