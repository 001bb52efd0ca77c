"""``formation-sim``'s command line, checked before rclpy and the cores are imported.

``--help``, a bad option and a bad formation file end here (exit 0, 2, 2) in a fraction of a
second, without rclpy or numba; a valid run goes on in :mod:`formation_sim.node.sim_node` with the
pre-flight result (the file is read once).
"""

from __future__ import annotations

import sys

from formation_core.verdict import guarded
from formation_sim.node.sim_options import sim_preflight


@guarded("formation-sim")
def sim(argv: list[str] | None = None) -> int:
    """Entry point of ``formation-sim``."""
    raw = list(sys.argv if argv is None else [sys.argv[0], *argv])
    run = sim_preflight(raw)
    from formation_sim.node.sim_node import main

    return main(argv, prepared=run)
