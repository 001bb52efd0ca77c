"""Freeze the headless paper scenario (provenance of paper_headless_reference.npz).

Run once with the interpreted closed loop of commit a93bff2 (before the run core was compiled):
``.venv/bin/python tests/formation_sim/data/make_paper_reference.py``. ``test_headless.py`` compares
today's run with it (e, ψ at the record rate and every margin, to 1e-9).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from formation_msgs_py.spec import load_formation
from formation_sim.cli.headless import run_headless

ROOT = Path(__file__).resolve().parents[3]


def main() -> None:
    spec = load_formation(ROOT / "config" / "paper_5agents.yaml")
    result = run_headless(spec)
    rec = result.recorder
    arr = rec.arrays()
    np.savez_compressed(
        Path(__file__).with_name("paper_headless_reference.npz"),
        t=arr["t"],
        e=arr["e"],
        psi=arr["psi"],
        p_final=arr["p"][-1],
        R_final=arr["R"][-1],
        v_final=arr["v"][-1],
        min_margin_e=rec.min_margin_e,
        min_margin_psi=rec.min_margin_psi,
        min_margin_v=rec.min_margin_v,
        peak_force=rec.peak_force,
        peak_torque=rec.peak_torque,
    )


if __name__ == "__main__":
    main()
