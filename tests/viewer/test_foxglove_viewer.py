"""Opt-in: short runs opened in a real viewer. Foxglove Studio 1.48 (the prebuilt web app of the npm
package @foxglove/studio-base) runs in headless Chromium and imports each run's layout through its own
Import button; the page and a screenshot are checked.

- A 0.5 s lockstep paper run's view.mcap, read over HTTP byte ranges from 127.0.0.1: the whole run on
  the timeline, the agents' markers drawn, no transform-tree message, both funnel plots with data
  across the run and legends naming each line.
- Two non-neighbours in contact over delayed and lossy links (data/contact_links_3agents.yaml), from
  its lockstep view.mcap and live from a realtime run's ``--foxglove`` server (through
  subprotocol_shim.py: Studio 1.x offers only the protocol's older name): every link's age plotted and
  named, the contact spheres drawn (and none in the paper run).

Install what it needs with tests/viewer/install.sh, then
``FORMATION_VIEWER_CHECK=1 .venv/bin/python -m pytest tests/viewer -q``. ``FORMATION_VIEWER_SCREENSHOTS=DIR``
also keeps the screenshots in DIR (docs/img holds three of them)."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bin_helpers import executable
from process_hygiene import stop_group
from studio_server import serving
from subprotocol_shim import renaming

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"
CONTACT_LINKS = Path(__file__).resolve().parent / "data" / "contact_links_3agents.yaml"
INSTALL = "tests/viewer/install.sh"
DURATION_S = 0.5
#: the simulator's display rate [Hz of simulated time] (its default marker_rate): the funnels' sample rate
DISPLAY_RATE = 30.0
CACHE = Path(os.environ.get("FORMATION_VIEWER_CACHE", Path.home() / ".cache" / "formation-viewer"))
MODULES = CACHE / "node_modules"
STUDIO = MODULES / "@foxglove" / "studio-base"
VIEWPORT = {"width": 1600, "height": 1000}
# Studio calls window.showOpenFilePicker (File System Access API), whose dialog headless Chromium
# neither shows nor hands to Playwright; this stand-in asks through an <input type=file> instead, whose
# file chooser Playwright answers. The app's own import code then reads the chosen file as usual.
FILE_PICKER_THROUGH_INPUT = """
window.showOpenFilePicker = (options) => new Promise((resolve) => {
  const input = document.createElement("input");
  input.type = "file";
  input.multiple = Boolean(options && options.multiple);
  input.accept = ".json,application/json";
  input.addEventListener("change", () => resolve(Array.from(input.files).map((file) => ({
    kind: "file", name: file.name, getFile: async () => file,
  }))));
  input.addEventListener("cancel", () => resolve([]));
  input.click();
});
"""
# Software WebGL: the 3D panel renders without a GPU.
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
TIMEOUT_MS = 180_000  # page loads and the first WebGL frames take tens of seconds on a busy machine


def chromium() -> str | None:
    """Debian's chromium binary (FORMATION_CHROMIUM overrides), or None."""
    return os.environ.get("FORMATION_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


def missing() -> str | None:
    """Why the check cannot run here (naming the install script), or None."""
    if os.environ.get("FORMATION_VIEWER_CHECK") != "1":
        return f"opt-in (a run, then Foxglove Studio in headless Chromium): {INSTALL}, then FORMATION_VIEWER_CHECK=1"
    if chromium() is None:
        return f"no chromium on PATH: {INSTALL} installs Debian's"
    if not (STUDIO / "assets" / "index.js").is_file() or not (MODULES / "react-dom" / "umd").is_dir():
        return f"@foxglove/studio-base 1.48 or react 17 not in {MODULES}: {INSTALL}"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return f"Playwright for Python not installed: {INSTALL}"
    return None


pytestmark = pytest.mark.skipif(missing() is not None, reason=str(missing()))


@dataclass
class Viewed:
    """What the viewer showed of the run."""

    layout: dict[str, Any]
    source_text: str  # the Data source sidebar: file, start and end time
    page_text: str  # the whole page after the layout was imported
    console: list[str] = field(default_factory=list)
    screenshot: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.uint8))  # (H, W, 3) RGB
    boxes: dict[str, tuple[int, int, int, int]] = field(default_factory=dict)  # panel id -> x0, y0, x1, y1 [px]


