"""Pre-flight of every runner: the checks made before anything starts (exit 2 on failure).

One function, :func:`preflight`, used by formation-headless, formation-sim and
formation-launch: load the formation file with the command-line overrides, refuse QoS settings
that cannot work (lockstep needs reliable measurements), refuse a control rate below what the
velocity loop needs (docs/controller.md, "Sampled-data implementation") unless asked to warn, refuse a duration that
takes no control step or that no run can take (:func:`duration_problem`), check the output
directory (:func:`check_out_dir`: a writable directory, never a non-empty one without
``--force``) and then prepare it (with ``--force``, an earlier run's outputs are removed first).
Nothing is created or removed before every check has passed.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from formation_core.errors import FormationError, FormationSpecError
from formation_core.options import HEADLESS, LAUNCH, RunOptions

if TYPE_CHECKING:
    from formation_core.formation import FormationSpec

# The file is read and validated before the numerical cores are imported (rate_problems): a bad
# file costs the loader (numpy, yaml) and no more (BENCHMARKS.md, "Bad input").


class InvalidRunError(FormationError):
    """The run cannot start as asked (settings, rate, output directory): exit 2."""


@dataclass(frozen=True)
class Prepared:
    """A run that passed pre-flight: the formation, the options with mode resolved, OUT, warnings."""

    spec: FormationSpec
    options: RunOptions
    out: Path | None
    warnings: tuple[str, ...]


def load_spec(options: RunOptions) -> FormationSpec:
    """The formation file with the command's ``simulation.*`` overrides and the agents' gains of its
    ``--params-file`` (raises FormationSpecError).

    A new control rate without a physics rate keeps the file's physics rate when it is an
    integer multiple of it, else runs physics at the control rate.
    """
    from formation_core.spec import load_formation

    if options.file is None:
        raise FormationSpecError("", "no formation file given")
    over = options.overrides()
    if "control_rate" in over and "physics_rate" not in over:
        spec = load_formation(options.file)
        ratio = spec.simulation.physics_rate / over["control_rate"]
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            over["physics_rate"] = over["control_rate"]
    spec = load_formation(options.file, overrides=over or None)
    if options.params_file is not None:
        from formation_agent.parameters_file import agent_gains

        spec = spec.with_agent_gains(agent_gains(options.params_file, spec.agent_ids))
    return spec


#: The longest simulated duration a run accepts [s]: a week (longer is a slip: 1e12 for 1e2).
MAX_DURATION_S = 7 * 86400.0
#: The fastest control rate [Hz]: every step's stamp (whole nanoseconds) differs from the one before.
MAX_CONTROL_RATE = 1e9
#: The most physics steps a run accepts (~14 h of a headless run at 50 µs a step).
MAX_PHYSICS_STEPS = 1_000_000_000
#: Bytes a trajectory row holds per agent (p, R, v, u) and per edge (e, ψ, ρ_e, ρ_ψ) in memory.
_ROW_BYTES_AGENT, _ROW_BYTES_EDGE = (3 + 9 + 6 + 6) * 8, 4 * 8


def _named(options: RunOptions, dest: str, key: str) -> str:
    """How the user set a value: the option, or the formation file's key."""
    if getattr(options, dest) is not None:
        return "--" + dest.replace("_", "-")
    return f"simulation.{key} in {options.file}"


