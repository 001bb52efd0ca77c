"""What the agents sense: relative poses of their tree neighbours and their own noisy twist.

For a tree edge between agents i and j, agent i receives (docs/topics.md), while j is within
i's sensing radius::

    p_i_j_in_i = R_iᵀ (p_j − p_i)    [m, frame agent_i]
    R_i_j      = R_iᵀ R_j

optionally with seeded Gaussian noise (position_std [m] per axis; rotation_std [rad], a
rotation vector applied on the right) of the receiving agent. The rotation travels as the
quaternion of the message (:func:`formation_core.rotations.quaternion_of_rows`), and what a
controller reads is the matrix an agent decodes from it
(:func:`formation_core.rotations.rows_of_quaternion`): the model gives both, so that every run
(headless, lockstep, the simulator's witness) computes on the values an agent receives.

Measurements are indexed by *edge end* (agent i's view of one of its edges, grouped by agent in
the order of ``agent_view(spec, i).edges``), the order the controller kernels read. The noise is
drawn per *link*, two per edge in file order (tail observes head, then head observes tail), for
every link at every measurement whether in range or not, so the stream does not depend on range.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from formation_core.formation import SimulatorView
from formation_core.numba_kernels import formula, kernel
from formation_core.rotations import quaternion_of_rows, rows_of_quaternion
from formation_core.so3 import add3, exp_rows, matmul3, matrix_rows, matTvec3, scale3, set3x3, transpose3, vec3

#: {agent_id: {neighbour_id: (p_i_j_in_i (3,), R_i_j (3,3))}}
RelativePoses = dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]


class Ends(NamedTuple):
    """The edge ends by id, in the controllers' order: end k is ``observer[k]``'s view of ``target[k]``."""

    agent_ids: tuple[str, ...]  # every agent, in formation-file order
    observer: tuple[str, ...]
    target: tuple[str, ...]


class Sensing(NamedTuple):
    """Per edge end: who observes whom, the link whose noise it takes, range and noise constants."""

    observer: np.ndarray  # (n_ends,) agent index
    target: np.ndarray  # (n_ends,) agent index
    link: np.ndarray  # (n_ends,) row of the noise draws: 2·edge + (0 tail, 1 head)
    radius2: np.ndarray  # sensing radius² of the observer [m²]
    position_std: np.ndarray  # [m]
    rotation_std: np.ndarray  # [rad]


def sensing(view: SimulatorView) -> Sensing:
    """The edge ends of ``view``'s formation in the controllers' order."""
    index = {a.id: a.index for a in view.agents}
    rows = []
    for a in view.agents:
        for e in view.edges:  # the order of agent_view(spec, a).edges
            if a.id in (e.tail, e.head):
                link, neighbour = (2 * e.index, e.head) if e.tail == a.id else (2 * e.index + 1, e.tail)
                noise = (a.position_noise_std, a.rotation_noise_std)
                rows.append((a.index, index[neighbour], link, a.sensing_radius**2, *noise))
    cols = list(zip(*rows))
    return Sensing(
        np.array(cols[0], dtype=np.int64),
        np.array(cols[1], dtype=np.int64),
        np.array(cols[2], dtype=np.int64),
        np.array(cols[3], dtype=np.float64),
        np.array(cols[4], dtype=np.float64),
        np.array(cols[5], dtype=np.float64),
    )


def measurement_ends(view: SimulatorView) -> Ends:
    """The edge ends of ``view``'s formation by id, in :func:`sensing`'s order."""
    ids = tuple(a.id for a in view.agents)
    s = sensing(view)
    return Ends(ids, tuple(ids[i] for i in s.observer), tuple(ids[j] for j in s.target))


@formula
def measure_end(p, R, sens, noise, k, p_rel, q_rel, R_rel):
    """Edge end k's relative pose, with the observer's noise if ``noise`` holds any: the position
    into ``p_rel`` (3,), the quaternion (x, y, z, w) of the message into ``q_rel`` (4,) and the
    matrix decoded from it into ``R_rel`` (3,3); True if its target is within the observer's
    sensing radius."""
    i, j = sens.observer[k], sens.target[k]
    d_world = (p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2])
    R_world_i = matrix_rows(R[i])
    p_i_j_in_i = matTvec3(R_world_i, d_world)
    R_i_j = matmul3(transpose3(R_world_i), matrix_rows(R[j]))
    if noise.shape[0] > 0:
        lk, s = sens.link[k], sens.rotation_std[k]
        p_i_j_in_i = add3(p_i_j_in_i, scale3(sens.position_std[k], vec3(noise[0, lk])))
        R_i_j = matmul3(R_i_j, exp_rows(scale3(s, vec3(noise[1, lk]))))
    q = quaternion_of_rows(R_i_j)
    for x in range(3):
        p_rel[x] = p_i_j_in_i[x]
    for x in range(4):
        q_rel[x] = q[x]
    set3x3(R_rel, rows_of_quaternion(q[0], q[1], q[2], q[3]))
    return d_world[0] * d_world[0] + d_world[1] * d_world[1] + d_world[2] * d_world[2] <= sens.radius2[k]


@kernel
def relative_poses(p, R, sens, noise, p_rel, q_rel, R_rel, in_range):
    """Fill p_rel (n_ends,3), q_rel (n_ends,4), R_rel (n_ends,3,3), in_range (n_ends,) from world
    poses p (N,3), R (N,3,3) (:func:`measure_end`).

    ``noise`` is (2, n_links, 3) standard normal draws (position, rotation) or empty (no noise).
    """
    for k in range(sens.observer.shape[0]):
        in_range[k] = measure_end(p, R, sens, noise, k, p_rel[k], q_rel[k], R_rel[k])


class MeasurementModel:
    """Relative-pose measurements along the tree, in both directions of every edge."""

    def __init__(self, view: SimulatorView, rng: np.random.Generator) -> None:
        self.sensing = sensing(view)
        self.ends = measurement_ends(view)
        self.n_links = 2 * len(view.edges)
        self.noisy = bool(np.any(self.sensing.position_std > 0) or np.any(self.sensing.rotation_std > 0))
        self.rng = rng
        n = len(self.sensing.observer)
        self.p_rel = np.zeros((n, 3))
        self.q_rel = np.zeros((n, 4))
        self.R_rel = np.zeros((n, 3, 3))
        self.in_range = np.zeros(n, dtype=np.bool_)

    def draw_noise(self, count: int) -> np.ndarray:
        """The noise of ``count`` measurements (count, 2, n_links, 3), in the stream's order."""
        if not self.noisy:
            return np.zeros((count, 0, 0, 3))
        return self.rng.standard_normal((count, 2, self.n_links, 3))

    def measure(self, p: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(p_rel (n_ends,3) [m, observer's frame], q_rel (n_ends,4) the messages' quaternions (x, y, z, w),
        R_rel (n_ends,3,3) decoded from them, in_range (n_ends,)) by edge end (:attr:`ends`), from world
        poses p (N,3), R (N,3,3); new arrays at every call. Every end is computed; an observer receives
        only the ends in range."""
        relative_poses(p, R, self.sensing, self.draw_noise(1)[0], self.p_rel, self.q_rel, self.R_rel, self.in_range)
        return self.p_rel.copy(), self.q_rel.copy(), self.R_rel.copy(), self.in_range.copy()
