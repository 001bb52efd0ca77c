"""Monte Carlo campaigns of headless runs: ``formation-campaign CAMPAIGN.yaml --out DIR``.

A campaign file names a base formation, how many random samples to draw, the control rates to run
each at and what varies between samples (plant, disturbance and noise amplitudes, initial
attitudes). Its keys are declared once, in :data:`CAMPAIGN_KEYS`, which validates the file
(:func:`parse_campaign`) and renders the reference of docs/campaigns.md
(``formation-campaign --schema``).

Each run is the compiled headless runner (sampled control) with its own plant; the physics rate is
the file's, rounded to a multiple of the control rate. Runs go to a local process pool
(``--workers``, default the cores) or to a Dask distributed cluster (``--scheduler ADDRESS``; the
formation file must be readable at the same path on the workers). Every finished run is appended
to ``DIR/runs.jsonl`` at once, so an interrupted campaign resumes where it stopped. At the end
``DIR`` holds ``runs.csv`` (one row per sample and rate: verdict, first violation, worst margins,
peak wrench), ``summary.json`` (pass rate and its 95 % Wilson interval per control rate) and the
figures ``pass_rate.png`` and ``worst_margin.png``.

``formation-campaign --sweep-rate FILE RATE…`` runs the file's own plant at each rate and prints
the pass/fail table next to the rate each agent needs (:mod:`formation_sim.core.rates`).

Exit status (:mod:`formation_core.verdict`): 0 done, 2 invalid campaign or formation file (naming the
field), 4 an I/O or internal error (the runs finished are kept: a rerun resumes), 130 interrupted.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from formation_core.errors import FormationSpecError
from formation_core.loader import read_document
from formation_core.schema import REQUIRED
from formation_core.verdict import ExitCode, guarded

if TYPE_CHECKING:  # numpy, the loader of formations and the cores: imported where used, not for --help
    from formation_core.formation import FormationSpec, SignalModel

#: the conditions a campaign may cross with the control rate: a link model's values (``links``) and
#: gains (``gains``); each run's row names its own (empty where the campaign does not set one)
CONDITIONS = ("link_delay", "link_loss", "link_jitter", "sensor_rate", "delta", "gamma")
COLUMNS = (
    "sample",
    "control_rate",
    *CONDITIONS,
    "seed",
    "verdict",
    "violation_t",
    "violation_kind",
    "violation_where",
    "violation_channel",
    "worst_margin_e",
    "worst_margin_psi",
    "worst_margin_v",
    "peak_force",
    "peak_torque",
    "wall_time",
)


class CampaignError(ValueError):
    """An invalid campaign file: the message names the field and the value."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


@dataclass(frozen=True)
class Campaign:
    """A validated campaign file."""

    formation: Path
    samples: int
    seed: int
    control_rates: tuple[float, ...]
    duration: float | None
    vary: Mapping[str, Any]
    #: the link grid (``apply_to``, ``delay``, ``loss``, ``jitter``, ``sensor_rate``), empty: the file's links
    links: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    #: the gains grid (``delta``, ``gamma``: tuples, None: the file's)
    gains: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def conditions(self) -> list[tuple[Any, ...]]:
        """Every combination of the grids, in :data:`CONDITIONS` order (None: the file's value)."""
        links, gains = self.links, self.gains
        out = []
        for delay in links.get("delay") or (None,):
            for loss in links.get("loss") or (None,):
                for jitter in links.get("jitter") or (None,):
                    for rate in links.get("sensor_rate") or (None,):
                        for delta in gains.get("delta") or (None,):
                            for gamma in gains.get("gamma") or (None,):
                                out.append((delay, loss, jitter, rate, delta, gamma))
        return out


@dataclass(frozen=True)
class Task:
    """One headless run: sample ``sample`` of the campaign at ``control_rate`` under ``condition``."""

    formation: str
    sample: int
    control_rate: float
    duration: float | None
    vary: Mapping[str, Any]
    entropy: int
    spawn_key: tuple[int, ...]
    #: values of :data:`CONDITIONS` (None: the file's)
    condition: tuple[Any, ...] = (None,) * len(CONDITIONS)
    #: the channels the link values apply to
    apply_to: tuple[str, ...] = ()

    @property
    def key(self) -> tuple[Any, ...]:
        return (self.sample, self.control_rate, *self.condition)


def row_key(row: Mapping[str, Any]) -> tuple[Any, ...]:
    """The :attr:`Task.key` of a finished run's row."""
    return (row["sample"], row["control_rate"], *(row.get(c) for c in CONDITIONS))


# --- the campaign file ---------------------------------------------------------------------------


