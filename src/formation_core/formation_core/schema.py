"""The formation-file schema: one declaration that validates, fills defaults, documents and builds.

Every field has a kind, a default (or ``REQUIRED``), a unit and a description.
:func:`parse_mapping` walks a YAML document against the schema and returns plain Python values
with defaults filled in; it reports every unknown key (with the nearest valid one) and wrong
type of a mapping as :class:`FormationSpecError` naming the field path (shortened values).
:func:`parse_partial` returns the errors with the values that did parse (a :class:`Parsed`), so
that the checks that need only those can still run.
:func:`schema_markdown` renders the reference table of ``docs/formation_file.md``, and
:func:`documented` the attribute list of the docstring of each frozen dataclass a block builds
(``SimulationSpec``, ``AgentSpec``, ``EdgeSpec``, ``ControllerGains``, ``VelocityFunnel``, ``Dynamics``,
written as typed classes in :mod:`formation_core.spec` so that a type checker sees them). Tests
keep the table, and each class's attribute names and types (:func:`attribute_type`), in step
with this declaration.

A field's ``attr`` names its attribute where it differs from the key (``distance`` -> ``d_des``),
an ``inline`` map's fields are attributes of the agent or edge itself (``distance_funnel.rho_inf``
-> ``rho_e_inf``). Semantic checks (tree, distance bounds, funnels) live in
:mod:`formation_core.spec`.

Over 500 lines: the declaration of every field of a formation file (the tables, about half the
module) and the one walker that reads them must change together; the tables are the point of the
module, and the walker has no other user.
"""

from __future__ import annotations

import difflib
import inspect
import math
import re
import reprlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from formation_core.errors import FormationSpecError, each_error, one_error


class _Required:
    def __repr__(self) -> str:
        return "required"


REQUIRED: Any = _Required()
AGENT_ID_PATTERN = re.compile(r"^[A-Za-z0-9_]+$")
#: Default actuator limits (N, N·m): above 5x the largest peak force (19.2 N) and torque (12.8 N·m)
#: of the presets in config/ (headless, BENCHMARKS.md), so that no preset ever saturates, yet a
#: runaway command stays bounded.
ACTUATOR_MAX_FORCE = 100.0
ACTUATOR_MAX_TORQUE = 100.0


@dataclass(frozen=True)
class Field:
    """One key of a mapping in the formation file."""

    name: str
    kind: str
    default: Any = REQUIRED
    doc: str = ""
    unit: str = ""
    children: tuple[Field, ...] = ()
    choices: tuple[str, ...] = ()
    variants: Mapping[str, tuple[Field, ...]] = field(default_factory=dict)
    #: ``positive``, ``nonnegative`` or ``""`` for numbers
    sign: str = ""
    #: the attribute of the built object (:mod:`formation_core.spec`) that holds the value; ``""``: ``name``
    attr: str = ""
    #: a ``map`` whose fields are attributes of the enclosing object (not an object of their own)
    inline: bool = False
    #: the attribute's type in the built object where it is not the kind's (:data:`KIND_TYPES`)
    type: str = ""
    #: a ``variant``'s key naming its variant
    key: str = "model"


# --- shared blocks ----------------------------------------------------------------------------

_ROTATION_DOC = (
    "exactly one of `matrix` (3x3, rows), `quaternion` [x, y, z, w], `rpy` [roll, pitch, yaw] "
    "(fixed axes x-y-z, rad) or `axis_angle` {axis: [x, y, z], angle: rad}; optional "
    "`project: true` replaces a matrix that is not a rotation by its nearest rotation; or the "
    "string `identity`"
)

