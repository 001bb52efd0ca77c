"""The headless paper scenario frozen: tests/formation_sim/data/paper_headless_reference.npz.

``.venv/bin/python tests/paper_reference.py`` runs today's compiled headless
loop on config/paper_5agents.yaml and stores e, ψ at the record rate, the final states, every margin
and peak wrench, and the numeric platform and code form that computed them
(formation_core.numba_kernels). ``tests/formation_sim/test_headless.py`` compares a run with it: bit for bit on that
platform, within the closed loop's response to round-off elsewhere. Run it again when a change
of the code is meant to change the run's last places (an operation order, a formula).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from formation_core.numba_kernels import CODE_FORM, numeric_platform
from formation_core.spec import load_formation
from formation_sim.cli.headless import run_headless

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "tests" / "formation_sim" / "data" / "paper_headless_reference.npz"


def golden_values(recorder) -> dict[str, np.ndarray]:
    """What the reference keeps of a run (a :class:`formation_sim.core.recorder.RunRecorder`)."""
    arrays, judge = recorder.arrays(), recorder.judge
    return {
        "t": arrays["t"],
        "e": arrays["e"],
        "psi": arrays["psi"],
        "p_final": arrays["p"][-1],
        "R_final": arrays["R"][-1],
        "v_final": arrays["v"][-1],
        "min_margin_e": np.asarray(judge.min_margin_e),
        "min_margin_psi": np.asarray(judge.min_margin_psi),
        "min_margin_v": np.asarray(judge.min_margin_v),
        "peak_force": np.asarray(recorder.peak_force),
        "peak_torque": np.asarray(recorder.peak_torque),
    }


def main() -> None:
    spec = load_formation(ROOT / "config" / "paper_5agents.yaml")
    values = golden_values(run_headless(spec).recorder)
    np.savez_compressed(REFERENCE, platform=np.array(numeric_platform()), code_form=np.array(CODE_FORM), **values)
    print(f"wrote {REFERENCE} (platform {numeric_platform()}, {CODE_FORM})")


if __name__ == "__main__":
    main()