def physical_memory() -> int | None:
    """This machine's memory [bytes], None if unknown."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        return None


def duration_problem(spec: FormationSpec, options: RunOptions) -> str | None:
    """Why the run's duration and rates make no run (none: they do): a control period under a
    nanosecond (:data:`MAX_CONTROL_RATE`), shorter than one control period (no step), longer than
    :data:`MAX_DURATION_S`, more than :data:`MAX_PHYSICS_STEPS`, or a trajectory larger than this
    machine's memory. Names the option or file key that set it."""
    s = spec.simulation
    duration = f"{_named(options, 'duration', 'duration')} {s.duration:g} s"
    period = 1.0 / s.control_rate
    if s.control_rate > MAX_CONTROL_RATE:
        rate = _named(options, "control_rate", "control_rate")
        return (
            f"control rate {s.control_rate:g} Hz ({rate}) has a period under a nanosecond: the steps' stamps, "
            f"whole nanoseconds, would not all differ (at most {MAX_CONTROL_RATE:g} Hz)"
        )
    if s.duration < period * (1 - 1e-9):
        rate = _named(options, "control_rate", "control_rate")
        return (
            f"{duration} is shorter than one control period: {period:g} s at {s.control_rate:g} Hz ({rate}); "
            "the run would take no step"
        )
    if s.duration > MAX_DURATION_S:
        return f"{duration} is longer than any run (at most {MAX_DURATION_S:g} s, a week)"
    steps = s.duration * s.physics_rate
    if steps > MAX_PHYSICS_STEPS:
        given = "physics_rate" if options.physics_rate is not None or options.control_rate is None else "control_rate"
        rate = _named(options, given, given)
        return (
            f"{duration} at a physics rate of {s.physics_rate:g} Hz ({rate}) is {steps:.3g} steps, more than any "
            f"run takes (at most {MAX_PHYSICS_STEPS:.0e})"
        )
    rows = s.duration * s.record_rate + 1
    need = rows * (len(spec.agents) * _ROW_BYTES_AGENT + len(spec.edges) * _ROW_BYTES_EDGE)
    memory = physical_memory()
    if memory is not None and need > memory:
        rate = _named(options, "record_rate", "record_rate")
        return (
            f"{duration} recorded at {s.record_rate:g} Hz ({rate}) keeps {rows:.3g} trajectory rows "
            f"({need / 1e9:.3g} GB), more than this machine's memory ({memory / 1e9:.3g} GB)"
        )
    return None


def rate_problems(spec: FormationSpec) -> list[str]:
    """One message per agent whose velocity loop needs more than the configured control rate."""
    from formation_sim.core.loop import initial_rho_v0
    from formation_sim.core.rates import rate_needs

    f_s = spec.simulation.control_rate
    return [
        f"agent {n.agent_id} needs {n.at_end:.0f} Hz by t={spec.simulation.duration:g} s "
        f"(insufficient from t={n.insufficient_from:.2f} s at {f_s:g} Hz)"
        for n in rate_needs(spec, initial_rho_v0(spec))
        if n.insufficient_from is not None
    ]


#: What a run leaves in OUT whatever its summary lists (the summary itself may be missing).
RUN_OUTPUTS = ("summary.json", "trajectory.npz", "bag", "view.mcap", "animation.gif")


def earlier_outputs(out: Path, extra: tuple[str, ...] = ()) -> list[Path]:
    """What an earlier run left in ``out``: :data:`RUN_OUTPUTS`, ``extra`` and every file its
    summary.json lists under ``outputs`` (plain names only: a summary cannot name a path outside OUT)."""
    names = {*RUN_OUTPUTS, *extra}
    try:
        listed = json.loads((out / "summary.json").read_text(encoding="utf-8")).get("outputs", [])
    except (OSError, ValueError, AttributeError):
        listed = []
    if isinstance(listed, list):
        names.update(n for n in listed if isinstance(n, str) and n not in ("", ".", "..") and Path(n).name == n)
    return sorted(out / n for n in names if os.path.lexists(out / n))


def _kind(path: Path) -> str:
    return "a file" if path.is_file() else "a symbolic link" if path.is_symlink() else "not a directory"