_MODEL_PARAMS = {
    "none": (),
    "paper": (
        Field("amplitude", "float", REQUIRED, "A in A·sin(‖p_ref‖₁·tr(R_i)·ω·t + φ)·v_i", "", sign="nonnegative"),
        Field("frequency", "float", REQUIRED, "ω in the paper's sinusoid", "rad/s", sign="nonnegative"),
        Field("phase", "float", 0.0, "φ in the paper's sinusoid", "rad"),
        Field(
            "position_reference",
            "enum",
            "first_agent",
            "whose position enters ‖p_ref‖₁: the first agent's (the paper, literally) or the agent's own",
            choices=("first_agent", "self"),
        ),
    ),
    "constant": (Field("value", "float_or_vec6", REQUIRED, "constant body-frame value [linear, angular]"),),
    "random": (
        Field("bound", "float_or_vec6", REQUIRED, "per-channel bound of the signal", sign="nonnegative"),
        Field("max_frequency", "float", 1.0, "highest frequency of the seeded sum of sinusoids", "Hz", sign="positive"),
        Field("components", "int", 4, "sinusoids per channel (seeded by simulation.seed)", sign="positive"),
    ),
}

_FUNNEL_V = (
    Field(
        "rho_0",
        "auto_or_vec6",
        "auto",
        "initial width ρ_v0 per channel, or `auto`: auto_scale·|e_v(0)| + auto_offset, "
        "computed by the agent at its first step",
    ),
    Field("auto_scale", "float", 2.0, "scale of |e_v(0)| when rho_0 is auto", sign="positive"),
    Field("auto_offset", "float", 1.0, "offset added when rho_0 is auto", "m/s, rad/s", sign="positive"),
    Field("rho_inf", "float_or_vec6", 0.1, "steady width ρ_v∞ per channel", "m/s, rad/s", sign="positive"),
    Field("decay", "float_or_vec6", 0.2, "decay rate l_v per channel", "1/s", sign="positive"),
)

_JITTER = {
    "none": (),
    "uniform": (Field("max", "float", REQUIRED, "largest extra delay: uniform on [0, max]", "s", sign="nonnegative"),),
    "exponential": (
        Field("mean", "float", REQUIRED, "mean extra delay of the untruncated distribution", "s", sign="positive"),
        Field("max", "float", REQUIRED, "the distribution is truncated to [0, max]", "s", sign="positive"),
    ),
}

_LOSS = {
    "none": (),
    "independent": (Field("probability", "probability", REQUIRED, "each sample is lost with this probability"),),
    "gilbert_elliott": (
        Field("p_good_bad", "probability", REQUIRED, "after each sample, the probability of going from good to bad"),
        Field("p_bad_good", "probability", REQUIRED, "after each sample, the probability of going from bad to good"),
        Field("loss_good", "probability", 0.0, "loss probability in the good state"),
        Field("loss_bad", "probability", 1.0, "loss probability in the bad state"),
    ),
}

_LINK_DELAY = Field("delay", "float", 0.0, "constant latency of every sample", "s", sign="nonnegative")
_LINK_LOSS = Field(
    "loss",
    "variant",
    {"model": "none"},
    "which samples are lost: `model` none | independent | gilbert_elliott (two states, bursts; starts good)",
    variants=_LOSS,
)

#: One measurement stream from the simulator to an agent (docs/links.md).
MEASUREMENT_LINK_FIELDS: tuple[Field, ...] = (
    Field(
        "rate",
        "optional_float",
        None,
        "sensor rate: a sample every 1/rate s (at the first control step at or after it), held by the agent "
        "between samples; null: every control step; at most simulation.control_rate",
        "Hz",
        sign="positive",
        type="float | None",
    ),
    _LINK_DELAY,
    Field(
        "jitter",
        "variant",
        {"distribution": "none"},
        "extra delay of each sample, never negative: `distribution` none | uniform | exponential; a sample "
        "that arrives after a newer one is dropped (the newest wins)",
        variants=_JITTER,
        key="distribution",
    ),
    _LINK_LOSS,
)

#: An agent's wrench on its way to the plant.
WRENCH_LINK_FIELDS: tuple[Field, ...] = (_LINK_DELAY, _LINK_LOSS)

AGENT_LINK_FIELDS: tuple[Field, ...] = (
    Field(
        "poses",
        "map",
        {},
        "the relative pose of each neighbour (an edge's `links` may set one end's)",
        children=MEASUREMENT_LINK_FIELDS,
        type="MeasurementLink",
    ),
    Field(
        "velocity",
        "map",
        {},
        "the agent's own velocity measurement",
        children=MEASUREMENT_LINK_FIELDS,
        type="MeasurementLink",
    ),
    Field(
        "wrench",
        "map",
        {},
        "the agent's wrench on its way to the plant, which applies the newest one it has received "
        "(zero before the first, and once it is older than simulation.command_timeout)",
        children=WRENCH_LINK_FIELDS,
        type="WrenchLink",
    ),
)

