"""The controller written as the paper's steps gives the wrenches of the hand-unrolled one it replaced.

``data/controller_reference.npz`` holds the outputs of the controller of commit a2d582a (with its
100 N, 100 N·m limits) on 200 seeded configurations of the paper's formation (80 % inside every
funnel, 20 % far outside: saturated, at the limits), made by ``data/make_reference.py``.
Tolerance 1e-12, relative for values above 1: the same formulas in the same order up to a few
roundings (r_ψ/ρ_ψ as two divisions), so the outputs differ by a few units in the last place.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from formation_agent.controller import AgentController
from formation_msgs_py.spec import agent_view, load_formation

DATA = np.load(Path(__file__).with_name("data") / "controller_reference.npz")
FIELDS = ("wrench", "v_des", "e", "psi", "xi_e", "xi_psi", "margin_e", "margin_psi", "xi_v", "margin_v")


def relative_poses(spec, p, R, agent):
    idx = {a.id: a.index for a in spec.agents}
    i = idx[agent]
    return {
        ie.neighbour: (R[i].T @ (p[idx[ie.neighbour]] - p[i]), R[i].T @ R[idx[ie.neighbour]])
        for ie in agent_view(spec, agent).edges
    }


def replay(spec, controller_class=AgentController):
    """Today's outputs on every frozen configuration: {field: (cases, agents, 6)}, levels."""
    out = {k: [] for k in FIELDS}
    levels = []
    for c in range(len(DATA["t"])):
        p, R, v, v0 = DATA["p"][c], DATA["R"][c], DATA["v"][c], DATA["v0"][c]
        rows = {k: [] for k in FIELDS}
        lv = []
        for i, a in enumerate(spec.agents):
            ctrl = controller_class(agent_view(spec, a.id))
            ctrl.compute(float(DATA["t0"][c]), relative_poses(spec, p, R, a.id), v0[i])
            o = ctrl.compute(float(DATA["t"][c]), relative_poses(spec, p, R, a.id), v[i])
            for k in FIELDS:
                val = np.array(getattr(o, k))
                rows[k].append(np.pad(val, (0, 6 - len(val)), constant_values=np.nan))
            lv.append(o.level)
        for k in FIELDS:
            out[k].append(rows[k])
        levels.append(lv)
    return {k: np.array(v) for k, v in out.items()}, np.array(levels)


def test_same_outputs_as_the_hand_unrolled_controller(paper_path: Path) -> None:
    """Every output of every agent on 200 configurations equals the frozen one to 1e-12 (levels exactly)."""
    spec = load_formation(paper_path)
    out, levels = replay(spec)
    assert 0 < np.count_nonzero(levels == 2) < levels.size  # both saturated and regular cases are covered
    np.testing.assert_array_equal(levels, DATA["level"])
    for k in FIELDS:
        np.testing.assert_allclose(out[k], DATA[k], rtol=1e-12, atol=1e-12, err_msg=k)


def test_interpreted_and_compiled_controllers_agree(paper_path: Path, tmp_path: Path) -> None:
    """The same source run as Python (NUMBA_DISABLE_JIT=1, another process) gives the compiled wrenches to 1e-12.

    Relative for values above 1, as above: the interpreter and LLVM may round a few operations
    differently (no fast-math is used, so only the last place can differ).
    """
    out_file = tmp_path / "interpreted.npz"
    script = (
        "import sys, numpy as np; sys.path.insert(0, sys.argv[1]);"
        "from formation_msgs_py.compiled import INTERPRETED; assert INTERPRETED;"
        "from formation_msgs_py.spec import load_formation;"
        "import test_controller_reference as t;"
        "out, levels = t.replay(load_formation(sys.argv[2]));"
        "np.savez(sys.argv[3], levels=levels, **out)"
    )
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    subprocess.run(
        [sys.executable, "-c", script, str(Path(__file__).parent), str(paper_path), str(out_file)], env=env, check=True
    )
    interpreted = np.load(out_file)
    compiled, levels = replay(load_formation(paper_path))
    np.testing.assert_array_equal(interpreted["levels"], levels)
    for k in FIELDS:
        np.testing.assert_allclose(interpreted[k], compiled[k], rtol=1e-12, atol=1e-12, err_msg=k)