def _box(locator: Any) -> tuple[int, int, int, int]:
    """A locator's bounding box in screenshot pixels (x0, y0, x1, y1)."""
    box = locator.bounding_box()
    assert box is not None
    return (round(box["x"]), round(box["y"]), round(box["x"] + box["width"]), round(box["y"] + box["height"]))


def _keep(png: bytes, name: str) -> None:
    """Save a screenshot under FORMATION_VIEWER_SCREENSHOTS, 256 colours (small enough for docs/img)."""
    target = os.environ.get("FORMATION_VIEWER_SCREENSHOTS")
    if not target:
        return
    from PIL import Image

    Path(target).mkdir(parents=True, exist_ok=True)
    image = Image.open(io.BytesIO(png)).convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    image.save(Path(target) / name, optimize=True)


def _studio(
    mounts: dict[str, Path],
    query: str,
    layout_file: Path,
    panel_keys: tuple[str, ...],
    loaded: Callable[[Any], None],
    screenshot: str,
) -> Viewed:
    """Foxglove Studio opened on ``query`` (its deep link to a data source), ``loaded(page)`` waited for, the
    layout in ``layout_file`` imported through its Import button, then the page and a screenshot."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    layout = json.loads(layout_file.read_text())
    console: list[str] = []
    mounts = {"/react": MODULES / "react", "/react-dom": MODULES / "react-dom", "/studio": STUDIO, **mounts}
    with serving(mounts) as base, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium(), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.set_default_timeout(TIMEOUT_MS)
            page.on("console", lambda message: console.append(f"{message.type}: {message.text}"))
            page.on("pageerror", lambda error: console.append(f"pageerror: {error}"))
            page.add_init_script(FILE_PICKER_THROUGH_INPUT)
            page.goto(f"{base}/?{query.format(base=base)}")
            loaded(page)
            source_text = page.inner_text("body")
            # the Layouts tab of the left sidebar, then its Import button
            page.locator('[role=tab][data-sidebar-key="layouts"]').click()
            with page.expect_file_chooser() as chooser:
                page.get_by_label("Import layout").click()
            chooser.value.set_files(str(layout_file))
            page.get_by_text(layout["configById"]["Plot!distance"]["title"]).wait_for()
            page.locator('[role=tab][data-sidebar-key="layouts"]').click()  # close the sidebar: room for the panels
            dismiss = page.get_by_label("Dismiss")
            if dismiss.count():
                dismiss.first.click()  # the 3D panel's "Open settings" hint would cover the scene
            panels = {key: page.locator(f'[data-testid="panel-mouseenter-container {key}"]') for key in panel_keys}
            page.wait_for_timeout(15_000)  # plots load their blocks and the 3D scene draws its frames
            png = page.screenshot()
            _keep(png, screenshot)
            boxes = {key: _box(panel.locator("canvas").first) for key, panel in panels.items()}
            page_text = page.inner_text("body")
        finally:
            browser.close()
    return Viewed(
        layout=layout,
        source_text=source_text,
        page_text=page_text,
        console=console,
        screenshot=np.asarray(Image.open(io.BytesIO(png)).convert("RGB")),
        boxes=boxes,
    )


def _file_loaded(page: Any) -> None:
    """The Data source sidebar shows the file's end time."""
    page.get_by_text("END TIME").wait_for()
    page.get_by_text(re.compile(r"^\d+\.\d{9}$")).nth(1).wait_for()