AGENT_FIELDS: tuple[Field, ...] = (
    Field("id", "agent_id", REQUIRED, "agent name: letters, digits, underscore (topics use agent_<id>)"),
    Field("radius", "float", REQUIRED, "radius r_i of the ball the agent occupies", "m", sign="positive"),
    Field("sensing_radius", "float", REQUIRED, "sensing radius s_i", "m", sign="positive"),
    Field("position", "vec3", REQUIRED, "initial position p_i(0) in the world frame", "m", type="np.ndarray"),
    Field("orientation", "rotation", "identity", "initial R_world_body R_i(0); " + _ROTATION_DOC, attr="R_world_body"),
    Field("linear_velocity", "vec3", (0.0, 0.0, 0.0), "initial body-frame linear velocity", "m/s"),
    Field("angular_velocity", "vec3", (0.0, 0.0, 0.0), "initial body-frame angular velocity", "rad/s"),
    Field(
        "controller",
        "map",
        {},
        "what the agent knows of itself: gains and velocity funnel",
        type="ControllerGains",
        children=(
            Field("delta", "float", 0.1, "gain δ_i of the desired velocity", sign="positive"),
            Field("gamma", "float", 15.0, "gain γ_i of the wrench", sign="positive"),
            Field(
                "velocity_funnel",
                "map",
                {},
                "velocity performance functions ρ_v",
                children=_FUNNEL_V,
                type="VelocityFunnel",
            ),
            Field(
                "saturation_margin",
                "float",
                1e-6,
                "a normalised error outside its funnel is clamped to (1 − margin) of it: finite, saturated wrench",
                sign="positive",
            ),
            Field(
                "max_force",
                "optional_float",
                None,
                "norm limit of the commanded force (null: the actuators' dynamics.max_force; at most that)",
                "N",
                sign="positive",
            ),
            Field(
                "max_torque",
                "optional_float",
                None,
                "norm limit of the commanded torque (null: the actuators' dynamics.max_torque; at most that)",
                "N·m",
                sign="positive",
            ),
            Field(
                "measurement_timeout",
                "float",
                0.1,
                "older measurements (behind /clock, sim time) are refused and dropped: counted, ERROR on /diagnostics",
                "s",
                sign="positive",
            ),
        ),
    ),
    Field(
        "dynamics",
        "map",
        REQUIRED,
        "true plant, read by the simulator only",
        type="Dynamics",
        children=(
            Field("mass", "float", REQUIRED, "mass m_i", "kg", sign="positive"),
            Field("inertia", "inertia", REQUIRED, "body-frame inertia: 3 diagonal entries or a 3x3 matrix", "kg·m²"),
            Field(
                "max_force",
                "float",
                ACTUATOR_MAX_FORCE,
                "actuator limit: the plant saturates the force norm to it; the simulator refuses a larger command",
                "N",
                sign="positive",
            ),
            Field(
                "max_torque",
                "float",
                ACTUATOR_MAX_TORQUE,
                "actuator limit: the plant saturates the torque norm to it; the simulator refuses a larger command",
                "N·m",
                sign="positive",
            ),
            Field(
                "disturbance",
                "variant",
                {"model": "none"},
                "w_i(x, v, t): `model` none | paper | constant | random",
                variants=_MODEL_PARAMS,
            ),
            Field(
                "velocity_noise",
                "variant",
                {"model": "none"},
                "n_i(x, t) added to the measured velocity: `model` none | paper | constant | random",
                variants=_MODEL_PARAMS,
            ),
        ),
    ),
    Field(
        "measurement_noise",
        "map",
        {},
        "noise on the relative poses this agent receives (simulator only, seeded)",
        children=(
            Field(
                "position_std",
                "float",
                0.0,
                "std of Gaussian noise per axis",
                "m",
                sign="nonnegative",
                attr="position_noise_std",
            ),
            Field(
                "rotation_std",
                "float",
                0.0,
                "std of a Gaussian rotation vector per axis",
                "rad",
                sign="nonnegative",
                attr="rotation_noise_std",
            ),
        ),
        inline=True,
    ),
    Field(
        "links",
        "map",
        {},
        "how measurements reach this agent and its wrench the plant: sensor rate, delay, jitter, loss "
        "(simulator only, seeded by simulation.seed; docs/links.md); none given: ideal links",
        children=AGENT_LINK_FIELDS,
        type="AgentLinks",
    ),
)

