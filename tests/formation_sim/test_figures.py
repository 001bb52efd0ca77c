"""The velocity-error figure's data, the figures' captions (verdict and run length) and the animation,
from a short trajectory (no ROS; the headless tests check that every figure is written)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam
from formation_sim.views.animation import write_animation, write_frame
from formation_sim.views.figures import velocity_errors


@pytest.fixture(scope="module")
def short_recorder() -> RunRecorder:
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
    return rec


@pytest.fixture(scope="module")
def short_run(short_recorder: RunRecorder):
    """The formation and the trajectory of :func:`short_recorder`."""
    return short_recorder.spec, short_recorder.arrays()


def test_velocity_errors_start_inside_their_auto_funnel(short_run) -> None:
    """ρ_v(0) = 2|e_v(0)| + 1 per channel (rho_0: auto), and every e_v stays inside ±ρ_v."""
    spec, arrays = short_run
    e_v, rho_v = velocity_errors(spec, arrays)
    # the figure's e_v is v − v_des from the record; ρ_v(0) was formed from the controller's own e_v: a few
    # roundings of values of order 1 apart, far below 1e-12
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
    caption = figures.Caption("PASS: every funnel held — t = 0–0.2 s of 0.2 s", "green")
    try:
        figures._save = figures_save
        figures.plot_run(tmp_path, spec, arrays, caption)
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
    from formation_sim.cli.headless import build_parser
    from formation_sim.offline.parsers import analyze_parser
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


def test_every_figure_shows_the_verdict_and_the_run_length(short_recorder, tmp_path: Path, monkeypatch) -> None:
    """A run that stopped at 0.2 s of 5 s: each figure write_outputs writes (as every runner and
    formation-analyze do) is titled INCOMPLETE with its reason and "t = 0–0.2 s of 5 s", in the
    verdict's colour, clear of the legend and inside the figure, and its PNG says the same."""
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from formation_sim.views import figures
    from formation_sim.views.outputs import write_outputs

    summary = short_recorder.summary(wall_time=1.0, requested_duration=5.0)
    assert summary["verdict"] == "INCOMPLETE"
    seen = {}
    real_save = figures._save
    monkeypatch.setattr(figures, "_save", lambda fig, path: seen.setdefault(path.name, fig) and real_save(fig, path))
    write_outputs(tmp_path, short_recorder, summary)
    assert tuple(seen) == figures.FIGURES
    expected = "INCOMPLETE: duration not reached: t=0.2 s of 5 s — t = 0–0.2 s of 5 s"
    for name, fig in seen.items():
        title = next(t for t in fig.texts if t.get_text() == fig.get_suptitle())
        assert title.get_text().replace("\n", " ") == expected, name
        assert title.get_color() == figures.VERDICT_COLOURS["INCOMPLETE"], name
        assert Image.open(tmp_path / name).text["Description"] == expected, name
        renderer = FigureCanvasAgg(fig).get_renderer()  # the figure was closed after it was saved
        box, legend = title.get_window_extent(renderer), fig.legends[0].get_window_extent(renderer)
        assert 0 <= box.x0 and box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height, name
        assert box.y0 >= legend.y1, name  # the caption sits above the legend, not on it
    plt.close("all")


def test_the_caption_says_each_verdict_its_reason_and_the_time_covered() -> None:
    """PASS, FAIL (with its first violation and an early stop), INCOMPLETE with a long reason (shortened),
    and a run whose requested duration is unknown."""
    from formation_sim.views.outputs import CAPTION_REASON_CHARS, run_caption

    base = {"first_violation": None, "incomplete_reason": None, "duration": 5.0, "requested_duration": 5.0}
    assert run_caption({**base, "verdict": "PASS"}, 0.0) == "PASS: every funnel held — t = 0–5 s of 5 s"
    fv = {"t": 2.15925, "kind": "velocity", "agent": "1", "channel": "vx"}
    fail = {**base, "verdict": "FAIL", "first_violation": fv, "duration": 2.159}
    assert run_caption(fail, 0.0) == "FAIL: first violation at t=2.1593 s: velocity 1 (vx) — t = 0–2.159 s of 5 s"
    stopped = run_caption({**fail, "incomplete_reason": "interrupted"}, 0.0)
    assert stopped.startswith("FAIL: first violation at t=2.1593 s: velocity 1 (vx); then the run stopped early: ")
    # a realtime run that went on to its end after an agent died did not stop early
    went_on = run_caption({**fail, "duration": 5.0, "incomplete_reason": "agent_3 was killed by SIGKILL"}, 0.0)
    assert went_on == (
        "FAIL: first violation at t=2.1593 s: velocity 1 (vx); then agent_3 was killed by SIGKILL — t = 0–5 s of 5 s"
    )
    long = {**base, "verdict": "INCOMPLETE", "incomplete_reason": "data missing: " + "agent_3 wrench gap; " * 20}
    verdict, covered = run_caption({**long, "duration": 1.5}, 0.0).split(" — ")
    assert verdict.startswith("INCOMPLETE: data missing: agent_3") and verdict.endswith(" …")
    assert len(verdict) <= CAPTION_REASON_CHARS and covered == "t = 0–1.5 s of 5 s"
    unknown = {**base, "verdict": "PASS", "requested_duration": None, "duration": 3.25}
    assert run_caption(unknown, 0.5) == "PASS: every funnel held — t = 0.5–3.25 s (no requested duration)"


def test_the_figures_of_a_ros_run_show_the_launchers_verdict(short_recorder, tmp_path: Path, capsys) -> None:
    """The simulator captions its figures PASS; an agent that died in a realtime run makes the run
    INCOMPLETE (exit 3), and formation-launch draws the figures again with that verdict."""
    from formation_core.options import RunOptions
    from formation_sim.launch import launcher as launch
    from formation_sim.views.figures import FIGURES
    from formation_sim.views.outputs import write_outputs

    summary = short_recorder.summary(wall_time=1.0, requested_duration=0.2)
    write_outputs(tmp_path, short_recorder, {**summary, "last_answer_t": {"3": 0.1}})
    assert Image.open(tmp_path / "errors.png").text["Description"].startswith("PASS: every funnel held")
    env = {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    run = launch.Launcher(short_recorder.spec, RunOptions(command="launch", mode="realtime"), tmp_path, env)
    run.timing = {"start": 0.0, "stop_from": 1.0, "stopped": 2.0}
    (tmp_path / "logs").mkdir()  # where the processes' logs were
    run.agent_died.append(launch.Death("3", "agent_3 was killed by SIGKILL"))
    assert launch._finish(run, None) == 3
    for name in FIGURES:
        caption = Image.open(tmp_path / name).text["Description"]
        assert caption == (
            "INCOMPLETE: agent_3 was killed by SIGKILL after answering the step of t=0.1000 s; the realtime run "
            "went on with its … — t = 0–0.2 s of 0.2 s"
        ), name
