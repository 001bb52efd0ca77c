"""An animated GIF of a run: the formation in 3D and every edge's funnel margin beside it.

Drawn from a run's ``trajectory.npz`` arrays (headless, ROS 2 or bag analysis: the same format)
with the scene of :mod:`formation_sim.views.markers`, the one the simulator publishes to viewers:
oriented bodies with their frames, tree edges coloured by the worst of their distance and
orientation margins, the desired distance as a ghost, force (orange) and torque (purple) arrows.
Beside it, each edge's worst margin over the run with a cursor at the frame's time.

Frames are taken at ``fps`` per second of simulated time (the GIF plays in real time) and
written with Pillow.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from formation_msgs_py.spec import FormationSpec
from formation_sim.views.markers import ARROW, CUBE, LINE_LIST, SPHERE, TEXT_VIEW_FACING, FormationScene, Shape

ANIMATION_NAME = "animation.gif"


def edge_margins(spec: FormationSpec, arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(T,K) worst of the distance and orientation margins of every edge, from the trajectory arrays."""
    c_col = np.array([e.c_col for e in spec.edges])
    c_con = np.array([e.c_con for e in spec.edges])
    xi_e = arrays["e"] / arrays["rho_e"]
    m_e = np.minimum(1.0 + xi_e / c_col, 1.0 - xi_e / c_con)
    m_psi = 1.0 - arrays["psi"] / arrays["rho_psi"]
    return np.minimum(m_e, m_psi)