EDGE_FIELDS: tuple[Field, ...] = (
    Field("tail", "agent_id", REQUIRED, "k1, the tail of the edge"),
    Field("head", "agent_id", REQUIRED, "k2, the head of the edge"),
    Field("distance", "float", REQUIRED, "desired distance d_k,des", "m", sign="positive", attr="d_des"),
    Field("orientation", "rotation", "identity", "desired R_k,des = R_headᵀ R_tail; " + _ROTATION_DOC, attr="R_des"),
    Field("d_col", "optional_float", None, "collision distance (default r_tail + r_head)", "m", sign="positive"),
    Field("d_con", "optional_float", None, "connectivity distance (default min(s_tail, s_head))", "m", sign="positive"),
    Field(
        "distance_funnel",
        "map",
        {},
        "ρ_e of the edge",
        children=(
            Field(
                "rho_inf",
                "float",
                0.1,
                "steady width ρ_e∞ in (0, max(C_col, C_con))",
                "m²",
                sign="positive",
                attr="rho_e_inf",
            ),
            Field("decay", "float", 1.5, "decay rate l_e", "1/s", sign="positive", attr="decay_e"),
        ),
        inline=True,
    ),
    Field(
        "orientation_funnel",
        "map",
        {},
        "ρ_ψ of the edge",
        children=(
            Field("rho_0", "float", 1.99, "initial width ρ_ψ0 in (ψ(0), 2)", sign="positive", attr="rho_psi_0"),
            Field("rho_inf", "float", 0.1, "steady width ρ_ψ∞ in (0, ρ_ψ0)", sign="positive", attr="rho_psi_inf"),
            Field("decay", "float", 1.5, "decay rate l_ψ", "1/s", sign="positive", attr="decay_psi"),
        ),
        inline=True,
    ),
    Field(
        "links",
        "map",
        {},
        "the link of one end's measurement of the other, replacing that agent's `links.poses` for it",
        type="EdgeLinks",
        children=(
            Field(
                "tail",
                "map",
                None,
                "the tail's measurement of the head (null: the tail's `links.poses`)",
                children=MEASUREMENT_LINK_FIELDS,
                type="MeasurementLink | None",
            ),
            Field(
                "head",
                "map",
                None,
                "the head's measurement of the tail (null: the head's `links.poses`)",
                children=MEASUREMENT_LINK_FIELDS,
                type="MeasurementLink | None",
            ),
        ),
    ),
)

SIMULATION_FIELDS: tuple[Field, ...] = (
    Field(
        "mode", "enum", "lockstep", "ROS 2 runs: lockstep (deterministic) or realtime", choices=("lockstep", "realtime")
    ),
    Field("duration", "float", 5.0, "simulated time", "s", sign="positive"),
    Field(
        "physics_rate", "float", 10000.0, "integrator rate; an integer multiple of control_rate", "Hz", sign="positive"
    ),
    Field(
        "control_rate",
        "float",
        1000.0,
        "rate at which agents compute wrenches (zero-order hold)",
        "Hz",
        sign="positive",
    ),
    Field(
        "controller",
        "enum",
        "sampled",
        "headless runs: sampled at control_rate, or continuous (evaluated at every integrator stage)",
        choices=("sampled", "continuous"),
    ),
    Field(
        "record_rate",
        "float",
        1000.0,
        "rate of trajectory.npz and plots (funnels are checked at every step)",
        "Hz",
        sign="positive",
    ),
    Field("seed", "int", 0, "seed of every random draw (noise, random disturbances)", sign="nonnegative"),
    Field("gravity", "vec3", (0.0, 0.0, 0.0), "gravity in the world frame (the paper: off)", "m/s²", type="np.ndarray"),
    Field(
        "spanning_tree",
        "bool",
        False,
        "reduce a cyclic sensing graph to a spanning tree (the dropped edges are printed)",
    ),
    Field(
        "rate_check",
        "enum",
        "refuse",
        "a control rate below what the velocity loop needs: refuse to run, or warn",
        choices=("refuse", "warn"),
    ),
    Field(
        "contact",
        "enum",
        "report",
        "two bodies touching (clearance, the distance between centres minus both radii, at most 0, for any pair, "
        "neighbours or not): report it (summary, verdict, figures, viewer), or also fail the run",
        choices=("report", "fail"),
    ),
    Field(
        "step_timeout",
        "float",
        5.0,
        "lockstep: wall time to wait for every wrench before a last resend; 3 s later the silent agents are reported",
        "s",
        sign="positive",
    ),
    Field(
        "command_timeout",
        "float",
        0.05,
        "realtime: a wrench older than this (sim time) is replaced by zero",
        "s",
        sign="positive",
    ),
)

