"""What a 3D viewer shows of a formation, without ROS: markers as plain data.

The simulator node turns :class:`Shape` lists into ``visualization_msgs/MarkerArray`` on
``/formation/markers`` (frame ``world``); the animation draws the same scene with matplotlib.
One scene per display instant:

- each agent: an oriented box (its body frame ``agent_<id>``: long side along x, short along z),
  the frame's axes (x red, y green, z blue, length r_i) and its id;
- each tree edge: a line coloured by the worst of its distance and orientation margins
  (green 1 … yellow 0.5 … red 0, magenta outside), and a translucent ghost of the head where it
  would sit at the desired distance d_k along the current direction;
- each agent's wrench: force (teal) and torque (purple) arrows in the world frame, length
  ``arrow_scale·ln(1 + |u|)`` m (logarithmic: peaks of 10³ N and steady values of 10⁻² N are
  both visible);
- every body in contact with another (clearance ≤ 0, neighbours or not: the judge's
  :class:`formation_sim.core.judge.Pairs`): a translucent red sphere of its radius around it, so that a
  pair that touches shows as two red spheres meeting (namespace ``contacts``, one per agent, clear
  while it touches nothing: the markers stay the same at every instant).

Positions in m (world frame), orientations as quaternions (x, y, z, w) of R_world_body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from formation_core.formation import FormationSpec
from formation_core.rotations import quaternion_from_matrix
from formation_sim.core.judge import EdgeErrors, Pairs, in_contact

# visualization_msgs/Marker type codes (a ROS message constant, repeated here to stay ROS-free)
ARROW, CUBE, SPHERE, LINE_LIST, TEXT_VIEW_FACING = 0, 1, 2, 5, 9

Vec3 = tuple[float, float, float]
Rgba = tuple[float, float, float, float]

AXIS_COLOURS: tuple[Rgba, Rgba, Rgba] = ((0.9, 0.1, 0.1, 1.0), (0.1, 0.8, 0.1, 1.0), (0.1, 0.3, 0.95, 1.0))
BODY_COLOUR: Rgba = (0.55, 0.6, 0.7, 0.9)
# teal, not orange: orange is a low margin on the edges
FORCE_COLOUR: Rgba = (0.0, 0.6, 0.7, 1.0)
TORQUE_COLOUR: Rgba = (0.6, 0.2, 0.85, 1.0)
CONTACT_COLOUR: Rgba = (0.9, 0.0, 0.0, 0.45)
GHOST_ALPHA = 0.25


@dataclass(frozen=True)
class Shape:
    """One ``visualization_msgs/Marker`` (ADD), by namespace and id."""

    ns: str
    id: int
    type: int
    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: Vec3 = (1.0, 1.0, 1.0)
    color: Rgba = (1.0, 1.0, 1.0, 1.0)
    points: tuple[Vec3, ...] = ()
    colors: tuple[Rgba, ...] = ()
    text: str = ""


def margin_colours(margin: np.ndarray) -> np.ndarray:
    """(K, 4) RGBA of K margins: green at ≥ 1, yellow at 0.5, red at 0, magenta below 0 or NaN."""
    m = np.minimum(np.asarray(margin, dtype=np.float64), 1.0)
    out = np.empty((m.size, 4))
    out[:, 0] = np.where(m >= 0.5, 2.0 * (1.0 - m), 1.0)
    out[:, 1] = np.where(m >= 0.5, 0.8, 1.6 * m)
    out[:, 2] = 0.0
    out[:, 3] = 1.0
    out[~(m >= 0.0)] = (1.0, 0.0, 1.0, 1.0)  # outside the funnel, or not finite
    return out


def margin_colour(margin: float) -> Rgba:
    """The colour of one margin (:func:`margin_colours`)."""
    r, g, b, a = margin_colours(np.array([margin]))[0].tolist()
    return (r, g, b, a)


def arrow_length(magnitude: float, arrow_scale: float) -> float:
    """Displayed length [m] of a force [N] or torque [N·m]: arrow_scale·ln(1 + |u|)."""
    return float(arrow_scale * np.log1p(abs(magnitude)))


def _v(x: np.ndarray) -> Vec3:
    return (float(x[0]), float(x[1]), float(x[2]))


def _v4(x: np.ndarray) -> tuple[float, float, float, float]:
    return (float(x[0]), float(x[1]), float(x[2]), float(x[3]))


@dataclass(frozen=True)
class SceneFrame:
    """What moves in one display instant, world frame [m]: N agents, K edges.

    ``q`` (N,4) quaternions (x, y, z, w) of R_world_body; ``axis_ends`` (N,3,3): end of body axis c
    of agent i at ``[i, c]``; ``labels`` (N,3); ``tips`` (N,2,3): tips of the force and torque
    arrows (they start at ``p``); ``edge_ends`` (K,2,3) tail and head; ``edge_colours`` (K,4) RGBA by
    the worst margin; ``ghosts`` (K,3); ``funnels``: :meth:`FormationScene.funnels`; ``touching`` (N,):
    whether each agent is in contact with another body.
    """

    t: float
    p: np.ndarray
    q: np.ndarray
    axis_ends: np.ndarray
    labels: np.ndarray
    tips: np.ndarray
    edge_ends: np.ndarray
    edge_colours: np.ndarray
    ghosts: np.ndarray
    funnels: dict[str, np.ndarray]
    touching: np.ndarray


class FormationScene:
    """Markers of one formation; :meth:`shapes` gives those of one instant."""

    def __init__(self, spec: FormationSpec, *, arrow_scale: float = 0.25) -> None:
        self.spec = spec
        self.arrow_scale = arrow_scale
        index = {a.id: a.index for a in spec.agents}
        self.ids = spec.agent_ids
        self.radius = np.array([a.radius for a in spec.agents])
        self.tail = np.array([index[e.tail] for e in spec.edges], dtype=int)
        self.head = np.array([index[e.head] for e in spec.edges], dtype=int)
        self.d_des = np.array([e.d_des for e in spec.edges])
        self.edges = EdgeErrors(spec)
        self.pairs = Pairs(spec)

    def funnels(self, t: float, p: np.ndarray, R: np.ndarray) -> dict[str, np.ndarray]:
        """Per edge (K,): e [m²], its bounds −C_col·ρ_e and C_con·ρ_e, ψ, ρ_ψ, and the margins."""
        e, psi = self.edges.errors(p, R)  # the judge's formulas (formation_sim.core.judge)
        rho_e, rho_psi, _, margin_e, margin_psi = self.edges.margins(t, e, psi)
        return {
            "e": e,
            "e_lower": -self.edges.c_col * rho_e,
            "e_upper": self.edges.c_con * rho_e,
            "psi": psi,
            "rho_psi": rho_psi,
            "margin_e": margin_e,
            "margin_psi": margin_psi,
        }

    def frame(self, t: float, p: np.ndarray, R: np.ndarray, u: np.ndarray | None) -> SceneFrame:
        """The scene at time t [s] from world poses p (N,3), R (N,3,3) and body wrenches u (N,6; None: 0)."""
        n = len(self.ids)
        r = self.radius
        q = np.array([quaternion_from_matrix(Ri) for Ri in R.tolist()])
        axis_ends = p[:, None, :] + r[:, None, None] * np.swapaxes(R, 1, 2)  # row c: p + r·(column c of R)
        labels = p + np.outer(0.6 * r, (0.0, 0.0, 1.0))
        body = np.zeros((n, 2, 3)) if u is None else np.asarray(u, dtype=np.float64).reshape(n, 2, 3)
        w_world = np.einsum("nij,nkj->nki", R, body)  # force and torque in the world frame
        norm = np.linalg.norm(w_world, axis=-1)
        length = self.arrow_scale * r[:, None] * np.log1p(norm)
        unit = np.divide(w_world, norm[..., None], out=np.zeros_like(w_world), where=norm[..., None] > 0.0)
        tips = p[:, None, :] + unit * length[..., None]
        f = self.funnels(t, p, R)
        a, b = p[self.tail], p[self.head]
        direction = b - a
        dist = np.linalg.norm(direction, axis=-1)
        ahead = np.divide(
            direction, dist[:, None], out=np.tile([1.0, 0.0, 0.0], (len(dist), 1)), where=dist[:, None] > 0.0
        )
        return SceneFrame(
            t=t,
            p=p,
            q=q,
            axis_ends=axis_ends,
            labels=labels,
            tips=tips,
            edge_ends=np.stack([a, b], axis=1),
            edge_colours=margin_colours(np.minimum(f["margin_e"], f["margin_psi"])),
            ghosts=a + ahead * self.d_des[:, None],
            funnels=f,
            touching=self.touching(p),
        )

    def touching(self, p: np.ndarray) -> np.ndarray:
        """(N,) whether each agent touches another body at world positions p (N,3)."""
        pairs = in_contact(self.pairs.clearances(p))
        out = np.zeros(len(self.ids), dtype=bool)
        out[self.pairs.i[pairs]] = True
        out[self.pairs.j[pairs]] = True
        return out

    def shapes(self, t: float, p: np.ndarray, R: np.ndarray, u: np.ndarray | None) -> list[Shape]:
        """Every marker at time t [s] (:meth:`frame`); no wrench arrows when ``u`` is None."""
        return self.shapes_of(self.frame(t, p, R, u), arrows=u is not None)

    def shapes_of(self, f: SceneFrame, arrows: bool = True) -> list[Shape]:
        """The markers of one :class:`SceneFrame`, agents then edges (the order of /formation/markers)."""
        out: list[Shape] = []
        cols = tuple(AXIS_COLOURS[c] for c in range(3) for _ in range(2))
        for i, aid in enumerate(self.ids):
            r = float(self.radius[i])
            start = _v(f.p[i])
            q = _v4(f.q[i])
            out.append(Shape("bodies", i, CUBE, start, q, (0.8 * r, 0.5 * r, 0.25 * r), BODY_COLOUR))
            pts = tuple(x for c in range(3) for x in (start, _v(f.axis_ends[i, c])))
            out.append(Shape("frames", i, LINE_LIST, scale=(0.03 * r, 0.0, 0.0), points=pts, colors=cols))
            out.append(Shape("labels", i, TEXT_VIEW_FACING, _v(f.labels[i]), scale=(0.0, 0.0, 0.4 * r), text=str(aid)))
            if arrows:
                scale = (0.05 * r, 0.1 * r, 0.1 * r)
                for c, (ns, colour) in enumerate((("forces", FORCE_COLOUR), ("torques", TORQUE_COLOUR))):
                    out.append(Shape(ns, i, ARROW, scale=scale, color=colour, points=(start, _v(f.tips[i, c]))))
        for k in range(len(self.d_des)):
            colour = _v4(f.edge_colours[k])
            width = 0.06 * float(min(self.radius[self.tail[k]], self.radius[self.head[k]]))
            ends = (_v(f.edge_ends[k, 0]), _v(f.edge_ends[k, 1]))
            out.append(Shape("edges", k, LINE_LIST, scale=(width, 0.0, 0.0), color=colour, points=ends))
            size = 0.5 * float(self.radius[self.head[k]])
            ghost = (colour[0], colour[1], colour[2], GHOST_ALPHA)
            out.append(Shape("desired", k, SPHERE, _v(f.ghosts[k]), scale=(size, size, size), color=ghost))
        for i in range(len(self.ids)):
            size = 2.0 * float(self.radius[i])
            colour = CONTACT_COLOUR if f.touching[i] else (*CONTACT_COLOUR[:3], 0.0)
            out.append(Shape("contacts", i, SPHERE, _v(f.p[i]), scale=(size, size, size), color=colour))
        return out
