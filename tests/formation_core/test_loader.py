"""The catalogue of bad formation files: each class is one error (or several, all reported) with
FILE:LINE:COL and the field, exit 2 from every command, never a traceback."""

from __future__ import annotations

import itertools
import re
import subprocess
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml
from bin_helpers import executable

from formation_core import loader
from formation_core.errors import CollectedFormationSpecError, FormationSpecError
from formation_core.spec import load_formation

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"

MINIMAL = """\
simulation:
  duration: 1.0
  physics_rate: 1000.0
  control_rate: 1000.0
agents:
  - id: a
    radius: 0.5
    sensing_radius: 3.0
    position: [0, 0, 0]
    dynamics: {mass: 1.0, inertia: [0.1, 0.1, 0.1]}
  - id: b
    radius: 0.5
    sensing_radius: 3.0
    position: [2, 0, 0]
    dynamics: {mass: 1.0, inertia: [0.1, 0.1, 0.1]}
edges:
  - {tail: a, head: b, distance: 1.5}
"""


def write(tmp_path: Path, text: str | bytes, name: str = "f.yaml") -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def error_of(path: Path) -> FormationSpecError:
    with pytest.raises(FormationSpecError) as info:
        load_formation(path)
    return info.value


def billion_laughs(levels: int = 10, width: int = 10) -> str:
    names = "abcdefghijklmnop"[:levels]
    lines = [f"{names[0]}: &{names[0]} [" + ", ".join(['"lol"'] * width) + "]"]
    for prev, name in itertools.pairwise(names):
        lines.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * width) + "]")
    lines += [f"agents: *{names[-1]}", f"edges: *{names[-1]}"]
    return "\n".join(lines) + "\n"


def test_minimal_file_loads(tmp_path) -> None:
    """The reference text of these tests is valid (each test below breaks one thing)."""
    assert load_formation(write(tmp_path, MINIMAL)).agent_ids == ("a", "b")


