"""``formation-agent``: one agent process. The controller kernels run interpreted in it.

An agent process evaluates one controller per control step, at the rate ROS delivers
measurements; loading numba and the compiled kernels costs more start time and memory per
process than the interpreted form of the same source costs per step (BENCHMARKS.md, "Agent
process"), and 50 such processes share a host. ``NUMBA_DISABLE_JIT=0`` in the environment
selects the compiled kernels instead.
"""

from __future__ import annotations

import os


def main(args: list[str] | None = None) -> int:
    os.environ.setdefault("NUMBA_DISABLE_JIT", "1")
    from formation_agent.agent_node import main as node_main

    return node_main(args)
