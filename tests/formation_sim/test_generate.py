"""formation-generate writes valid, reproducible trees of the asked shape."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from formation_core.spec import formation_from_dict, load_formation
from formation_sim.cli import generate


@pytest.mark.parametrize("topology", ["chain", "star", "random"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_generated_formations_are_valid_trees(topology: str, seed: int) -> None:
    doc = generate.generate(12, topology=topology, seed=seed)
    spec = formation_from_dict(doc)
    assert len(spec.agents) == 12 and len(spec.edges) == 11
    tails = [e.tail for e in spec.edges]
    if topology == "chain":
        assert [(e.tail, e.head) for e in spec.edges] == [(str(i), str(i + 1)) for i in range(1, 12)]
    if topology == "star":
        assert set(tails) == {"1"}
    p = np.array([a.position for a in spec.agents])
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(12) * 10
    assert d.min() > 1.0  # no two bodies (radius 0.5) overlap


def test_same_seed_same_file(tmp_path) -> None:
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    assert generate.main(["6", "--seed", "4", "--out", str(a)]) == 0
    assert generate.main(["6", "--seed", "4", "--out", str(b)]) == 0
    assert a.read_text() == b.read_text()
    assert generate.main(["6", "--seed", "4", "--out", str(a)]) == 2  # refuses to overwrite
    spec = load_formation(a)
    assert spec.simulation.seed == 4


def test_bad_arguments_exit_2(capsys) -> None:
    assert generate.main(["1"]) == 2
    assert "at least 2" in capsys.readouterr().err


def test_presets_match_their_generator(paper_path) -> None:
    """config/random_20agents.yaml and chain_8agents_gravity.yaml are the generator's output."""
    config = paper_path.parent
    cases = {
        "random_20agents.yaml": dict(n_agents=20, seed=3, name="random_20agents"),
        "chain_8agents_gravity.yaml": dict(
            n_agents=8, topology="chain", gravity=9.81, seed=1, name="chain_8agents_gravity"
        ),
        "realtime_20agents_100hz.yaml": dict(
            n_agents=20, seed=1, control_rate=100.0, duration=10.0, name="realtime_20agents_100hz", preset="realtime"
        ),
        "realtime_50agents_50hz.yaml": dict(
            n_agents=50, seed=1, control_rate=50.0, duration=10.0, name="realtime_50agents_50hz", preset="realtime"
        ),
    }
    for file, kwargs in cases.items():
        assert yaml.safe_load((config / file).read_text()) == generate.generate(**kwargs), file


@pytest.mark.parametrize(("n", "rate"), [(6, 100.0), (12, 50.0), (8, 20.0)])
def test_realtime_preset_needs_a_fraction_of_its_rate(n: int, rate: float) -> None:
    """--preset realtime: realtime mode at the asked rate, every agent's rate need over the run
    at most rate / REALTIME_MARGIN (γ chosen from the need; 1e-9 relative for the rounding of γ)."""
    from formation_sim.core.loop import initial_rho_v0
    from formation_sim.core.rates import rate_needs

    spec = formation_from_dict(generate.generate(n, seed=n, control_rate=rate, duration=10.0, preset="realtime"))
    s = spec.simulation
    assert (s.mode, s.control_rate, s.physics_rate, s.record_rate) == ("realtime", rate, rate, rate)
    needs = rate_needs(spec, initial_rho_v0(spec))
    assert len(needs) == n
    worst = max(r.at_end for r in needs)
    assert worst <= rate / generate.REALTIME_MARGIN * (1 + 1e-9)
    assert worst >= rate / generate.REALTIME_MARGIN / 2  # γ is not needlessly small


def test_realtime_preset_from_the_command_line(tmp_path) -> None:
    out = tmp_path / "rt.yaml"
    assert generate.main(["5", "--preset", "realtime", "--control-rate", "50", "--out", str(out)]) == 0
    spec = load_formation(out)
    assert (spec.simulation.mode, spec.simulation.control_rate, spec.simulation.duration) == ("realtime", 50.0, 10.0)
    with pytest.raises(ValueError, match="preset: 'fast'"):
        generate.generate(5, preset="fast")