def test_binary_file_is_one_line_not_a_traceback(tmp_path) -> None:
    """A PNG given by mistake: not UTF-8, with the position of the first bad byte."""
    path = write(tmp_path, b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    err = error_of(path)
    assert str(err) == f"{path}:1:1: not UTF-8 text (byte 0x89): a formation file is YAML text"
    path = write(tmp_path, MINIMAL.encode() + b"name: caf\xe9\n", "latin1.yaml")
    assert str(error_of(path)).startswith(f"{path}:18:10: not UTF-8 text (byte 0xe9)")


def test_alias_bomb_is_refused_fast_and_small(tmp_path) -> None:
    """10 levels of 10 aliases (10¹⁰ nodes once expanded, 1.3 kB): refused before construction.

    Bounds: < 1 s and < 100 MB of Python allocations (measured here: a few ms, well under 1 MB).
    """
    path = write(tmp_path, billion_laughs())
    tracemalloc.start()
    started = time.perf_counter()
    err = error_of(path)
    elapsed = time.perf_counter() - started
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert elapsed < 1.0 and peak < 100e6, (elapsed, peak)
    assert re.fullmatch(
        rf"{re.escape(str(path))}:5:4: YAML aliases expand this document beyond 100000 nodes .*", str(err)
    )


def test_small_aliases_are_allowed(tmp_path) -> None:
    """An anchor reused a few times is fine: only the expansion is bounded."""
    text = MINIMAL.replace("    dynamics: {mass", "    dynamics: &dyn {mass", 1)
    text = text.replace("    dynamics: {mass: 1.0, inertia: [0.1, 0.1, 0.1]}\n", "    dynamics: *dyn\n", 1)
    assert text.count("*dyn") == 1
    assert load_formation(write(tmp_path, text)).agents[1].dynamics.mass == 1.0


def test_recursive_alias_is_refused(tmp_path) -> None:
    path = write(tmp_path, "name: &x [*x]\n")
    assert "recursive" in str(error_of(path)) or "not valid YAML" in str(error_of(path))


def test_duplicate_key_names_both_lines(tmp_path) -> None:
    """A second `duration:` (once silently a 500 s run): an error at the second, naming the first."""
    path = write(tmp_path, MINIMAL.replace("  duration: 1.0\n", "  duration: 1.0\n  duration: 500.0\n"))
    assert str(error_of(path)) == (
        f"{path}:3:3: simulation.duration: duplicate key (first at line 2); YAML would silently keep the last one"
    )


def test_duplicate_block_is_an_error(tmp_path) -> None:
    """A second `simulation:` block (once replaced the first, exit 0)."""
    path = write(tmp_path, MINIMAL + "simulation:\n  duration: 2.0\n")
    err = error_of(path)
    assert str(err).startswith(f"{path}:18:1: simulation: duplicate key (first at line 1)")


def test_exponent_without_dot_is_a_number(tmp_path) -> None:
    """`physics_rate: 1e4` (YAML 1.1 reads a string) is 10000.0, as in YAML 1.2."""
    path = write(tmp_path, MINIMAL.replace("physics_rate: 1000.0", "physics_rate: 1e4"))
    assert load_formation(path).simulation.physics_rate == 10000.0


def test_negative_seed_is_an_error(tmp_path) -> None:
    """`simulation.seed: -1` (once accepted, then a crash in numpy) is refused at its line."""
    path = write(tmp_path, MINIMAL.replace("  duration: 1.0\n", "  duration: 1.0\n  seed: -1\n"))
    assert str(error_of(path)) == f"{path}:3:3: simulation.seed: -1 must be >= 0"


@pytest.mark.parametrize(
    ("matrix", "why"),
    [
        ("[[1, 0, 0], [0, 1, 0], [0, 0, -1]]", "det = -1.0000 <= 0"),
        ("[[0, 0, 0], [0, 0, 0], [0, 0, 0]]", "det = 0.0000 <= 0"),
        ("[[2, 0, 0], [0, 1, 0], [0, 0, 1]]", "‖RᵀR − I‖_F = 3 > 0.5"),
    ],
)
def test_project_refuses_what_is_not_close_to_a_rotation(tmp_path, matrix, why) -> None:
    """`project: true` projects only ‖RᵀR − I‖_F ≤ 0.5 with det > 0 (the paper's R_2(0) is 0.37 off)."""
    text = MINIMAL.replace(
        "    position: [2, 0, 0]\n", f"    position: [2, 0, 0]\n    orientation: {{matrix: {matrix}, project: true}}\n"
    )
    path = write(tmp_path, text)
    err = error_of(path)
    assert (
        str(err)
        == f"{path}:15:19: agents[1].orientation.matrix: is too far from a rotation to project ({why}): give a rotation"
    )


def test_reflection_without_project_does_not_suggest_it(tmp_path) -> None:
    text = MINIMAL.replace(
        "    position: [2, 0, 0]\n",
        "    position: [2, 0, 0]\n    orientation: {matrix: [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}\n",
    )
    err = str(error_of(write(tmp_path, text)))
    assert "is not a rotation" in err and "project" not in err


def test_paper_preset_still_projects(paper_path) -> None:
    assert load_formation(paper_path).agents[1].R_world_body.shape == (3, 3)


def test_error_in_defaults_points_at_the_defaults(tmp_path) -> None:
    """A typo in defaults.agent.controller: reported once, at the defaults' line, with the nearest key."""
    text = MINIMAL.replace("agents:\n", "defaults:\n  agent:\n    controller: {gama: 3.0}\nagents:\n")
    path = write(tmp_path, text)
    err = error_of(path)
    assert str(err).startswith(f"{path}:7:18: defaults.agent.controller.gama: unknown key (did you mean 'gamma'?)")
    assert not isinstance(err, CollectedFormationSpecError)  # not once more per agent


def test_bad_value_in_defaults_points_at_the_defaults(tmp_path) -> None:
    text = MINIMAL.replace("agents:\n", "defaults:\n  agent:\n    radius: -1\nagents:\n").replace(
        "    radius: 0.5\n", ""
    )
    path = write(tmp_path, text)
    assert str(error_of(path)) == f"{path}:7:5: defaults.agent.radius: -1 must be > 0"


THIRD_AGENT = """\
  - id: c
    radius: 0.5
    sensing_radius: 3.0
    position: [0, 2, 0]
    dynamics: {mass: 1.0, inertia: [0.1, 0.1, 0.1]}
edges:
  - {tail: a, head: b, distance: 1.5}
  - {tail: a, head: c, distance: 1.5}
"""


def test_constraint_broken_through_defaults_names_every_edge(tmp_path) -> None:
    """defaults.edge.d_con above the agents' sensing radius: at the default, and each edge it breaks with its line."""
    text = MINIMAL.replace("agents:\n", "defaults:\n  edge:\n    d_con: 4\nagents:\n")
    text = text.replace("edges:\n  - {tail: a, head: b, distance: 1.5}\n", THIRD_AGENT)
    path = write(tmp_path, text)
    assert str(error_of(path)) == (
        f"{path}:7:5: defaults.edge.d_con: 4 exceeds the sensing radius 3 of its agents: the edge would be lost "
        f"inside its funnel; broken by edges[0] (a, b) at {path}:25:5, edges[1] (a, c) at {path}:26:5"
    )


def test_orientation_funnel_from_defaults_names_the_edge(tmp_path) -> None:
    """defaults.edge.orientation_funnel.rho_0 below ψ(0) of one edge: that edge (and only it) is named."""
    text = MINIMAL.replace("agents:\n", "defaults:\n  edge:\n    orientation_funnel: {rho_0: 1.99}\nagents:\n")
    text = text.replace("edges:\n  - {tail: a, head: b, distance: 1.5}\n", THIRD_AGENT)
    text = text.replace(
        "    position: [2, 0, 0]\n", "    position: [2, 0, 0]\n    orientation: {rpy: [0, 0, 3.0992]}\n"
    )
    path = write(tmp_path, text)
    assert str(error_of(path)) == (
        f"{path}:7:26: defaults.edge.orientation_funnel.rho_0: 1.99 must exceed the initial orientation error "
        f"psi(0)=1.9991; broken by edges[0] (a, b) at {path}:26:5"
    )


def test_agent_constraint_broken_through_defaults_names_the_agent(tmp_path) -> None:
    """defaults.agent.controller.max_force above agent b's actuators only: agent b is named with its line."""
    text = MINIMAL.replace("agents:\n", "defaults:\n  agent:\n    controller: {max_force: 30}\nagents:\n")
    text = text.replace("inertia: [0.1, 0.1, 0.1]}\nedges", "inertia: [0.1, 0.1, 0.1], max_force: 20}\nedges")
    path = write(tmp_path, text)
    assert str(error_of(path)) == (
        f"{path}:7:18: defaults.agent.controller.max_force: 30 exceeds the actuators' dynamics.max_force 20: "
        f"the simulator would refuse it; broken by agents[1] (id b) at {path}:14:5"
    )


def test_unknown_key_gets_the_nearest_valid_key(tmp_path) -> None:
    path = write(tmp_path, MINIMAL.replace("  control_rate:", "  contol_rate:"))
    err = error_of(path)
    assert any(
        str(e).startswith(f"{path}:4:3: simulation.contol_rate: unknown key (did you mean 'control_rate'?)")
        for e in getattr(err, "errors", [err])
    )


def test_every_error_is_reported_up_to_a_cap(tmp_path) -> None:
    """Three independent mistakes: three lines, in file order, each with its position."""
    text = (
        MINIMAL.replace("  duration: 1.0", "  duration: -1")
        .replace("    radius: 0.5\n", "    radius: zero\n", 1)
        .replace("distance: 1.5", "distance: far")
    )
    path = write(tmp_path, text)
    err = error_of(path)
    lines = str(err).splitlines()
    assert len(lines) == 3, lines
    assert lines[0] == f"{path}:2:3: simulation.duration: -1 must be > 0"
    assert lines[1] == f"{path}:7:5: agents[0].radius: expected a number, got str 'zero'"
    assert lines[2] == f"{path}:17:24: edges[0].distance: expected a number, got str 'far'"
    many = MINIMAL.replace("edges:\n", "".join(f"  - {{id: x{k}}}\n" for k in range(30)) + "edges:\n")
    lines = str(error_of(write(tmp_path, many, "many.yaml"))).splitlines()
    assert len(lines) == 21 and re.fullmatch(r"… and \d+ more errors", lines[-1])


#: Four mistakes of four kinds: a duplicate key (YAML), an unknown key (schema), a matrix that is not
#: a rotation and a desired distance at d_con (semantic checks).
FOUR_MISTAKES = (
    MINIMAL.replace("  duration: 1.0\n", "  duration: 1.0\n  duration: 500.0\n")
    .replace("    position: [0, 0, 0]\n", "    position: [0, 0, 0]\n    controller: {gama: 3.0}\n")
    .replace(
        "    position: [2, 0, 0]\n",
        "    position: [2, 0, 0]\n    orientation: {matrix: [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}\n",
    )
    .replace("distance: 1.5", "distance: 3.0")
)


def four_mistakes_lines(path: Path) -> list[str]:
    """The four errors of FOUR_MISTAKES written at ``path``, in file order, as printed."""
    return [
        f"{path}:3:3: simulation.duration: duplicate key (first at line 2); YAML would silently keep the last one",
        f"{path}:11:18: agents[0].controller.gama: unknown key (did you mean 'gamma'?) (expected one of: delta, "
        "gamma, max_force, max_torque, measurement_timeout, saturation_margin, velocity_funnel)",
        f"{path}:17:19: agents[1].orientation.matrix: is not a rotation (‖RᵀR − I‖_F = 0, det = -1.0000)",
        f"{path}:20:24: edges[0].distance: 3.0 is not inside (d_col=1.0, d_con=3.0)",
    ]


def test_four_kinds_of_mistake_in_one_load(tmp_path) -> None:
    """YAML, schema and semantic errors of one file come from one load, each at its line, in file order."""
    path = write(tmp_path, FOUR_MISTAKES)
    assert str(error_of(path)).splitlines() == four_mistakes_lines(path)


def test_errors_are_in_file_order(tmp_path) -> None:
    """Edges written before the agents: the edge's error comes first, as in the file."""
    agents, edges = MINIMAL.split("edges:\n")
    text = "edges:\n" + edges.replace("distance: 1.5", "distance: 3.0") + agents.replace("mass: 1.0", "mass: -1", 1)
    path = write(tmp_path, text)
    assert str(error_of(path)).splitlines() == [
        f"{path}:2:24: edges[0].distance: 3.0 is not inside (d_col=1.0, d_con=3.0)",
        f"{path}:12:16: agents[0].dynamics.mass: -1 must be > 0",
    ]


def test_duplicate_keys_collected_keep_the_first_value() -> None:
    """collect_duplicates: each duplicate is listed, the first value kept (the one whose line is indexed)."""
    raw = b"a: 1\nb: {c: 2, c: 3}\na: 4\n"
    document = loader.parse_document(raw, "t.yaml", collect_duplicates=True)
    assert document.data == {"a": 1, "b": {"c": 2}}
    assert [str(e) for e in document.errors] == [
        "t.yaml:2:11: b.c: duplicate key (first at line 2); YAML would silently keep the last one",
        "t.yaml:3:1: a: duplicate key (first at line 1); YAML would silently keep the last one",
    ]
    assert document.location("a") == "t.yaml:1:1"
    with pytest.raises(CollectedFormationSpecError) as info:  # without it, the duplicates are raised
        loader.parse_document(raw, "t.yaml")
    assert [e.path for e in info.value.errors] == ["b.c", "a"]


def test_values_in_messages_are_shortened(tmp_path) -> None:
    """A 10 000-element list where a number belongs: the message stays short."""
    text = MINIMAL.replace("  duration: 1.0", "  duration: [" + ", ".join(["1"] * 10_000) + "]")
    err = str(error_of(write(tmp_path, text)))
    assert len(err) < 200 and "..." in err


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "the file is empty"),
        ("- 1\n- 2\n", "a formation file is a mapping at the top level, got list"),
        ("agents: [\n", "not valid YAML"),
        ("a: b\n\tc: d\n", "not valid YAML"),
    ],
)
def test_not_a_formation_at_all(tmp_path, text, expected) -> None:
    path = write(tmp_path, text)
    err = str(error_of(path))
    assert err.startswith(f"{path}") and expected in err