class SceneArtists:
    """matplotlib 3D artists for the shapes of a scene, created once and moved every frame."""

    def __init__(self, ax) -> None:
        self.ax = ax
        self.artists: dict[tuple[str, int], list] = {}

    def _make(self, s: Shape) -> list:
        ax = self.ax
        if s.type == LINE_LIST:
            width = 3.0 if s.ns == "edges" else 1.5
            return [ax.plot([], [], [], lw=width)[0] for _ in range(len(s.points) // 2)]
        if s.type == ARROW:
            return [ax.plot([], [], [], lw=2.0)[0], ax.plot([], [], [], marker="o", ms=3)[0]]
        if s.type == CUBE:
            return [ax.plot([], [], [], marker="s", ms=7, ls="")[0]]
        if s.type == SPHERE:
            return [ax.plot([], [], [], marker="o", ms=13, ls="")[0]]
        if s.type == TEXT_VIEW_FACING:
            return [ax.text(0.0, 0.0, 0.0, s.text, fontsize=9)]
        raise ValueError(f"marker type {s.type} of {s.ns}/{s.id} has no matplotlib drawing")

    def update(self, shapes: list[Shape]) -> None:
        for s in shapes:
            key = (s.ns, s.id)
            if key not in self.artists:
                self.artists[key] = self._make(s)
            artists = self.artists[key]
            if s.type == LINE_LIST:
                for k, line in enumerate(artists):
                    (x0, y0, z0), (x1, y1, z1) = s.points[2 * k], s.points[2 * k + 1]
                    line.set_data_3d([x0, x1], [y0, y1], [z0, z1])
                    colour = s.colors[2 * k] if s.colors else s.color
                    line.set_color(colour[:3])
            elif s.type == ARROW:
                (x0, y0, z0), (x1, y1, z1) = s.points
                artists[0].set_data_3d([x0, x1], [y0, y1], [z0, z1])
                artists[1].set_data_3d([x1], [y1], [z1])
                for a in artists:
                    a.set_color(s.color[:3])
            elif s.type in (CUBE, SPHERE):
                x, y, z = s.position
                artists[0].set_data_3d([x], [y], [z])
                artists[0].set_color(s.color[:3])
                artists[0].set_alpha(min(1.0, s.color[3] + 0.15))
            else:
                artists[0].set_position_3d(s.position)


class RunFigure:
    """The animation's figure: the 3D scene of one sample and the margins with a time cursor."""

    def __init__(self, spec: FormationSpec, arrays: dict[str, np.ndarray]) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import MaxNLocator

        self.spec, self.arrays = spec, arrays
        t, p = arrays["t"], arrays["p"]
        self.scene = FormationScene(spec)
        margins = edge_margins(spec, arrays)
        lo, hi = p.min(axis=(0, 1)), p.max(axis=(0, 1))
        self.centre = (lo + hi) / 2
        self.half = max(float(np.max(hi - lo)) / 2, 1.0) + float(np.max(self.scene.radius))
        self.fig = plt.figure(figsize=(10.0, 4.8))
        # no tight_layout: it ignores the 3D axis labels, and z [m] then sits against the margins' axis
        grid = self.fig.add_gridspec(1, 2, width_ratios=(1.2, 1.0), left=0.0, right=0.98, bottom=0.11, wspace=0.3)
        self.ax3d = self.fig.add_subplot(grid[0], projection="3d")
        for setter, c in zip((self.ax3d.set_xlim, self.ax3d.set_ylim, self.ax3d.set_zlim), self.centre):
            setter(c - self.half, c + self.half)
        self.ax3d.set_xlabel("x [m]")
        self.ax3d.set_ylabel("y [m]")
        self.ax3d.set_zlabel("z [m]")
        for axis in (self.ax3d.xaxis, self.ax3d.yaxis, self.ax3d.zaxis):
            axis.set_major_locator(MaxNLocator(4))  # tick labels are most of a 3D frame's drawing time
        self.ax3d.tick_params(labelsize=7)
        self.shapes = SceneArtists(self.ax3d)
        axm = self.fig.add_subplot(grid[1])
        every = max(1, len(t) // 1000)  # a line of ≤ 1000 points draws as well and much faster
        for k, e in enumerate(spec.edges):
            axm.plot(t[::every], margins[::every, k], lw=1.2, label=f"edge {e.tail}-{e.head}")
        axm.axhline(0.0, color="k", lw=0.8)
        axm.set_ylim(min(-0.05, float(np.min(margins)) - 0.05), 1.05)
        axm.set_xlabel("t [s]")
        axm.set_ylabel("worst margin of e and ψ (1 centre, 0 bound)")
        axm.set_title("funnel margins", fontsize=10)
        axm.grid(alpha=0.3)
        axm.legend(fontsize=7, loc="lower right")
        self.cursor = axm.axvline(t[0], color="C3", lw=1.0)

    def draw(self, s: int) -> None:
        """Show sample ``s`` of the trajectory."""
        a = self.arrays
        t = float(a["t"][s])
        self.shapes.update(self.scene.shapes(t, a["p"][s], a["R"][s], a["u"][s]))
        self.ax3d.set_title(f"{self.spec.name}   t = {t:.2f} s", fontsize=10)
        self.cursor.set_xdata([t, t])

    def close(self) -> None:
        import matplotlib.pyplot as plt

        plt.close(self.fig)


def write_animation(
    out_dir: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], *, fps: float = 20.0, dpi: int = 80
) -> tuple[Path, int, float]:
    """Write ``out_dir/animation.gif``; returns (path, frames, wall seconds).

    Each frame is drawn once on the Agg canvas and kept as a Pillow image (matplotlib's
    PillowWriter draws every frame twice); Pillow writes the GIF.
    """
    from PIL import Image

    started = time.perf_counter()
    t = arrays["t"]
    frame_times = np.arange(t[0], t[-1] + 1e-9, 1.0 / fps)
    samples = np.minimum(np.searchsorted(t, frame_times), len(t) - 1)
    figure = RunFigure(spec, arrays)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    figure.fig.set_dpi(dpi)
    frames = []
    try:
        for s in samples:
            figure.draw(int(s))
            canvas = figure.fig.canvas
            assert isinstance(canvas, FigureCanvasAgg)  # RunFigure selects the Agg backend
            canvas.draw()
            rgba = np.asarray(canvas.buffer_rgba())
            frames.append(Image.fromarray(rgba[..., :3]).quantize(colors=128))
    finally:
        figure.close()
    path = out_dir / ANIMATION_NAME
    tmp = out_dir / (ANIMATION_NAME + ".part")
    frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0)
    tmp.replace(path)
    return path, len(samples), time.perf_counter() - started


def write_frame(path: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], t_frame: float, dpi: int = 100) -> Path:
    """The animation's frame at time ``t_frame`` [s] as a PNG (for documentation)."""
    figure = RunFigure(spec, arrays)
    try:
        figure.draw(min(int(np.searchsorted(arrays["t"], t_frame)), len(arrays["t"]) - 1))
        figure.fig.savefig(path, dpi=dpi)
    finally:
        figure.close()
    return path
