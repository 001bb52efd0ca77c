"""Pre-flight of every runner: the checks made before anything starts (exit 2 on failure).

One function, :func:`preflight`, used by formation-headless, formation-sim and
formation-launch: load the formation file with the command-line overrides, refuse QoS settings
that cannot work (lockstep needs reliable measurements), refuse a control rate below what the
velocity loop needs (docs/controller.md, "Sampled-data implementation") unless asked to warn, and prepare the output
directory (never overwrite a non-empty one without ``--force``; with it, an earlier run's
outputs are removed first).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from formation_msgs_py.errors import FormationError
from formation_msgs_py.options import HEADLESS, LAUNCH, RunOptions

if TYPE_CHECKING:
    from formation_msgs_py.spec import FormationSpec

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
    """The formation file with the command's ``simulation.*`` overrides (raises FormationSpecError).

    A new control rate without a physics rate keeps the file's physics rate when it is an
    integer multiple of it, else runs physics at the control rate.
    """
    from formation_msgs_py.spec import load_formation

    over = options.overrides()
    if "control_rate" in over and "physics_rate" not in over:
        spec = load_formation(options.file)
        ratio = spec.simulation.physics_rate / over["control_rate"]
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            over["physics_rate"] = over["control_rate"]
    return load_formation(options.file, overrides=over or None)


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


def prepare_out_dir(out: Path, force: bool, extra: tuple[str, ...] = ()) -> None:
    """Create ``out``; refuse a non-empty one unless ``force``, which removes an earlier run's
    outputs first (:func:`earlier_outputs`, with the command's own ``extra`` names): a run that
    stops before writing its own summary must not leave the earlier run's to be read as its own.
    Other files in ``out`` stay. InvalidRunError on failure."""
    try:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            if not force:
                raise InvalidRunError(f"output directory {out} exists and is not empty (use --force to overwrite)")
            if out.is_dir():
                for path in earlier_outputs(out, extra):
                    if path.is_dir() and not path.is_symlink():
                        shutil.rmtree(path)
                    else:
                        path.unlink()
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidRunError(f"output directory {out}: {exc.strerror or exc}") from None


def preflight(
    options: RunOptions,
    default_out: Callable[[FormationSpec, RunOptions], Path] | None,
) -> Prepared:
    """Everything checked before a run starts; raises FormationSpecError or InvalidRunError.

    ``default_out(spec, options)`` names OUT when ``--out`` is not given (None: no OUT).
    """
    spec = load_spec(options)
    sim = spec.simulation
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
        # the launcher's logs too: an earlier run's agent fault files must not be merged into this
        # run's summary (the simulator it starts, with --force, must leave them)
        prepare_out_dir(out, options.force, ("logs",) if options.command == LAUNCH else ())
        options = options.replace(out=out)
    return Prepared(spec, options, out, tuple(warnings))