def test_directory_and_oversized_file(tmp_path) -> None:
    assert "is a directory" in str(error_of(tmp_path))
    big = write(tmp_path, b"#" * (loader.MAX_BYTES + 1), "big.yaml")
    assert "more than any formation file" in str(error_of(big))
    huge = tmp_path / "huge.yaml"
    with huge.open("wb") as fh:  # sparse: 100 MB on paper, nothing on disk
        fh.truncate(100_000_000)
    assert f"{huge}: 100000000 bytes is more than any formation file" in str(error_of(huge))  # its real size


@pytest.mark.parametrize(
    "case",
    ["binary", "bomb", "duplicate", "seed", "reflection", "defaults"],
)
@pytest.mark.parametrize("script", ["formation-check", "formation-headless"])
def test_commands_exit_2_without_traceback(tmp_path, case, script) -> None:
    """Every class of bad file: exit 2, FILE:LINE:COL on stderr, no traceback, nothing written."""
    texts = {
        "binary": b"\x89PNG\r\n\x1a\n\x00",
        "bomb": billion_laughs().encode(),
        "duplicate": MINIMAL.replace("  duration: 1.0\n", "  duration: 1.0\n  duration: 500.0\n").encode(),
        "seed": MINIMAL.replace("  duration: 1.0\n", "  duration: 1.0\n  seed: -1\n").encode(),
        "reflection": MINIMAL.replace(
            "    position: [2, 0, 0]\n",
            "    position: [2, 0, 0]\n    orientation: {matrix: [[1, 0, 0], [0, 1, 0], [0, 0, -1]], project: true}\n",
        ).encode(),
        "defaults": MINIMAL.replace(
            "agents:\n", "defaults:\n  agent:\n    controller: {gama: 3.0}\nagents:\n"
        ).encode(),
    }
    path = write(tmp_path, texts[case])
    out = [] if script == "formation-check" else ["--out", str(tmp_path / "out")]
    started = time.monotonic()
    r = subprocess.run([executable(script), str(path), *out], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr + r.stdout
    assert re.search(rf"{re.escape(str(path))}:\d+:\d+: ", r.stderr), r.stderr
    assert not (tmp_path / "out").exists()
    assert time.monotonic() - started < 30


def test_yaml_loader_does_not_change_pyyaml_for_others() -> None:
    """The 1e4 resolver is on the loader's own copy: yaml.safe_load still reads YAML 1.1."""
    assert yaml.safe_load("x: 1e4") == {"x": "1e4"}
    assert loader.parse_document(b"x: 1e4\n", "t").data == {"x": 10000.0}
