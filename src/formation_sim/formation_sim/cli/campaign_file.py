"""The campaign file of ``formation-campaign``: its keys, declared once in :data:`CAMPAIGN_KEYS`, which
validate a file (:func:`parse_campaign`, :func:`load_campaign`: every error at once, each naming the key)
and render the reference of docs/campaigns.md (:func:`reference_markdown`, ``formation-campaign --schema``).

A campaign file names a base formation, how many random samples to draw, the control rates to run
each at and what varies between samples (plant, disturbance and noise amplitudes, initial attitudes,
link and gain grids): a :class:`Campaign`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from formation_core.errors import FormationSpecError
from formation_core.loader import read_document
from formation_core.schema import REQUIRED

#: the conditions a campaign may cross with the control rate: a link model's values (``links``) and
#: gains (``gains``); each run's row names its own (empty where the campaign does not set one)
CONDITIONS = ("link_delay", "link_loss", "link_jitter", "sensor_rate", "delta", "gamma")


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


def checked_number(field: str, value: Any, *, positive: bool = False, integer: bool = False) -> float:
    """``value`` as a number (an int with ``integer``, > 0 with ``positive``), or CampaignError naming ``field``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        kind = "an integer" if integer else "a number"
        raise CampaignError(field, f"expected {kind}, got {type(value).__name__} {value!r}")
    if not math.isfinite(value) or (positive and value <= 0):
        raise CampaignError(field, f"expected a {'positive ' if positive else ''}finite number, got {value!r}")
    return value


def _range(field: str, value: Any) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise CampaignError(field, f"expected [low, high], got {value!r}")
    lo, hi = (checked_number(f"{field}[{k}]", v) for k, v in enumerate(value))
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
    return int(checked_number(field, value, positive=True, integer=True))


def _seed(field: str, value: Any, base: Path) -> int:
    seed = int(checked_number(field, value, integer=True))
    if seed < 0:
        raise CampaignError(field, f"expected a non-negative integer, got {seed}")
    return seed


def _rates(field: str, value: Any, base: Path) -> tuple[float, ...]:
    if not isinstance(value, list) or not value:
        raise CampaignError(field, f"expected a non-empty list of rates [Hz], got {value!r}")
    return tuple(float(checked_number(f"{field}[{k}]", r, positive=True)) for k, r in enumerate(value))


def _duration(field: str, value: Any, base: Path) -> float:
    return float(checked_number(field, value, positive=True))


def _scale_range(field: str, value: Any, base: Path) -> tuple[float, float]:
    lo, hi = _range(field, value)
    if lo <= 0:
        raise CampaignError(field, f"expected a positive scale range, got {list(value)!r}")
    return lo, hi


def _amplitude_range(field: str, value: Any, base: Path) -> tuple[float, float]:
    return _range(field, value)


def _angle(field: str, value: Any, base: Path) -> float:
    angle = float(checked_number(field, value))
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
        x = float(checked_number(f"{field}[{k}]", x))
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