def _launch(formation: Path, out: Path, ros_domain_id: int, *options: str) -> None:
    """formation-launch of ``formation`` into ``out``, which must end with exit 0."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_STATIC_PEERS", None)
    run = subprocess.run(
        [executable("formation-launch"), str(formation), *options, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=900,
        env=env,
        start_new_session=True,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]


FILE_QUERY = "ds=remote-file&ds.url={base}/run/view.mcap"  # Studio's deep link to a file behind a URL


@pytest.fixture(scope="module")
def viewed(tmp_path_factory: pytest.TempPathFactory, ros_domain_id: int) -> Viewed:
    """A 0.5 s lockstep paper run, opened in Foxglove Studio with its layout imported."""
    run = tmp_path_factory.mktemp("viewer_run") / "run"
    _launch(PAPER, run, ros_domain_id, "--duration", str(DURATION_S))
    keys = ("3D!formation", "Plot!distance", "Plot!orientation")
    return _studio(
        {"/run": run}, FILE_QUERY, run / "foxglove_layout.json", keys, _file_loaded, "foxglove_formation.png"
    )


LINK_KEYS = ("3D!formation", "Plot!links")


@pytest.fixture(scope="module")
def viewed_links(tmp_path_factory: pytest.TempPathFactory, ros_domain_id: int) -> Viewed:
    """A 2 s lockstep run of two non-neighbours in contact over delayed and lossy links, its view.mcap in
    Foxglove Studio with its layout imported."""
    run = tmp_path_factory.mktemp("viewer_links") / "run"
    _launch(CONTACT_LINKS, run, ros_domain_id)
    return _studio({"/run": run}, FILE_QUERY, run / "foxglove_layout.json", LINK_KEYS, _file_loaded, "links_view.png")


@pytest.fixture(scope="module")
def viewed_live(tmp_path_factory: pytest.TempPathFactory, ros_domain_id: int) -> Viewed:
    """The same formation in a realtime run with --foxglove, Studio connected to it live (through the
    subprotocol relay) with the formation's layout imported; the run stopped (by its PID) once seen."""
    from formation_core.spec import load_formation
    from formation_sim.views.foxglove_layout import write_layout

    tmp = tmp_path_factory.mktemp("viewer_live")
    layout_file = write_layout(tmp, load_formation(CONTACT_LINKS))
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_STATIC_PEERS", None)
    # long enough for Studio to load, connect and draw; stopped once the screenshot is taken
    cmd = [executable("formation-launch"), str(CONTACT_LINKS), "--mode", "realtime", "--duration", "600"]
    cmd += ["--no-record", "--no-plots", "--foxglove", "127.0.0.1:0", "--out", str(tmp / "run")]
    log = tmp / "launch.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    try:
        url = _live_url(log, proc)
        with renaming(url) as relay:

            def connected(page: Any) -> None:
                page.get_by_text(relay).first.wait_for()  # the data source sidebar names the connection

            return _studio(
                {}, f"ds=foxglove-websocket&ds.url={relay}", layout_file, LINK_KEYS, connected, "links_live.png"
            )
    finally:
        stop_group(proc)


def _live_url(log: Path, proc: subprocess.Popen) -> str:
    """The live view's address, as the run prints it (port 0: the server picked one)."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        found = re.search(r"live view on (ws://127\.0\.0\.1:\d+)", log.read_text(errors="replace"))
        if found:
            return found.group(1)
        assert proc.poll() is None, log.read_text(errors="replace")[-3000:]
        time.sleep(0.5)
    raise AssertionError("no live view address in 300 s: " + log.read_text(errors="replace")[-3000:])


def _crop(viewed: Viewed, key: str) -> np.ndarray:
    x0, y0, x1, y1 = viewed.boxes[key]
    return viewed.screenshot[y0:y1, x0:x1].astype(int)


def _near(image: np.ndarray, rgb: tuple[int, int, int], tolerance: int) -> np.ndarray:
    """(H, W) mask of pixels within ``tolerance`` of ``rgb`` in every channel."""
    return np.all(np.abs(image - np.array(rgb)) <= tolerance, axis=-1)


def _hex(colour: str) -> tuple[int, int, int]:
    return int(colour[1:3], 16), int(colour[3:5], 16), int(colour[5:7], 16)


def test_timeline_holds_the_whole_run(viewed: Viewed) -> None:
    """The Data source sidebar gives start 0 and an end within one display period of the duration."""
    times = re.search(r"START TIME\s+(\d+\.\d+)\s+END TIME\s+(\d+\.\d+)", viewed.source_text)
    assert times is not None, viewed.source_text[:500]
    start, end = float(times.group(1)), float(times.group(2))
    assert start == 0.0
    # the view file holds the display rate's samples: the last one lies within a display period of the end
    assert abs(end - DURATION_S) <= 1.0 / 30.0, (start, end)
    assert "view.mcap" in viewed.source_text


def test_markers_are_drawn_in_the_3d_panel(viewed: Viewed) -> None:
    """The 3D panel shows the bodies (grey-blue boxes) and their body axes (red and green lines)."""
    scene = _crop(viewed, "3D!formation")
    red_axes = int((_near(scene, (230, 26, 26), 60)).sum())
    green_axes = int((_near(scene, (26, 204, 26), 60)).sum())
    r, g, b = scene[..., 0], scene[..., 1], scene[..., 2]
    bodies = int(((b - r > 15) & (b - r < 70) & (np.abs(r - g) < 25) & (r > 70) & (r < 190)).sum())
    # a few hundred pixels each at this viewport; the floors are a tenth of what one frame shows
    assert red_axes >= 30 and green_axes >= 30 and bodies >= 300, (red_axes, green_axes, bodies)


def test_no_transform_tree_message(viewed: Viewed) -> None:
    """Nothing in the page or the console speaks of a transform tree cycle (relative poses are not TF)."""
    texts = [viewed.page_text, *viewed.console]
    assert not [t for t in texts if "cycle" in t.lower()], [t for t in texts if "cycle" in t.lower()]


@pytest.mark.parametrize("panel", ["Plot!distance", "Plot!orientation"])
def test_plots_have_data_across_the_run(viewed: Viewed, panel: str) -> None:
    """Each funnel plot draws its lines across the plot's width, with no hole, and names each line."""
    config = viewed.layout["configById"][panel]
    plot = _crop(viewed, panel)
    # every path's colour, bounds included: in a short plot the ψ lines lie under their bound and its dots
    colours = {path["color"] for path in config["paths"]}
    drawn = np.zeros(plot.shape[:2], bool)
    for colour in colours:
        drawn |= _near(plot, _hex(colour), 40)
    columns = np.flatnonzero(drawn.any(axis=0))
    width = plot.shape[1]
    assert columns.size, f"{panel}: no series pixel"
    span = (columns[-1] - columns[0]) / width
    largest_gap = int(np.diff(columns).max()) if columns.size > 1 else width
    # the x axis runs over the run: the lines cover most of the canvas (axis labels, legend and margins aside)
    assert span >= 0.75, (panel, span)
    # a hole is a display sample missing: a gap of two display periods; lines cross between samples
    period_px = (columns[-1] - columns[0]) / (DURATION_S * DISPLAY_RATE)
    assert largest_gap <= 1.5 * period_px, (panel, largest_gap, period_px)
    for path in config["paths"]:
        assert path["label"] in viewed.page_text, (panel, path["label"])


