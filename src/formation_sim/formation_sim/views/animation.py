"""An animated GIF of a run: the formation in 3D and every edge's funnel margin beside it.

Drawn from a run's ``trajectory.npz`` arrays (headless, ROS 2 or bag analysis: the same format)
with the scene of :mod:`formation_sim.views.markers`, the one the simulator publishes to viewers:
oriented bodies with their frames, tree edges coloured by the worst of their distance and
orientation margins, the desired distance as a ghost, force (teal) and torque (purple) arrows.
Beside it, each edge's worst margin over the run with a cursor at the frame's time, and below
them a key: what the edge colours, the ghosts, the arrows and the body axes mean. The margin
curves use colours that mean nothing else in the frame (no red, orange, yellow or green: those
are the margin scale; no teal or purple: the arrows), and the cursor is black.

Frames are taken at ``fps`` per second of simulated time (the GIF plays in real time) and
written with Pillow, every frame with the same palette (a GIF's colours are a palette per frame:
quantised one by one, a colour drifted between frames).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from formation_core import funnels
from formation_core.formation import FormationSpec
from formation_sim.views.markers import (
    ARROW,
    AXIS_COLOURS,
    CUBE,
    FORCE_COLOUR,
    LINE_LIST,
    SPHERE,
    TEXT_VIEW_FACING,
    TORQUE_COLOUR,
    FormationScene,
    Rgba,
    Shape,
    margin_colour,
)

if TYPE_CHECKING:  # Pillow: imported when an animation is written
    from PIL.Image import Image as PILImage

ANIMATION_NAME = "animation.gif"
#: the margin curves' colours: blues, greys and browns, none of the scene's meanings
EDGE_CURVE_COLOURS = ("#1f77b4", "#7f7f7f", "#8c564b", "#393b79", "#708090", "#9c9ede", "#000080", "#5f9ea0")
#: samples of the run from which the GIF's one palette is made
PALETTE_SAMPLES = 12


def edge_margins(spec: FormationSpec, arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(T,K) worst of the distance and orientation margins of every edge, from the trajectory arrays."""
    c_col = np.array([e.c_col for e in spec.edges])
    c_con = np.array([e.c_con for e in spec.edges])
    m_e = funnels.margin_e(arrays["e"] / arrays["rho_e"], c_col, c_con)
    m_psi = funnels.margin_psi(arrays["psi"] / arrays["rho_psi"])
    return np.minimum(m_e, m_psi)


class SceneArtists:
    """matplotlib 3D artists for the shapes of a scene, created once and moved every frame."""

    def __init__(self, ax: Any) -> None:  # a 3D Axes: mpl_toolkits.mplot3d ships no types
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
            return [ax.plot([], [], [], marker="s", ms=11, ls="")[0]]
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
        self.fig = plt.figure(figsize=(10.0, 5.6))
        # no tight_layout: it ignores the 3D axis labels, and z [m] then sits against the margins' axis
        grid = self.fig.add_gridspec(1, 2, width_ratios=(1.2, 1.0), left=0.0, right=0.98, bottom=0.26, wspace=0.3)
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
            colour = EDGE_CURVE_COLOURS[k % len(EDGE_CURVE_COLOURS)]
            axm.plot(t[::every], margins[::every, k], lw=1.2, color=colour, label=f"edge {e.tail}-{e.head}")
        axm.axhline(0.0, color="k", lw=0.8)
        axm.set_ylim(min(-0.05, float(np.min(margins)) - 0.05), 1.05)
        axm.set_xlabel("t [s]")
        axm.set_ylabel("worst margin of e and ψ (1 centre, 0 bound)")
        axm.set_title("funnel margins", fontsize=10)
        axm.grid(alpha=0.3)
        axm.legend(fontsize=8, loc="lower right")
        self.cursor = axm.axvline(t[0], color="k", lw=1.0, ls="--")
        self._key()

    def _key(self) -> None:
        """The legend of the 3D scene, below both panels."""
        from matplotlib.lines import Line2D

        def line(colour: str | Rgba, label: str, **style: Any) -> Line2D:
            rgb = colour if isinstance(colour, str) else (colour[0], colour[1], colour[2])
            return Line2D([], [], color=rgb, label=label, **style)

        handles = [
            *(line(margin_colour(m), f"edge, margin {m:g}", lw=3) for m in (1.0, 0.5, 0.0)),
            line(margin_colour(-1.0), "edge, outside its funnel", lw=3),
            line("0.55", "head at the desired distance (edge colour)", marker="o", ms=10, ls="", alpha=0.75),
            line(FORCE_COLOUR, "force (length ∝ ln(1+|f|))", lw=2),
            line(TORQUE_COLOUR, "torque (length ∝ ln(1+|τ|))", lw=2),
            *(line(AXIS_COLOURS[c], f"body {axis} axis", lw=1.5) for c, axis in enumerate("xyz")),
            line("k", "time of the frame", lw=1.0, ls="--"),
        ]
        self.fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False)

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
    rgb = []
    try:
        for s in samples:
            figure.draw(int(s))
            canvas = figure.fig.canvas
            assert isinstance(canvas, FigureCanvasAgg)  # RunFigure selects the Agg backend
            canvas.draw()
            rgb.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3].copy()))
    finally:
        figure.close()
    palette = _palette(rgb)
    frames = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in rgb]
    path = out_dir / ANIMATION_NAME
    tmp = out_dir / (ANIMATION_NAME + ".part")
    frames[0].save(
        tmp, format="GIF", save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0, optimize=False
    )  # optimize would cut each frame's palette to its own colours
    tmp.replace(path)
    return path, len(samples), time.perf_counter() - started


def _palette(frames: list) -> PILImage:
    """One 255-colour palette for every frame: quantised from a strip of frames spread over the run."""
    from PIL import Image

    picks = [frames[int(i)] for i in np.linspace(0, len(frames) - 1, min(PALETTE_SAMPLES, len(frames)))]
    w, h = picks[0].size
    strip = Image.new("RGB", (w, h * len(picks)))
    for k, im in enumerate(picks):
        strip.paste(im, (0, k * h))
    return strip.quantize(colors=255, dither=Image.Dither.NONE)


def write_frame(path: Path, spec: FormationSpec, arrays: dict[str, np.ndarray], t_frame: float, dpi: int = 100) -> Path:
    """The animation's frame at time ``t_frame`` [s] as a PNG (for documentation)."""
    figure = RunFigure(spec, arrays)
    try:
        figure.draw(min(int(np.searchsorted(arrays["t"], t_frame)), len(arrays["t"]) - 1))
        figure.fig.savefig(path, dpi=dpi)
    finally:
        figure.close()
    return path
