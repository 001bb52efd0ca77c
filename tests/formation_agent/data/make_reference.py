"""Freeze the controller's outputs on seeded random configurations (provenance of controller_reference.npz).

Run once with the hand-unrolled controller of commit a2d582a (before the controller was rewritten as
the paper's steps): ``.venv/bin/python tests/formation_agent/data/make_reference.py``. The test
``test_controller_reference.py`` replays the same configurations through today's controller.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from formation_agent.controller import AgentController
from formation_core.formation import agent_view
from formation_core.spec import load_formation

ROOT = Path(__file__).resolve().parents[3]
CASES = 200


def relative_poses(spec, p, R, agent):
    idx = {a.id: a.index for a in spec.agents}
    i = idx[agent]
    return {
        ie.neighbour: (R[i].T @ (p[idx[ie.neighbour]] - p[i]), R[i].T @ R[idx[ie.neighbour]])
        for ie in agent_view(spec, agent).edges
    }


def main() -> None:
    spec = load_formation(ROOT / "config" / "paper_5agents.yaml")
    rng = np.random.default_rng(20261128)
    p0 = np.array([a.position for a in spec.agents])
    R0 = np.array([a.R_world_body for a in spec.agents])
    n = len(spec.agents)
    fields = ("wrench", "v_des", "e", "psi", "xi_e", "xi_psi", "margin_e", "margin_psi", "xi_v", "margin_v")
    out: dict[str, list] = {k: [] for k in ("p", "R", "v", "t0", "t", "v0", "level", *fields)}
    for _ in range(CASES):
        # mostly small perturbations (inside the funnels), some large (saturated)
        scale = 0.05 if rng.random() < 0.8 else 0.6
        p = p0 + rng.normal(scale=scale, size=p0.shape)
        R = np.array([R0[i] @ Rotation.from_rotvec(rng.normal(scale=scale, size=3)).as_matrix() for i in range(n)])
        v = rng.normal(scale=0.5, size=(n, 6))
        v0 = rng.normal(scale=0.5, size=(n, 6))
        t0 = float(rng.uniform(0.0, 1.0))
        t = t0 + float(rng.uniform(0.0, 4.0))
        rows = {k: [] for k in ("level", *fields)}
        for i, a in enumerate(spec.agents):
            ctrl = AgentController(agent_view(spec, a.id))
            ctrl.compute(t0, relative_poses(spec, p, R, a.id), v0[i])  # sets ρ_v0 from this first step
            o = ctrl.compute(t, relative_poses(spec, p, R, a.id), v[i])
            for k in fields:
                val = np.array(getattr(o, k))
                rows[k].append(np.pad(val, (0, 6 - len(val)), constant_values=np.nan))
            rows["level"].append(o.level)
        for k, val in (("p", p), ("R", R), ("v", v), ("t0", t0), ("t", t), ("v0", v0)):
            out[k].append(val)
        for k, val in rows.items():
            out[k].append(np.array(val))
    arrays = {k: np.array(v) for k, v in out.items()}
    np.savez_compressed(Path(__file__).with_name("controller_reference.npz"), **arrays)


if __name__ == "__main__":
    main()