TOP_FIELDS: tuple[Field, ...] = (
    Field("name", "str", "", "name of the formation (default: the file name)"),
    Field("description", "str", "", "free text"),
    Field("simulation", "map", {}, "run settings", children=SIMULATION_FIELDS),
    Field(
        "defaults",
        "defaults",
        {},
        "`agent:` and `edge:` mappings merged under every agent and edge (the item's own keys win)",
    ),
    Field("agents", "agents", REQUIRED, "list of agents (at least 2)", children=AGENT_FIELDS),
    Field("edges", "edges", REQUIRED, "list of edges of the sensing tree", children=EDGE_FIELDS),
)


# --- parsing ----------------------------------------------------------------------------------


def _type_name(value: Any) -> str:
    return type(value).__name__ if value is not None else "null"


_SHORT = reprlib.Repr()
_SHORT.maxstring = _SHORT.maxother = 40
_SHORT.maxlist = _SHORT.maxtuple = _SHORT.maxdict = 4
_SHORT.maxlevel = 2


def short(value: Any) -> str:
    """A repr of ``value`` of at most about 60 characters (error messages never print a whole document)."""
    text = _SHORT.repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def did_you_mean(key: Any, known: Sequence[str]) -> str:
    """`` (did you mean 'gamma'?)`` for the nearest valid key, or ``""``."""
    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def unknown_key(path: str, key: Any, known: Sequence[str]) -> FormationSpecError:
    """The error of an unknown key, with the nearest valid one."""
    listed = ", ".join(sorted(known)) or "none"
    return _fail(path, f"unknown key{did_you_mean(key, known)} (expected one of: {listed})", key)


def _fail(path: str, message: str, value: Any = None) -> FormationSpecError:
    return FormationSpecError(path, message, value)