def check_out_dir(out: Path, force: bool) -> None:
    """InvalidRunError if ``out`` cannot be a run's output directory: not a directory, inside a
    file, not writable (read-only file system, permission), or not empty without ``force``.
    Creates and changes nothing."""
    try:
        if out.exists() or out.is_symlink():
            if not out.is_dir():
                raise InvalidRunError(f"output directory {out} is {_kind(out)}, not a directory")
            if not force and any(out.iterdir()):
                raise InvalidRunError(f"output directory {out} exists and is not empty (use --force to overwrite)")
        base = out
        while not base.exists():  # the directory the run would create OUT in
            if base.is_symlink():
                raise InvalidRunError(f"output directory {out}: {base} is a broken symbolic link")
            base = base.parent
        if not base.is_dir():
            raise InvalidRunError(f"output directory {out}: {base} is {_kind(base)}, not a directory")
        if os.statvfs(base).f_flag & os.ST_RDONLY:
            raise InvalidRunError(f"output directory {out}: {base} is on a read-only file system")
        if not os.access(base, os.W_OK | os.X_OK):
            raise InvalidRunError(f"output directory {out}: {base} is not writable (permission denied)")
    except OSError as exc:
        raise InvalidRunError(f"output directory {out}: {exc.strerror or exc}") from None


def prepare_out_dir(out: Path, force: bool, extra: tuple[str, ...] = ()) -> None:
    """Create ``out`` after :func:`check_out_dir`; with ``force`` remove an earlier run's outputs first
    (:func:`earlier_outputs`, with the command's own ``extra`` names): a run that stops before
    writing its own summary must not leave the earlier run's to be read as its own. Other files in
    ``out`` stay. InvalidRunError on failure."""
    check_out_dir(out, force)
    try:
        if out.is_dir():
            if force:
                for path in earlier_outputs(out, extra):
                    if path.is_dir() and not path.is_symlink():
                        shutil.rmtree(path)
                    else:
                        path.unlink()
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidRunError(f"output directory {out}: {exc.strerror or exc}") from None


def launch_outputs(options: RunOptions) -> tuple[str, ...]:
    """What ``--force`` removes besides :data:`RUN_OUTPUTS`: formation-launch's logs too (an earlier
    run's agent fault files must not be merged into this run's summary; the simulator it starts,
    with --force, must leave them)."""
    return ("logs",) if options.command == LAUNCH else ()


def preflight(
    options: RunOptions,
    default_out: Callable[[FormationSpec, RunOptions], Path] | None,
    *,
    prepare: bool = True,
) -> Prepared:
    """Everything checked before a run starts; raises FormationSpecError or InvalidRunError.

    ``default_out(spec, options)`` names OUT when ``--out`` is not given (None: no OUT).
    ``prepare`` false: OUT is checked only (:func:`check_out_dir`), for a command with checks of its
    own still to make, which then calls :func:`prepare_out_dir` itself.
    """
    spec = load_spec(options)
    sim = spec.simulation
    problem = duration_problem(spec, options)
    if problem is not None:
        raise InvalidRunError(problem)
    options = options.replace(mode=sim.mode, controller=sim.controller)
    if options.command != HEADLESS and sim.mode == "lockstep" and options.measurement_qos != "reliable":
        raise InvalidRunError(
            f"--measurement-qos {options.measurement_qos} is for realtime runs only: "
            "in lockstep a lost measurement stalls the step"
        )
    warnings: list[str] = []
    if options.command != HEADLESS or sim.controller == "sampled":
        problems = rate_problems(spec)
        if problems and not (options.allow_low_rate or sim.rate_check == "warn"):
            raise InvalidRunError(
                "control rate too low (raise --control-rate or pass --allow-low-rate): " + "; ".join(problems)
            )
        warnings += problems
    if spec.dropped_edges:
        warnings.append("spanning tree: dropped edges " + ", ".join(f"({a}, {b})" for a, b in spec.dropped_edges))
    out = options.out or (default_out(spec, options) if default_out is not None else None)
    if out is not None:
        if prepare:
            prepare_out_dir(out, options.force, launch_outputs(options))
        else:
            check_out_dir(out, options.force)
        options = options.replace(out=out)
    return Prepared(spec, options, out, tuple(warnings))