def _number(field: str, value: Any, *, positive: bool = False, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        kind = "an integer" if integer else "a number"
        raise CampaignError(field, f"expected {kind}, got {type(value).__name__} {value!r}")
    if not math.isfinite(value) or (positive and value <= 0):
        raise CampaignError(field, f"expected a {'positive ' if positive else ''}finite number, got {value!r}")
    return value


def _range(field: str, value: Any) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise CampaignError(field, f"expected [low, high], got {value!r}")
    lo, hi = (_number(f"{field}[{k}]", v) for k, v in enumerate(value))
    if not 0 <= lo <= hi:
        raise CampaignError(field, f"expected 0 <= low <= high, got [{lo!r}, {hi!r}]")
    return float(lo), float(hi)


def _file_name(field: str, value: Any, base: Path) -> Path:
    if not isinstance(value, str):
        raise CampaignError(field, f"expected a file name, got {value!r}")
    path = (base / value).resolve()
    if not path.is_file():
        raise CampaignError(field, f"no such file {str(path)!r}")
    return path


def _count(field: str, value: Any, base: Path) -> int:
    return int(_number(field, value, positive=True, integer=True))


def _seed(field: str, value: Any, base: Path) -> int:
    seed = int(_number(field, value, integer=True))
    if seed < 0:
        raise CampaignError(field, f"expected a non-negative integer, got {seed}")
    return seed


def _rates(field: str, value: Any, base: Path) -> tuple[float, ...]:
    if not isinstance(value, list) or not value:
        raise CampaignError(field, f"expected a non-empty list of rates [Hz], got {value!r}")
    return tuple(float(_number(f"{field}[{k}]", r, positive=True)) for k, r in enumerate(value))


def _duration(field: str, value: Any, base: Path) -> float:
    return float(_number(field, value, positive=True))


def _scale_range(field: str, value: Any, base: Path) -> tuple[float, float]:
    lo, hi = _range(field, value)
    if lo <= 0:
        raise CampaignError(field, f"expected a positive scale range, got {list(value)!r}")
    return lo, hi


def _amplitude_range(field: str, value: Any, base: Path) -> tuple[float, float]:
    return _range(field, value)


def _angle(field: str, value: Any, base: Path) -> float:
    angle = float(_number(field, value))
    if not 0 <= angle < math.pi:
        raise CampaignError(field, f"expected an angle in [0, pi) [rad], got {value!r}")
    return angle


def _grid(field: str, value: Any, *, low: float = 0.0, high: float = math.inf, none: bool = False) -> tuple:
    """A non-empty list of numbers in [low, high] (``none``: null allowed, the file's value)."""
    if not isinstance(value, list) or not value:
        raise CampaignError(field, f"expected a non-empty list, got {value!r}")
    out: list[float | None] = []
    for k, x in enumerate(value):
        if x is None and none:
            out.append(None)
            continue
        x = float(_number(f"{field}[{k}]", x))
        if not low <= x <= high:
            raise CampaignError(f"{field}[{k}]", f"expected a value in [{low:g}, {high:g}], got {x!r}")
        out.append(x)
    return tuple(out)


def _seconds_grid(field: str, value: Any, base: Path) -> tuple:
    return _grid(field, value)


def _probability_grid(field: str, value: Any, base: Path) -> tuple:
    return _grid(field, value, high=1.0)


def _rate_grid(field: str, value: Any, base: Path) -> tuple:
    out = _grid(field, value, none=True)
    for k, x in enumerate(out):
        if x is not None and x <= 0:
            raise CampaignError(f"{field}[{k}]", f"expected a rate > 0 [Hz] or null, got {x!r}")
    return out


def _gain_grid(field: str, value: Any, base: Path) -> tuple:
    out = _grid(field, value)
    for k, x in enumerate(out):
        if x <= 0:
            raise CampaignError(f"{field}[{k}]", f"expected a gain > 0, got {x!r}")
    return out


LINK_CHANNELS = ("poses", "velocity", "wrench")


def _channels(field: str, value: Any, base: Path) -> tuple[str, ...]:
    if not isinstance(value, list) or not value or any(v not in LINK_CHANNELS for v in value):
        raise CampaignError(field, f"expected a non-empty list of {', '.join(LINK_CHANNELS)}, got {value!r}")
    return tuple(dict.fromkeys(value))


@dataclass(frozen=True)
class Key:
    """One key of a campaign file: how it is checked (``parse``) and what its reference says."""

    name: str
    type: str
    #: the value a missing (or null) key takes, or :data:`REQUIRED`
    default: Any
    unit: str
    doc: str
    #: (field path, value, the campaign file's directory) -> the checked value; raises CampaignError
    parse: Callable[[str, Any, Path], Any] | None = None
    #: the keys of a mapping
    children: tuple[Key, ...] = ()


def _vary_range(name: str, what: str, parse: Callable[[str, Any, Path], Any], kind: str) -> Key:
    return Key(name, kind, None, "", f"per agent: {what}; `null`: not varied", parse)


_AMPLITUDE = "[low, high], 0 ≤ low ≤ high"
#: Every key of a campaign file: :func:`parse_campaign` validates with it, :func:`reference_markdown`
#: renders it as the table of docs/campaigns.md (``formation-campaign --schema``).
CAMPAIGN_KEYS: tuple[Key, ...] = (
    Key(
        "formation",
        "file name",
        REQUIRED,
        "",
        "the base formation file ([formation_file.md](formation_file.md)), relative to the campaign file; "
        "its plant, initial state, gains, funnels and simulation settings are every sample's start",
        _file_name,
    ),
    Key(
        "samples",
        "integer > 0",
        REQUIRED,
        "",
        "N: random plants (and initial attitudes), each run at every rate",
        _count,
    ),
    Key(
        "seed",
        "integer ≥ 0",
        REQUIRED,
        "",
        "sample i draws from numpy's `SeedSequence(seed).spawn(N)[i]`: the same plant at every rate, "
        "however the runs are spread",
        _seed,
    ),
    Key(
        "control_rates",
        "non-empty list of numbers > 0",
        REQUIRED,
        "Hz",
        "every sample runs at every rate (paired); the physics rate is the file's, rounded to a multiple of it",
        _rates,
    ),
    Key(
        "duration",
        "number > 0",
        None,
        "s",
        "simulated time of each run; `null`: the file's `simulation.duration`",
        _duration,
    ),
    Key(
        "vary",
        "mapping",
        {},
        "",
        "what differs between samples, each drawn uniformly and independently per agent; a key left out keeps "
        "the file's value",
        children=(
            _vary_range("mass", "m ← m·U(low, high)", _scale_range, "[low, high], 0 < low ≤ high"),
            _vary_range(
                "inertia", "J ← J·U(low, high) (the whole matrix)", _scale_range, "[low, high], 0 < low ≤ high"
            ),
            _vary_range(
                "disturbance_amplitude",
                "amplitude A ← U(low, high) of a `paper` disturbance (other models unchanged)",
                _amplitude_range,
                _AMPLITUDE,
            ),
            _vary_range(
                "noise_amplitude",
                "amplitude A ← U(low, high) of a `paper` velocity noise (other models unchanged)",
                _amplitude_range,
                _AMPLITUDE,
            ),
            Key(
                "initial_rotation",
                "number in [0, π)",
                None,
                "rad",
                "per agent: R(0) ← R(0)·exp(S(θ)), the rotation vector θ uniform in the ball of this radius; "
                "`null`: not varied",
                _angle,
            ),
        ),
    ),
    Key(
        "links",
        "mapping",
        {},
        "",
        "a grid of link models ([links.md](links.md)) crossed with the control rates: every sample runs under "
        "every combination of the lists below, each value set on every agent's links of `apply_to` (an "
        "edge's own link of those channels is dropped); left out: the formation file's links",
        children=(
            Key(
                "apply_to",
                "non-empty list of poses, velocity, wrench",
                ["poses"],
                "",
                "the channels the values set (`sensor_rate` and `jitter` do not apply to `wrench`)",
                _channels,
            ),
            Key("delay", "non-empty list of numbers ≥ 0", [0.0], "s", "the links' constant latency", _seconds_grid),
            Key(
                "loss",
                "non-empty list of numbers in [0, 1]",
                [0.0],
                "",
                "each sample lost independently with this probability",
                _probability_grid,
            ),
            Key(
                "jitter",
                "non-empty list of numbers ≥ 0",
                [0.0],
                "s",
                "extra delay of each sample, uniform on [0, jitter]",
                _seconds_grid,
            ),
            Key(
                "sensor_rate",
                "non-empty list of numbers > 0 or null",
                [None],
                "Hz",
                "sensor rate (sample and hold); null: every control step; at most every control rate",
                _rate_grid,
            ),
        ),
    ),
    Key(
        "gains",
        "mapping",
        {},
        "",
        "gains crossed with the rest: every agent's δ and γ set to each value; left out: the file's",
        children=(
            Key("delta", "non-empty list of numbers > 0", None, "", "δ of every agent", _gain_grid),
            Key("gamma", "non-empty list of numbers > 0", None, "", "γ of every agent", _gain_grid),
        ),
    ),
)


def _parse_keys(node: Any, keys: tuple[Key, ...], prefix: str, base: Path) -> dict[str, Any]:
    names = [k.name for k in keys]
    for key in node:
        if key not in names:
            raise CampaignError(f"{prefix}{key}", f"unknown key (expected one of {', '.join(names)})")
    out: dict[str, Any] = {}
    for k in keys:
        field = prefix + k.name
        value = node.get(k.name)
        if k.default is REQUIRED and k.name not in node:
            raise CampaignError(field, "missing")
        if value is None and k.default is not REQUIRED:
            out[k.name] = k.default
        elif k.children:
            if not isinstance(value, Mapping):
                raise CampaignError(field, f"expected a mapping, got {value!r}")
            out[k.name] = _parse_keys(value, k.children, f"{field}.", base)
        else:
            assert k.parse is not None  # a key without children declares its parser
            out[k.name] = k.parse(field, value, base)
    return out


def parse_campaign(document: Any, base: Path) -> Campaign:
    """Validate a parsed campaign document against :data:`CAMPAIGN_KEYS`; ``base`` is the directory
    relative paths start from."""
    if not isinstance(document, Mapping):
        raise CampaignError("<top>", f"a campaign file is a mapping, got {type(document).__name__}")
    given_links = "links" in document and document["links"] is not None
    parsed = _parse_keys(document, CAMPAIGN_KEYS, "", base)
    parsed["vary"] = {k: v for k, v in parsed["vary"].items() if v is not None}  # only what varies
    links = parsed["links"]
    if given_links:
        links = {k: tuple(v) if isinstance(v, list) else v for k, v in links.items()}
        for k, rate in enumerate(links["sensor_rate"]):
            if rate is not None and rate > min(parsed["control_rates"]):
                raise CampaignError(
                    f"links.sensor_rate[{k}]",
                    f"{rate:g} Hz is faster than the control rate {min(parsed['control_rates']):g} Hz",
                )
    parsed["links"] = links if given_links else {}
    parsed["gains"] = {k: v for k, v in parsed["gains"].items() if v is not None}
    return Campaign(**parsed)


def reference_markdown() -> str:
    """The reference table of every key of a campaign file, in Markdown (docs/campaigns.md)."""

    def rows(keys: tuple[Key, ...], prefix: str) -> list[str]:
        out = []
        for k in keys:
            default = "required" if k.default is REQUIRED else f"`{json.dumps(k.default)}`"
            out.append(f"| `{prefix}{k.name}` | {k.type} | {default} | {k.unit} | {k.doc} |")
            out.extend(rows(k.children, f"{prefix}{k.name}."))
        return out

    header = ["| key | type | default | unit | meaning |", "|---|---|---|---|---|"]
    return "\n".join(header + rows(CAMPAIGN_KEYS, "")) + "\n"


def load_campaign(path: Path) -> Campaign:
    """Read and validate a campaign file with the formation files' reader (duplicate keys, size and
    alias budgets); errors name the field and its FILE:LINE:COL."""
    from formation_core.spec import load_formation

    try:
        document = read_document(path)
    except FormationSpecError as exc:
        raise CampaignError("campaign file", str(exc).replace("formation file", "campaign file")) from None
    try:
        campaign = parse_campaign(document.data, path.parent)
    except CampaignError as exc:
        raise CampaignError(exc.field, f"{exc.args[0].split(': ', 1)[1]} ({document.location(exc.field)})") from None
    load_formation(campaign.formation)  # a bad base formation is an error before anything runs
    return campaign


def tasks(campaign: Campaign) -> list[Task]:
    """Every run, sample-major; sample i's plant is drawn from the i-th child seed, the same at every rate."""
    import numpy as np

    root = np.random.SeedSequence(campaign.seed)
    entropy = root.entropy
    assert isinstance(entropy, int)  # the campaign's seed
    out = []
    apply_to = tuple(campaign.links.get("apply_to", ()))
    for child in root.spawn(campaign.samples):
        i = child.spawn_key[-1]
        for condition in campaign.conditions():
            for rate in campaign.control_rates:
                out.append(
                    Task(
                        str(campaign.formation),
                        i,
                        rate,
                        campaign.duration,
                        campaign.vary,
                        entropy,
                        tuple(child.spawn_key),
                        condition,
                        apply_to,
                    )
                )
    return out


# --- one sample --------------------------------------------------------------------------------


def _scaled_amplitude(model: SignalModel, value: float) -> SignalModel:
    from formation_core.formation import SignalModel

    if model.model != "paper":
        return model
    return SignalModel(model.model, {**model.params, "amplitude": value})


def sample_spec(task: Task) -> FormationSpec:
    """The base formation with sample ``task.sample``'s plant, initial orientations and control rate."""
    import numpy as np

    from formation_core.so3 import exp_so3
    from formation_core.spec import load_formation

    spec = load_formation(task.formation)
    rng = np.random.default_rng(np.random.SeedSequence(task.entropy, spawn_key=task.spawn_key))
    vary = task.vary
    agents = []
    for a in spec.agents:
        d = a.dynamics
        mass = d.mass * rng.uniform(*vary["mass"]) if "mass" in vary else d.mass
        inertia = d.inertia * rng.uniform(*vary["inertia"]) if "inertia" in vary else d.inertia
        dist, noise = d.disturbance, d.velocity_noise
        if "disturbance_amplitude" in vary:
            dist = _scaled_amplitude(dist, rng.uniform(*vary["disturbance_amplitude"]))
        if "noise_amplitude" in vary:
            noise = _scaled_amplitude(noise, rng.uniform(*vary["noise_amplitude"]))
        R = a.R_world_body
        if "initial_rotation" in vary:
            axis = rng.normal(size=3)
            angle = vary["initial_rotation"] * rng.uniform() ** (1 / 3)  # uniform in the ball
            R = R @ exp_so3(axis / np.linalg.norm(axis) * angle)
        dyn = dataclasses.replace(d, mass=mass, inertia=inertia, disturbance=dist, velocity_noise=noise)
        agents.append(dataclasses.replace(a, dynamics=dyn, R_world_body=R))
    spec = dataclasses.replace(spec, agents=tuple(agents))
    spec = _with_condition(spec, task.condition, task.apply_to)
    physics = task.control_rate * max(1, round(spec.simulation.physics_rate / task.control_rate))
    changes: dict[str, Any] = {"control_rate": task.control_rate, "physics_rate": physics}
    changes["record_rate"] = min(spec.simulation.record_rate, task.control_rate)
    if task.duration is not None:
        changes["duration"] = task.duration
    if task.apply_to:  # a link grid: each sample its own losses and jitter (and noise), the same at every condition
        changes["seed"] = spec.simulation.seed + task.sample
    return spec.with_simulation(**changes)


def _with_condition(spec: FormationSpec, condition: tuple[Any, ...], apply_to: tuple[str, ...]) -> FormationSpec:
    """``spec`` with a run's link values on every agent's links of ``apply_to`` and its gains."""
    from formation_core.formation import EdgeLinks, MeasurementLink, SignalModel, WrenchLink

    delay, loss, jitter, sensor_rate, delta, gamma = condition
    agents = []
    for a in spec.agents:
        c = a.controller
        controller = dataclasses.replace(
            c, delta=c.delta if delta is None else delta, gamma=c.gamma if gamma is None else gamma
        )
        links = a.links
        if delay is not None:
            loss_model = SignalModel("independent", {"probability": loss}) if loss else SignalModel("none", {})
            spread = SignalModel("uniform", {"max": jitter}) if jitter else SignalModel("none", {})
            measured = MeasurementLink(sensor_rate, delay, spread, loss_model)
            links = dataclasses.replace(
                links,
                poses=measured if "poses" in apply_to else links.poses,
                velocity=measured if "velocity" in apply_to else links.velocity,
                wrench=WrenchLink(delay, loss_model) if "wrench" in apply_to else links.wrench,
            )
        agents.append(dataclasses.replace(a, controller=controller, links=links))
    edges = spec.edges
    if delay is not None and "poses" in apply_to:
        edges = tuple(dataclasses.replace(e, links=EdgeLinks(None, None)) for e in spec.edges)
    return dataclasses.replace(spec, agents=tuple(agents), edges=edges)


def run_task(task: Task) -> dict[str, Any]:
    """One sample's headless run, as a row of ``runs.csv``."""
    from formation_sim.cli.headless import run_headless

    spec = sample_spec(task)
    summary = run_headless(spec, stop_on_violation=True).summary
    fv = summary["first_violation"] or {}
    edges, agents = summary["edges"].values(), summary["agents"].values()

    def worst(values: Iterable[float | None]) -> float | None:
        vals = [v for v in values if v is not None]
        return min(vals) if vals else None

    return {
        "sample": task.sample,
        "control_rate": task.control_rate,
        **dict(zip(CONDITIONS, task.condition)),
        "seed": f"{task.entropy}:{'/'.join(map(str, task.spawn_key))}",
        "verdict": summary["verdict"],  # PASS, FAIL or INCOMPLETE
        "violation_t": fv.get("t"),
        "violation_kind": fv.get("kind"),
        "violation_where": fv.get("edge") or fv.get("agent"),
        "violation_channel": fv.get("channel"),
        "worst_margin_e": worst(e["min_margin_e"] for e in edges),
        "worst_margin_psi": worst(e["min_margin_psi"] for e in edges),
        "worst_margin_v": worst(a["min_margin_v"] for a in agents),
        "peak_force": max(a["peak_force"] for a in agents),
        "peak_torque": max(a["peak_torque"] for a in agents),
        "wall_time": summary["wall_time"],
    }


# --- running many ------------------------------------------------------------------------------


def _finished(log: Path) -> dict[tuple[Any, ...], dict[str, Any]]:
    """Rows of an earlier (interrupted) campaign in ``log``; a torn last line is ignored."""
    rows = {}
    if log.exists():
        for line in log.read_text(encoding="utf-8").splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            rows[row_key(row)] = row
    return rows


def _progress(done: int, total: int, started: float) -> None:
    elapsed = time.perf_counter() - started
    eta = elapsed / done * (total - done) if done else float("nan")
    print(f"\r  {done}/{total} runs  {elapsed:6.1f} s elapsed  ETA {eta:6.1f} s", end="", flush=True)


def run_tasks(todo: list[Task], log: Path, *, workers: int, scheduler: str | None, quiet: bool = False) -> None:
    """Run ``todo`` and append each row to ``log`` as it finishes."""
    started = time.perf_counter()
    torn = log.exists() and log.stat().st_size > 0 and not log.read_bytes().endswith(b"\n")
    with log.open("a", encoding="utf-8") as out:
        if torn:  # a killed writer left half a line: end it, so that it stays one ignored line
            out.write("\n")

        def record(row: dict[str, Any], done: int) -> None:
            out.write(json.dumps(row) + "\n")
            out.flush()
            os.fsync(out.fileno())
            if not quiet:
                _progress(done, len(todo), started)

        if scheduler is not None:
            from distributed import Client
            from distributed import as_completed as dask_completed

            with Client(scheduler) as client:
                futures = client.map(run_task, todo, pure=False)
                for done, fut in enumerate(dask_completed(futures), 1):
                    record(fut.result(), done)
        elif workers == 1:
            for done, task in enumerate(todo, 1):
                record(run_task(task), done)
        else:
            pool = ProcessPoolExecutor(max_workers=workers)
            try:
                futures = [pool.submit(run_task, t) for t in todo]
                for done, fut in enumerate(as_completed(futures), 1):
                    record(fut.result(), done)
            finally:  # interrupted: the runs not started are dropped, not waited for
                pool.shutdown(wait=True, cancel_futures=True)
    if not quiet and todo:
        print()


def wilson(passes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval (low, high) of the pass rate ``passes / n``; low <= rate <= high
    (a 100 % rate has high == 1.0, a 0 % rate low == 0.0); no runs: (0, 1)."""
    if n == 0:
        return 0.0, 1.0
    p = passes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    # the interval contains p exactly; rounding leaves the upper bound of a 100 % rate (the lower of
    # a 0 % rate) a unit in the last place inside it, so p itself bounds it
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def summarise(rows: list[dict[str, Any]], campaign: Campaign) -> dict[str, Any]:
    """Pass rate and its 95 % interval, worst margins, per control rate."""
    per_rate = {}
    for rate in campaign.control_rates:
        sel = [r for r in rows if r["control_rate"] == rate]
        passes = sum(r["verdict"] == "PASS" for r in sel)
        lo, hi = wilson(passes, len(sel))
        per_rate[f"{rate:g}"] = {
            "runs": len(sel),
            "passes": passes,
            "pass_rate": passes / len(sel) if sel else None,
            "pass_rate_ci95": [lo, hi],
            "first_violation_kinds": {
                k: sum(r["violation_kind"] == k for r in sel)
                for k in sorted({r["violation_kind"] or "" for r in sel})
                if k
            },
        }
    out: dict[str, Any] = {
        "formation": str(campaign.formation),
        "samples": campaign.samples,
        "seed": campaign.seed,
        "vary": {k: list(v) if isinstance(v, tuple) else v for k, v in campaign.vary.items()},
        "duration": campaign.duration,
        "per_control_rate": per_rate,
    }
    if campaign.links or campaign.gains:
        out["links"] = {k: list(v) if isinstance(v, tuple) else v for k, v in campaign.links.items()}
        out["gains"] = {k: list(v) for k, v in campaign.gains.items()}
        out["per_condition"] = per_condition(rows, campaign)
        out["tolerance"] = tolerance(out["per_condition"])
    return out


#: a pass rate at least this is what ``tolerance`` calls holding
HOLDS = 0.95


def _largest(group: list[dict[str, Any]], axis: str, fixed: str) -> float | None:
    """The largest value of ``axis`` up to which every cell passes :data:`HOLDS` (``fixed`` at its least)."""
    least = min((c[fixed] for c in group if c[fixed] is not None), default=None)
    line = sorted((c for c in group if c[fixed] == least), key=lambda c: c[axis] or 0.0)
    best = None
    for c in line:
        if (c["pass_rate"] or 0.0) < HOLDS:
            break
        best = c[axis]
    return best


def per_condition(rows: list[dict[str, Any]], campaign: Campaign) -> list[dict[str, Any]]:
    """Pass rate and its 95 % interval of every condition of the grids at every control rate."""
    out = []
    for condition in campaign.conditions():
        for rate in campaign.control_rates:
            sel = [r for r in rows if r["control_rate"] == rate and tuple(r.get(c) for c in CONDITIONS) == condition]
            passes = sum(r["verdict"] == "PASS" for r in sel)
            lo, hi = wilson(passes, len(sel))
            out.append(
                {
                    "control_rate": rate,
                    **dict(zip(CONDITIONS, condition)),
                    "runs": len(sel),
                    "passes": passes,
                    "pass_rate": passes / len(sel) if sel else None,
                    "pass_rate_ci95": [lo, hi],
                }
            )
    return out


def tolerance(cells: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per group of conditions that differ only in delay and loss: the largest delay at which at least
    :data:`HOLDS` of the runs pass at every delay up to it (at the grid's smallest loss), and the
    largest loss likewise (at the smallest delay); None where even the smallest fails."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for c in cells:
        key = (c["control_rate"], c["link_jitter"], c["sensor_rate"], c["delta"], c["gamma"])
        groups.setdefault(key, []).append(c)
    out = []
    for (rate, jitter, sensor, delta, gamma), group in groups.items():
        out.append(
            {
                "control_rate": rate,
                "link_jitter": jitter,
                "sensor_rate": sensor,
                "delta": delta,
                "gamma": gamma,
                "largest_delay": _largest(group, "link_delay", "link_loss"),
                "largest_loss": _largest(group, "link_loss", "link_delay"),
            }
        )
    return out


def write_results(out: Path, rows: list[dict[str, Any]], campaign: Campaign) -> dict[str, Any]:
    """runs.csv, summary.json and the figures, each written atomically."""
    rows = sorted(rows, key=lambda r: tuple(-1.0 if v is None else v for v in row_key(r)))
    tmp = out / "runs.csv.tmp"
    with tmp.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(out / "runs.csv")
    summary = summarise(rows, campaign)
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    tmp.replace(out / "summary.json")
    plot_campaign(out, rows, summary)
    if "per_condition" in summary:
        plot_links(out, summary)
    return summary


def plot_campaign(out: Path, rows: list[dict[str, Any]], summary: dict[str, Any]) -> None:
    """pass_rate.png (pass rate vs control rate, 95 % intervals) and worst_margin.png (histograms)."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per = summary["per_control_rate"]
    rates = [float(r) for r in per]
    rate_vals = np.array([per[r]["pass_rate"] or 0.0 for r in per])
    ci = np.array([per[r]["pass_rate_ci95"] for r in per])
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ax.errorbar(rates, rate_vals, yerr=[rate_vals - ci[:, 0], ci[:, 1] - rate_vals], fmt="o-", capsize=4)
    ax.set_xscale("log")
    ax.set_xlabel("control rate [Hz]")
    ax.set_ylabel("pass rate (95 % CI)")
    ax.set_ylim(-0.05, 1.05)
    ax.grid(alpha=0.3)
    runs = max(per[r]["runs"] for r in per)
    ax.set_title(f"{Path(summary['formation']).name}: {runs} random plants per rate")
    fig.tight_layout()
    tmp = out / "pass_rate.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "pass_rate.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for r in rates:
        margins = (
            [m for m in (row["worst_margin_e"], row["worst_margin_psi"], row["worst_margin_v"]) if m is not None]
            for row in rows
            if row["control_rate"] == r
        )
        worst = [min(m) for m in margins if m]  # a run stopped before its first check has no margin
        ax.hist(worst, bins=30, alpha=0.5, label=f"{r:g} Hz")
    ax.axvline(0.0, color="r", lw=1)
    ax.set_xlabel("worst margin over the run (< 0: a funnel was left)")
    ax.set_ylabel("runs")
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = out / "worst_margin.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "worst_margin.png")
    plt.close(fig)


def plot_links(out: Path, summary: dict[str, Any]) -> None:
    """link_pass_rate.png: per group of the other conditions (at most 6), the pass rate of every delay and
    loss of the grid, a cell per pair (the number in it), coloured from red (0) to green (1)."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = summary["per_condition"]
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for c in cells:
        groups.setdefault((c["control_rate"], c["link_jitter"], c["sensor_rate"], c["delta"], c["gamma"]), []).append(c)
    shown = list(groups.items())[:6]
    cols = min(3, len(shown))
    rows_n = math.ceil(len(shown) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.6 * cols, 3.6 * rows_n), squeeze=False)
    for ax, ((rate, jitter, sensor, delta, gamma), group) in zip(axes.flat, shown):
        delays = sorted({c["link_delay"] or 0.0 for c in group})
        losses = sorted({c["link_loss"] or 0.0 for c in group})
        grid = np.full((len(losses), len(delays)), np.nan)
        for c in group:
            grid[losses.index(c["link_loss"] or 0.0), delays.index(c["link_delay"] or 0.0)] = c["pass_rate"]
        ax.imshow(grid, origin="lower", cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
        for (y, x), value in np.ndenumerate(grid):
            ax.text(x, y, "-" if np.isnan(value) else f"{value:.2f}", ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(delays)), [f"{d * 1e3:g}" for d in delays], fontsize=7)
        ax.set_yticks(range(len(losses)), [f"{p * 100:g}" for p in losses], fontsize=7)
        ax.set_xlabel("delay [ms]")
        ax.set_ylabel("loss [%]")
        extra = [f"{rate:g} Hz"]
        extra += [f"jitter {jitter * 1e3:g} ms"] if jitter else []
        extra += [f"sensor {sensor:g} Hz"] if sensor else []
        extra += [f"δ {delta:g}"] if delta else []
        extra += [f"γ {gamma:g}"] if gamma else []
        ax.set_title(", ".join(extra), fontsize=9)
    for ax in list(axes.flat)[len(shown) :]:
        ax.axis("off")
    fig.suptitle(f"{Path(summary['formation']).name}: pass rate per delay and loss", fontsize=10)
    fig.tight_layout()
    tmp = out / "link_pass_rate.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(out / "link_pass_rate.png")
    plt.close(fig)


def run_campaign(
    campaign: Campaign, out: Path, *, workers: int = 1, scheduler: str | None = None, quiet: bool = False
) -> dict[str, Any]:
    """Run what ``out/runs.jsonl`` does not hold yet, then write the results."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "runs.jsonl"
    finished = _finished(log)
    todo = [t for t in tasks(campaign) if t.key not in finished]
    if not quiet:
        print(f"formation-campaign: {len(todo)} runs to do, {len(finished)} already done", flush=True)
    run_tasks(todo, log, workers=workers, scheduler=scheduler, quiet=quiet)
    wanted = {t.key for t in tasks(campaign)}
    rows = [r for k, r in _finished(log).items() if k in wanted]
    return write_results(out, rows, campaign)


def condition_table(summary: dict[str, Any]) -> str:
    """The pass rates of a grid campaign as text, one line per condition, then the tolerances."""

    def fmt(value: Any, scale: float = 1.0, unit: str = "") -> str:
        return "file" if value is None else f"{value * scale:g}{unit}"

    def sensor(value: float | None) -> str:
        if value is None:  # a grid's null: every control step; no grid: the file's
            return "each step" if summary.get("links") else "file"
        return f"{value:g} Hz"

    lines = ["  rate [Hz]  delay     loss   jitter    sensor   delta  gamma   pass    95 % interval"]
    for c in summary["per_condition"]:
        lo, hi = c["pass_rate_ci95"]
        lines.append(
            f"  {c['control_rate']:>9g}  {fmt(c['link_delay'], 1e3, ' ms'):>8}  {fmt(c['link_loss'], 100, ' %'):>6}  "
            f"{fmt(c['link_jitter'], 1e3, ' ms'):>7}  {sensor(c['sensor_rate']):>8}  {fmt(c['delta']):>5}  "
            f"{fmt(c['gamma']):>5}  {c['passes']:>3}/{c['runs']:<3}  {lo:.2f}-{hi:.2f}"
        )
    for t in summary["tolerance"]:
        delay = "none" if t["largest_delay"] is None else f"{t['largest_delay'] * 1e3:g} ms"
        loss = "none" if t["largest_loss"] is None else f"{t['largest_loss'] * 100:g} %"
        lines.append(
            f"  holds (≥ {HOLDS:.0%} pass) at {t['control_rate']:g} Hz, jitter {fmt(t['link_jitter'], 1e3, ' ms')}, "
            f"sensor {sensor(t['sensor_rate'])}: largest delay {delay}, largest loss {loss}"
        )
    return "\n".join(lines)


# --- command line ------------------------------------------------------------------------------


def sweep_rate(formation: Path, rates: list[float], out: Path, *, workers: int, scheduler: str | None) -> int:
    """The file's own plant at each rate, with the rate each agent needs."""
    from formation_core.spec import load_formation

    spec = load_formation(formation)
    from formation_sim.core.loop import initial_rho_v0  # numba: once the file is valid
    from formation_sim.core.rates import rate_needs

    campaign = Campaign(formation.resolve(), 1, 0, tuple(rates), None, {})
    summary = run_campaign(campaign, out, workers=workers, scheduler=scheduler, quiet=True)
    rows = {r["control_rate"]: r for r in _finished(out / "runs.jsonl").values()}
    print(f"formation-campaign: rate sweep of {spec.name}, {spec.simulation.duration:g} s")
    print("  control rate [Hz]   verdict   first violation")
    for rate in rates:
        r = rows[rate]
        where = (
            "" if r["verdict"] == "PASS" else f"t={r['violation_t']:.3f} s {r['violation_kind']} {r['violation_where']}"
        )
        print(f"  {rate:>17g}   {r['verdict']:<7}   {where}")
    needs = rate_needs(spec, initial_rho_v0(spec))
    print("  needed (formation-check): " + ", ".join(f"agent {n.agent_id} {n.at_end:.0f} Hz" for n in needs))
    print(f"outputs in {out}/")
    return 0 if summary else 4


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="formation-campaign",
        description="Monte Carlo campaign of headless runs (the campaign file: docs/campaigns.md, --schema), "
        "or a rate sweep. "
        "Exit status: 0 done, 2 invalid input, 4 I/O or internal error (a rerun resumes), 130 interrupted.",
    )
    p.add_argument("campaign", type=Path, nargs="?", help="campaign file (YAML)")
    p.add_argument("--out", type=Path, help="output directory (default out/<campaign>-campaign); resumes if it exists")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local worker processes (default: cores)")
    p.add_argument("--scheduler", help="address of a Dask distributed scheduler (e.g. tcp://host:8786)")
    p.add_argument(
        "--sweep-rate", nargs="+", metavar=("FILE", "RATE"), help="a formation file and control rates [Hz] to try"
    )
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.add_argument("--schema", action="store_true", help="print the reference of the campaign file's keys and exit")
    return p


@guarded("formation-campaign")
def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.schema:
        print(reference_markdown(), end="")
        return 0
    try:
        if args.sweep_rate:
            formation = Path(args.sweep_rate[0])
            try:
                rates = [
                    float(_number(f"--sweep-rate[{k}]", float(r), positive=True))
                    for k, r in enumerate(args.sweep_rate[1:], 1)
                ]
            except ValueError as exc:
                raise CampaignError("--sweep-rate", f"rates must be numbers [Hz]: {exc}") from None
            if not rates:
                raise CampaignError("--sweep-rate", "give a formation file and at least one rate")
            out = args.out or Path("out") / f"{formation.stem}-sweep"
            return sweep_rate(formation, rates, out, workers=args.workers, scheduler=args.scheduler)
        if args.campaign is None:
            parser.error("give a campaign file or --sweep-rate FILE RATE…")
        campaign = load_campaign(args.campaign)
        if args.workers < 1:
            raise CampaignError("--workers", f"expected at least 1, got {args.workers}")
    except (CampaignError, FormationSpecError) as exc:
        print(f"formation-campaign: {exc}", file=sys.stderr)
        return 2
    out = args.out or Path("out") / f"{args.campaign.stem}-campaign"
    try:
        summary = run_campaign(campaign, out, workers=args.workers, scheduler=args.scheduler, quiet=args.quiet)
    except KeyboardInterrupt:
        print("\nformation-campaign: interrupted; run again to resume", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except OSError as exc:  # the runs finished are in runs.jsonl: a rerun resumes
        print(f"\nformation-campaign: could not write {out}: {exc}; run again to resume", file=sys.stderr)
        return ExitCode.INCOMPLETE
    if "per_condition" in summary:
        print(condition_table(summary))
    else:
        for rate, s in summary["per_control_rate"].items():
            lo, hi = s["pass_rate_ci95"]
            print(f"  {rate:>8} Hz: {s['passes']}/{s['runs']} pass ({lo:.2f}-{hi:.2f} at 95 %)")
    print(f"outputs in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