def _as_float(value: Any, path: str, sign: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(path, f"expected a number, got {_type_name(value)} {short(value)}", value)
    x = float(value)
    if not math.isfinite(x):
        raise _fail(path, f"{short(value)} is not finite", value)
    if sign == "positive" and x <= 0:
        raise _fail(path, f"{short(value)} must be > 0", value)
    if sign == "nonnegative" and x < 0:
        raise _fail(path, f"{short(value)} must be >= 0", value)
    return x


def _as_vector(value: Any, n: int, path: str, sign: str = "") -> tuple[float, ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != n:
        raise _fail(path, f"expected a list of {n} numbers, got {short(value)}", value)
    return tuple(_as_float(x, f"{path}[{i}]", sign) for i, x in enumerate(value))


def _as_matrix(value: Any, path: str) -> tuple[tuple[float, ...], ...]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 3:
        raise _fail(path, f"expected a 3x3 matrix (3 rows of 3 numbers), got {short(value)}", value)
    return tuple(_as_vector(row, 3, f"{path}[{i}]") for i, row in enumerate(value))


def _parse_rotation(value: Any, path: str) -> dict[str, Any]:
    if value == "identity":
        return {"matrix": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "project": False}
    if not isinstance(value, Mapping):
        raise _fail(path, f"expected a rotation mapping or 'identity', got {short(value)}", value)
    forms = [k for k in ("matrix", "quaternion", "rpy", "axis_angle") if k in value]
    unknown = sorted(set(value) - {"matrix", "quaternion", "rpy", "axis_angle", "project"})
    if unknown:
        raise unknown_key(f"{path}.{unknown[0]}", unknown[0], ("matrix", "quaternion", "rpy", "axis_angle", "project"))
    if len(forms) != 1:
        raise _fail(path, f"give exactly one of matrix, quaternion, rpy, axis_angle (got {forms or 'none'})", value)
    form = forms[0]
    out: dict[str, Any] = {"project": False}
    if "project" in value:
        if not isinstance(value["project"], bool):
            raise _fail(f"{path}.project", f"expected true or false, got {short(value['project'])}", value["project"])
        out["project"] = value["project"]
    raw = value[form]
    if form == "matrix":
        out["matrix"] = _as_matrix(raw, f"{path}.matrix")
    elif form == "quaternion":
        q = _as_vector(raw, 4, f"{path}.quaternion")
        if math.sqrt(sum(c * c for c in q)) < 1e-9:
            raise _fail(f"{path}.quaternion", f"{list(q)} has zero norm", raw)
        out["quaternion"] = q
    elif form == "rpy":
        out["rpy"] = _as_vector(raw, 3, f"{path}.rpy")
    else:
        if not isinstance(raw, Mapping) or set(raw) != {"axis", "angle"}:
            raise _fail(f"{path}.axis_angle", f"expected {{axis: [x, y, z], angle: rad}}, got {short(raw)}", raw)
        axis = _as_vector(raw["axis"], 3, f"{path}.axis_angle.axis")
        if math.sqrt(sum(c * c for c in axis)) < 1e-12:
            raise _fail(f"{path}.axis_angle.axis", f"{list(axis)} has no direction", raw["axis"])
        out["axis_angle"] = (axis, _as_float(raw["angle"], f"{path}.axis_angle.angle"))
    return out


def _parse_value(f: Field, value: Any, path: str) -> Any:
    kind = f.kind
    if kind == "float":
        return _as_float(value, path, f.sign)
    if kind == "optional_float":
        return None if value is None else _as_float(value, path, f.sign)
    if kind == "probability":
        x = _as_float(value, path)
        if not 0.0 <= x <= 1.0:
            raise _fail(path, f"{short(value)} is not a probability in [0, 1]", value)
        return x
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(path, f"expected an integer, got {_type_name(value)} {short(value)}", value)
        if f.sign == "positive" and value <= 0:
            raise _fail(path, f"{short(value)} must be > 0", value)
        if f.sign == "nonnegative" and value < 0:
            raise _fail(path, f"{short(value)} must be >= 0", value)
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise _fail(path, f"expected true or false, got {short(value)}", value)
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise _fail(path, f"expected a string, got {_type_name(value)} {short(value)}", value)
        return value
    if kind == "enum":
        if value not in f.choices:
            raise _fail(path, f"{short(value)} is not one of {', '.join(f.choices)}", value)
        return value
    if kind == "agent_id":
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise _fail(path, f"expected an agent id (integer or name), got {short(value)}", value)
        text = str(value)
        if not AGENT_ID_PATTERN.match(text):
            raise _fail(path, f"{short(value)} is not a valid agent id (letters, digits, underscore)", value)
        return text
    if kind == "vec3":
        return _as_vector(value, 3, path, f.sign)
    if kind == "float_or_vec6":
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return (_as_float(value, path, f.sign),) * 6
        return _as_vector(value, 6, path, f.sign)
    if kind == "auto_or_vec6":
        if value == "auto":
            return "auto"
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return (_as_float(value, path, "positive"),) * 6
        if isinstance(value, str):
            raise _fail(path, f"{short(value)} is neither 'auto' nor a number or list of 6", value)
        return _as_vector(value, 6, path, "positive")
    if kind == "inertia":
        if (
            isinstance(value, Sequence)
            and not isinstance(value, str)
            and len(value) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
        ):
            d = _as_vector(value, 3, path)
            return tuple(tuple(d[i] if i == j else 0.0 for j in range(3)) for i in range(3))
        return _as_matrix(value, path)
    if kind == "rotation":
        return _parse_rotation(value, path)
    if kind == "map":
        return parse_mapping(value, f.children, path)
    if kind == "variant":
        key = f.key
        if not isinstance(value, Mapping) or key not in value:
            raise _fail(path, f"expected a mapping with a '{key}' key, got {short(value)}", value)
        model = value[key]
        if not isinstance(model, str) or model not in f.variants:  # a mapping or list is no model name
            raise _fail(f"{path}.{key}", f"{short(model)} is not one of {', '.join(f.variants)}", model)
        rest = {k: v for k, v in value.items() if k != key}
        out = parse_mapping(rest, f.variants[model], path)
        out[key] = model
        return out
    raise AssertionError(f"schema kind {kind!r} has no parser")  # pragma: no cover


class UnusableValueError(KeyError):
    """A value read from a :class:`Parsed` that is missing because the file gets it wrong (its error
    is reported already): the check that reads it is skipped."""


class Parsed(dict[str, Any]):
    """The fields of a mapping that parsed; reading one that did not raises :class:`UnusableValueError`."""

    def __missing__(self, key: str) -> Any:
        raise UnusableValueError(key)


def parse_partial(node: Any, fields: tuple[Field, ...], path: str) -> tuple[Parsed, list[FormationSpecError]]:
    """Validate ``node`` against ``fields``: every field that parsed (defaults filled in; a nested
    ``map`` is parsed field by field too) and every error (unknown keys, bad or missing fields)."""
    if node is None:
        node = {}
    if not isinstance(node, Mapping):
        return Parsed(), [_fail(path, f"expected a mapping, got {_type_name(node)} {short(node)}", node)]
    known = [f.name for f in fields]
    errors = [unknown_key(f"{path}.{key}" if path else str(key), key, known) for key in node if key not in known]
    out = Parsed()
    for f in fields:
        where = f"{path}.{f.name}" if path else f.name
        # defaults go through the same parser, so they are normalised like given values
        value = node[f.name] if f.name in node else f.default
        if value is REQUIRED:
            errors.append(_fail(where, "is required"))
        elif f.kind == "map" and value is None and f.default is None:
            out[f.name] = None  # an optional block, absent
        elif f.kind == "map":
            out[f.name], errs = parse_partial(value, f.children, where)
            errors.extend(errs)
        else:
            try:
                out[f.name] = _parse_value(f, value, where)
            except FormationSpecError as exc:
                errors.extend(each_error(exc))
    return out, errors


def parse_mapping(node: Any, fields: tuple[Field, ...], path: str) -> dict[str, Any]:
    """Validate ``node`` against ``fields``; returns a dict with every field set.

    Every unknown key and bad field is reported: one FormationSpecError, or CollectedFormationSpecError.
    """
    out, errors = parse_partial(node, fields, path)
    if errors:
        raise one_error(errors)
    return out


def check_partial(node: Any, fields: tuple[Field, ...], path: str) -> list[FormationSpecError]:
    """Errors of a partial mapping (a ``defaults`` block): unknown keys and bad values; none required."""
    if not isinstance(node, Mapping):
        return [_fail(path, f"expected a mapping, got {_type_name(node)} {short(node)}", node)]
    by_name = {f.name: f for f in fields}
    errors: list[FormationSpecError] = []
    for key, value in node.items():
        where = f"{path}.{key}"
        f = by_name.get(key)
        if f is None:
            errors.append(unknown_key(where, key, list(by_name)))
        elif f.kind == "map" and value is None and f.default is None:
            continue
        elif f.kind == "map":
            errors.extend(check_partial(value, f.children, where))
        else:
            try:
                _parse_value(f, value, where)
            except FormationSpecError as exc:
                errors.extend(each_error(exc))
    return errors


# --- built objects ----------------------------------------------------------------------------

#: The type of a built object's attribute (as written in :mod:`formation_core.spec`) per kind;
#: a field's ``type`` overrides it where the loader converts the value further (a numpy array, a
#: nested object). ``optional_float``: the loader resolves ``null`` to the derived number.
KIND_TYPES: Mapping[str, str] = {
    "float": "float",
    "optional_float": "float",
    "probability": "float",
    "int": "int",
    "bool": "bool",
    "str": "str",
    "enum": "str",
    "agent_id": "str",
    "vec3": "tuple[float, ...]",
    "float_or_vec6": "tuple[float, ...]",
    "auto_or_vec6": "tuple[float, ...] | None",
    "inertia": "np.ndarray",
    "rotation": "np.ndarray",
    "variant": "SignalModel",
}


def block(fields: tuple[Field, ...], *names: str) -> tuple[Field, ...]:
    """The children of the nested mapping ``names`` (e.g. ``block(AGENT_FIELDS, "controller")``)."""
    for name in names:
        fields = next(f for f in fields if f.name == name).children
    return fields


def attributes(fields: tuple[Field, ...], prefix: str = "") -> list[tuple[str, Field]]:
    """(file key, field) of each attribute of the built object: inline maps contribute their children."""
    out: list[tuple[str, Field]] = []
    for f in fields:
        out.extend(attributes(f.children, f"{prefix}{f.name}.") if f.inline else [(prefix + f.name, f)])
    return out


def attribute_type(f: Field) -> str:
    """The annotation of the attribute ``f`` becomes in its built object."""
    return f.type or KIND_TYPES[f.kind]


def record_values(fields: tuple[Field, ...], parsed: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of a built object from a block :func:`parse_mapping` returned."""
    out: dict[str, Any] = {}
    for f in fields:
        if f.inline:
            out.update(record_values(f.children, parsed[f.name]))
        else:
            out[f.attr or f.name] = parsed[f.name]
    return out


_T = TypeVar("_T")


def documented(fields: tuple[Field, ...], *, derived: tuple[tuple[str, str], ...] = ()) -> Callable[[_T], _T]:
    """A class decorator: appends the attributes of the block ``fields`` (unit, meaning, file key) to
    the class's docstring, so that the schema stays the one place where a field is described.

    ``derived``: (name, doc) of attributes that are not in the file (an index), first.
    """
    lines = ["", "Attributes (declared in formation_core.schema):"]
    lines += [f"    {n}: {d}" for n, d in derived]
    lines += [
        f"    {f.attr or f.name}{f' [{f.unit}]' if f.unit else ''}: {f.doc}" + (f" (file: {key})" if f.attr else "")
        for key, f in attributes(fields)
    ]

    def apply(cls: _T) -> _T:
        cls.__doc__ = "\n".join([inspect.cleandoc(cls.__doc__ or ""), *lines])
        return cls

    return apply


# --- documentation ----------------------------------------------------------------------------


def _rows(fields: tuple[Field, ...], prefix: str) -> list[str]:
    rows: list[str] = []
    for f in fields:
        name = f"{prefix}{f.name}"
        if f.kind in ("map", "agents", "edges") and f.children:
            default = "required" if f.default is REQUIRED else "null" if f.default is None else ""
            rows.append(f"| `{name}` | {f.kind} | {default} | {f.unit} | {f.doc} |")
            child_prefix = f"{name}[]." if f.kind in ("agents", "edges") else f"{name}."
            rows.extend(_rows(f.children, child_prefix))
            continue
        if f.kind == "variant":
            default = f"{f.key}: {f.default[f.key]}"
            rows.append(f"| `{name}` | variant | {default} | {f.unit} | {f.doc} |")
            for model, params in f.variants.items():
                for p in params:
                    d = "required" if p.default is REQUIRED else f"`{p.default}`"
                    rows.append(f"| `{name}.{p.name}` ({model}) | {p.kind} | {d} | {p.unit} | {p.doc} |")
            continue
        default = "required" if f.default is REQUIRED else f"`{_fmt_default(f.default)}`"
        kind = f.kind if not f.choices else " \\| ".join(f.choices)
        rows.append(f"| `{name}` | {kind} | {default} | {f.unit} | {f.doc} |")
    return rows


def _fmt_default(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_fmt_default(v) for v in value) + "]"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict) and not value:
        return "{}"
    return str(value)


def schema_markdown() -> str:
    """The reference table of every field of a formation file, in Markdown."""
    header = [
        "| field | kind | default | unit | meaning |",
        "|---|---|---|---|---|",
    ]
    return "\n".join(header + _rows(TOP_FIELDS, "")) + "\n"
