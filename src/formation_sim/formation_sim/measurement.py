"""What the agents sense: relative poses of their tree neighbours and their own noisy twist.

For a tree edge between agents i and j, agent i receives (docs/topics.md), while j is within
i's sensing radius::

    p_i_j_in_i = R_iᵀ (p_j − p_i)    [m, frame agent_i]
    R_i_j      = R_iᵀ R_j

optionally with seeded Gaussian noise (position_std [m] per axis; rotation_std [rad], a
rotation vector applied on the right) of the receiving agent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from formation_msgs_py.so3 import exp_so3
from formation_msgs_py.spec import SimulatorView

#: {agent_id: {neighbour_id: (p_i_j_in_i [3], R_i_j [3][3])}} as Python lists
RelativePoses = dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]


@dataclass(frozen=True)
class Link:
    """Directed sensing link: observer i measures target j."""

    observer: int
    target: int
    observer_id: str
    target_id: str
    sensing_radius: float
    position_std: float
    rotation_std: float


class MeasurementModel:
    """Relative-pose measurements along the tree, in both directions of every edge."""

    def __init__(self, view: SimulatorView, rng: np.random.Generator) -> None:
        index = {a.id: a.index for a in view.agents}
        links = []
        for e in view.edges:
            for obs, tgt in ((e.tail, e.head), (e.head, e.tail)):
                a = view.agents[index[obs]]
                links.append(
                    Link(index[obs], index[tgt], obs, tgt, a.sensing_radius, a.position_noise_std, a.rotation_noise_std)
                )
        self.links = tuple(links)
        self.agent_ids = tuple(a.id for a in view.agents)
        self._obs = np.array([lk.observer for lk in links])
        self._tgt = np.array([lk.target for lk in links])
        self._radius = np.array([lk.sensing_radius for lk in links])
        self._pos_std = np.array([lk.position_std for lk in links])
        self._rot_std = np.array([lk.rotation_std for lk in links])
        self._noisy = bool(np.any(self._pos_std > 0) or np.any(self._rot_std > 0))
        self.rng = rng

    def measure(self, p: np.ndarray, R: np.ndarray) -> RelativePoses:
        """Relative poses every agent receives now, from world poses p (N,3), R (N,3,3)."""
        Ri_T = np.swapaxes(R[self._obs], 1, 2)
        d_world = p[self._tgt] - p[self._obs]
        p_rel = np.einsum("lij,lj->li", Ri_T, d_world)
        R_rel = Ri_T @ R[self._tgt]
        in_range = np.einsum("li,li->l", d_world, d_world) <= self._radius**2
        if self._noisy:
            # Drawn for every link, in a fixed order, so the stream does not depend on range.
            p_rel = p_rel + self.rng.standard_normal(p_rel.shape) * self._pos_std[:, None]
            R_rel = R_rel @ exp_so3(self.rng.standard_normal(p_rel.shape) * self._rot_std[:, None])
        out: RelativePoses = {aid: {} for aid in self.agent_ids}
        # Python lists: what the controller reads fastest (and what messages carry).
        p_list, R_list, ok = p_rel.tolist(), R_rel.tolist(), in_range.tolist()
        for k, lk in enumerate(self.links):
            if ok[k]:
                out[lk.observer_id][lk.target_id] = (p_list[k], R_list[k])
        return out
