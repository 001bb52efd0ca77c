"""The velocity-error figure's data and the animation, from a short trajectory (no ROS; the headless
tests check that every figure is written)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from formation_msgs_py.spec import load_formation, simulator_view
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam
from formation_sim.views.animation import write_animation, write_frame
from formation_sim.views.figures import velocity_errors


@pytest.fixture(scope="module")
def short_run():
    """The paper's first 0.2 s at 1 kHz control, recorded every 20 steps (11 samples)."""
    spec = load_formation(Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml")
    sim = Simulation(simulator_view(spec), physics_rate=1000.0, control_rate=1000.0)
    team = AgentTeam(spec)
    rec = RunRecorder(spec, record_every=20)
    for _ in range(201):
        u, margin_v, _ = team.evaluate(sim.sense(), rec)
        s = sim.state
        rec.add(sim.t, s.p, s.R, s.v, u, margin_v)
        sim.advance(u)
    return spec, rec.arrays()


def test_velocity_errors_start_inside_their_auto_funnel(short_run) -> None:
    """ρ_v(0) = 2|e_v(0)| + 1 per channel (rho_0: auto), and every e_v stays inside ±ρ_v."""
    spec, arrays = short_run
    e_v, rho_v = velocity_errors(spec, arrays)
    np.testing.assert_allclose(rho_v[0], 2.0 * np.abs(e_v[0]) + 1.0, rtol=1e-12)
    assert np.all(np.abs(e_v) < rho_v)


def test_animation_frames(short_run, tmp_path: Path) -> None:
    """One GIF frame per 1/fps of simulated time; a single frame as PNG."""
    spec, arrays = short_run
    path, frames, _ = write_animation(tmp_path, spec, arrays, fps=20.0)
    assert frames == 5 and Image.open(path).n_frames == 5
    png = write_frame(tmp_path / "frame.png", spec, arrays, 0.1)
    assert Image.open(png).size == (1000, 560)


def test_animation_frames_share_one_palette(short_run, tmp_path: Path) -> None:
    """Every GIF frame maps its pixels through the same palette, so a colour means the same in each."""
    spec, arrays = short_run
    path, frames, _ = write_animation(tmp_path, spec, arrays, fps=20.0)
    with Image.open(path) as gif:
        flat = gif.getpalette()
        palette = {tuple(flat[i : i + 3]) for i in range(0, len(flat), 3)}
        for k in range(frames):
            gif.seek(k)
            colours = np.unique(np.asarray(gif.convert("RGB")).reshape(-1, 3), axis=0)
            assert {tuple(int(x) for x in c) for c in colours} <= palette, f"frame {k} has its own colours"


def test_edge_figures_are_two_columns_with_one_legend(short_run, tmp_path: Path) -> None:
    """errors.png: the 4 edges in 2 columns (each the run above its second half), one figure legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from formation_sim.views import figures

    spec, arrays = short_run
    seen = []
    real_save = figures._save
    figures_save = lambda fig, path: seen.append((fig, path.name)) or real_save(fig, path)  # noqa: E731
    try:
        figures._save = figures_save
        figures.plot_run(tmp_path, spec, arrays)
    finally:
        figures._save = real_save
    assert tuple(name for _, name in seen) == figures.FIGURES
    fig = dict((name, f) for f, name in seen)["errors.png"]
    assert len([ax for ax in fig.axes if ax.get_visible()]) == 2 * len(spec.edges)
    assert len(fig.legends) == 1 and len(fig.legends[0].get_texts()) == 3
    for ax in fig.axes:
        assert ax.get_legend() is None
    plt.close("all")


def test_every_runner_help_and_outputs_page_name_every_figure() -> None:
    """formation-headless and formation-analyze --help, docs/outputs.md and docs/bags.md name each figure."""
    from formation_bag.parsers import analyze_parser
    from formation_sim.cli.headless import build_parser
    from formation_sim.views.figures import FIGURES
    from formation_sim.views.foxglove_layout import LAYOUT_NAME

    repo = Path(__file__).resolve().parents[2]
    texts = {
        "formation-headless --help": build_parser().format_help(),
        "formation-analyze --help": analyze_parser().format_help(),
        "docs/outputs.md": (repo / "docs" / "outputs.md").read_text(encoding="utf-8"),
        "docs/bags.md": (repo / "docs" / "bags.md").read_text(encoding="utf-8"),
    }
    missing = [(where, name) for where, text in texts.items() for name in (*FIGURES, LAYOUT_NAME) if name not in text]
    assert not missing