def _contact_pixels(viewed: Viewed) -> int:
    """Pixels of the 3D panel in the contact spheres' red (markers.CONTACT_COLOUR, half transparent over
    the scene or a body): red well above green and blue, darker than the axes' full red."""
    scene = _crop(viewed, "3D!formation")
    r, g, b = scene[..., 0], scene[..., 1], scene[..., 2]
    return int(((r - g > 60) & (r - b > 40) & (r < 215) & (r > 120)).sum())


@pytest.mark.parametrize("source", ["viewed_links", "viewed_live"])
def test_link_ages_are_plotted(request: pytest.FixtureRequest, source: str) -> None:
    """The plot of /formation/links draws the links' ages, from view.mcap over the whole run and live over
    what the viewer received, and names every link."""
    viewed: Viewed = request.getfixturevalue(source)
    config = viewed.layout["configById"]["Plot!links"]
    plot = _crop(viewed, "Plot!links")
    drawn = np.zeros(plot.shape[:2], bool)
    for colour in {path["color"] for path in config["paths"]}:
        drawn |= _near(plot, _hex(colour), 40)
    columns = np.flatnonzero(drawn.any(axis=0))
    assert columns.size, f"{source}: no link age drawn"
    span = (columns[-1] - columns[0]) / plot.shape[1]
    # a file: the whole run on the x axis (as the funnel plots); live: from the first message received,
    # which a slow page may receive late, on an axis from 0
    assert span >= (0.5 if source == "viewed_links" else 0.1), (source, span)
    for path in config["paths"]:
        assert path["label"] in viewed.page_text, (source, path["label"])


@pytest.mark.parametrize("source", ["viewed_links", "viewed_live"])
def test_a_contact_is_drawn(request: pytest.FixtureRequest, source: str, viewed: Viewed) -> None:
    """Agents 1 and 3 touch from the start to the end: the 3D panel shows their contact spheres (red, half
    transparent), from view.mcap and live; the paper run, whose bodies never touch, shows none."""
    shown, paper = _contact_pixels(request.getfixturevalue(source)), _contact_pixels(viewed)
    # two spheres of the bodies' radius: about 4000 pixels at this viewport and camera; without them a
    # few tens (the anti-aliased edges of the red body axes)
    assert shown >= 1000 and paper <= 300, (shown, paper)
