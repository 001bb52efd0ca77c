"""What a host holds in realtime: message counts, the CPU model, the calibration file, formation-check --realtime."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from formation_core.errors import CalibrationError
from formation_core.spec import formation_from_dict
from formation_sim import capacity
from formation_sim.cli import check
from formation_sim.cli.generate import generate

# pytest.approx's default (relative 1e-6) checks sums and products of a few stated costs against their
# closed form: rounding is some 1e-16 of them, a wrong count of messages off by a whole message.

#: message costs stated for the formula checks, no work terms: every figure is messages × cost
STATED = replace(
    capacity.DEFAULT_COSTS,
    sim_message_s=40e-6,
    agent_message_s=100e-6,
    sim_tick_s=0.0,
    sim_second_per_agent_s=0.0,
    agent_second_s=0.0,
    bag_write_s=0.0,
    source="stated",
)


def _doc(n: int, rate: float, topology: str = "chain") -> dict:
    return generate(n, topology=topology, seed=3, control_rate=rate, duration=2.0, preset="realtime")


def _spec(n: int, rate: float, topology: str = "chain"):
    return formation_from_dict(_doc(n, rate, topology))


def _file(tmp_path: Path, n: int, rate: float, topology: str = "chain") -> Path:
    path = tmp_path / f"{topology}_{n}_{rate:g}.yaml"
    path.write_text(yaml.safe_dump(_doc(n, rate, topology)))
    return path


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch) -> None:
    """No calibration of the user's: the cache directory is the test's own (empty) one."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def test_message_counts_of_a_chain_at_100_hz() -> None:
    """Chain of 5 at 100 Hz, recording: the simulator 13 + /clock 0.1 + ground truth 1 + display 0.9 + 5 taken."""
    spec = _spec(5, 100.0)
    assert spec.simulation.record_rate == 100.0  # the realtime preset records every tick
    sim, agents = capacity.message_counts(spec, record=True)
    assert sim == pytest.approx(13 + 0.1 + 1.0 + 0.9 + 5)
    # ends: 1 pose + velocity + /clock + wrench; inner agents one pose more
    assert sorted(agents.values()) == pytest.approx([3.1, 3.1, 4.1, 4.1, 4.1])
    sim_no_record, _ = capacity.message_counts(spec, record=False)
    assert sim_no_record == pytest.approx(sim)  # record rate = control rate: ground truth every tick anyway


def test_prediction_is_the_formula_for_stated_costs() -> None:
    """40 µs per simulator message, 100 µs per agent message, no work: 0.80 ms and 0.31/0.41 ms per tick."""
    p = capacity.predict(_spec(5, 100.0), STATED, record=True)
    assert p.sim_cpu_s == pytest.approx(40e-6 * 20.0)
    assert sorted(p.agent_cpu_s.values()) == pytest.approx([310e-6, 310e-6, 410e-6, 410e-6, 410e-6])
    assert p.total_cpu_s == pytest.approx(0.8e-3 + 2 * 0.31e-3 + 3 * 0.41e-3)
    assert p.busy_cores == pytest.approx(p.total_cpu_s * 100.0)
    assert p.cores_needed == 1 and p.simulator_fits  # 0.265 busy cores / 0.5 -> 1


def test_prediction_grows_with_agents_and_rate() -> None:
    """More agents: more CPU per tick; a higher rate: more busy cores (the defaults and the stated costs)."""
    for costs in (STATED, capacity.DEFAULT_COSTS):
        by_n = [capacity.predict(_spec(n, 50.0, "random"), costs) for n in (5, 10, 20)]
        assert by_n[0].sim_cpu_s < by_n[1].sim_cpu_s < by_n[2].sim_cpu_s
        assert by_n[0].total_cpu_s < by_n[1].total_cpu_s < by_n[2].total_cpu_s
        by_rate = [capacity.predict(_spec(10, f, "random"), costs) for f in (25.0, 50.0, 100.0)]
        assert by_rate[0].busy_cores < by_rate[1].busy_cores < by_rate[2].busy_cores
        assert by_rate[0].cores_needed <= by_rate[1].cores_needed <= by_rate[2].cores_needed


def test_defaults_reproduce_the_floor_figures_they_come_from() -> None:
    """The default message costs give the quoted floor figures back within 5 % (they are their means)."""
    c = capacity.DEFAULT_COSTS
    # 20 agents at 100 Hz: simulator 58.1 published + 20 taken, 3.0 ms; agent 4.0 messages, 0.49 ms
    assert c.sim_message_s * 78.1 == pytest.approx(3.0e-3, rel=0.05)
    assert c.agent_message_s * 4.0 == pytest.approx(0.49e-3, rel=0.05)
    # 50 agents at 50 Hz: simulator 148.1 + 50 taken, 7.95 ms; agent 4.06 messages, 0.54 ms
    assert c.sim_message_s * 198.1 == pytest.approx(7.95e-3, rel=0.05)
    assert c.agent_message_s * 4.06 == pytest.approx(0.54e-3, rel=0.05)


def test_a_star_centre_is_the_busiest_agent() -> None:
    """The centre of a star of 8 takes 7 poses: it costs more than a leaf."""
    p = capacity.predict(_spec(8, 50.0, "star"), STATED)
    centre = max(p.agent_messages, key=p.agent_messages.__getitem__)
    assert p.agent_messages[centre] == pytest.approx(7 + 1 + 0.2 + 1)  # /clock at 10 Hz of 50
    assert p.agent_cpu_s[centre] == pytest.approx(100e-6 * 9.2)


def test_calibration_file_round_trip_and_refusals(tmp_path) -> None:
    """A stored calibration is used on its host, ignored on another, refused with the key named if bad."""
    path = tmp_path / "capacity.json"
    capacity.save_calibration(50e-6, 150e-6, {"floor": "test"}, path)
    doc = json.loads(path.read_text())
    assert {"host", "cpu_count", "date"} <= doc.keys()
    costs = capacity.load_costs(path)
    assert (costs.sim_message_s, costs.agent_message_s) == (50e-6, 150e-6)
    assert costs.source.startswith("calibrated on ")
    # the other terms scale with the message costs: the simulator's by 50/39, an agent's by 150/128
    d = capacity.DEFAULT_COSTS
    assert costs.sim_second_per_agent_s == pytest.approx(d.sim_second_per_agent_s * 50 / 39)
    assert costs.agent_second_s == pytest.approx(d.agent_second_s * 150 / 128)
    path.write_text(json.dumps(dict(doc, host="another-host")))
    assert capacity.load_costs(path).sim_message_s == capacity.DEFAULT_COSTS.sim_message_s
    path.write_text(json.dumps(dict(doc, agent_message_s=-1.0)))
    with pytest.raises(CalibrationError, match=r"agent_message_s = -1\.0"):
        capacity.load_costs(path)
    assert capacity.load_costs(tmp_path / "none.json") is capacity.DEFAULT_COSTS


def test_check_realtime_small_formation_exits_0(tmp_path, monkeypatch, capsys) -> None:
    """5 agents at 50 Hz fit two cores: exit 0, the prediction lines, built-in costs named."""
    monkeypatch.setattr(capacity, "available_cores", lambda: 2)
    path = _file(tmp_path, 5, 50.0)
    assert check.main([str(path), "--realtime"]) == 0
    out = capsys.readouterr().out
    p = capacity.predict(_spec(5, 50.0), capacity.DEFAULT_COSTS)
    assert "realtime capacity at 50 Hz (20 ms per tick), recording; costs: built-in defaults" in out
    assert f"CPU per tick: simulator {p.sim_cpu_s * 1e3:.2f} ms" in out
    assert f"{p.cores_needed} needed to keep ticks on time (at most 50% of each); this host has 2" in out
    assert "VALID" in out


def test_check_realtime_too_big_for_the_host_exits_1(tmp_path, monkeypatch, capsys) -> None:
    """50 agents at 100 Hz need more than two cores: exit 1 (valid but unsafe), the reason names both counts."""
    monkeypatch.setattr(capacity, "available_cores", lambda: 2)
    path = _file(tmp_path, 50, 100.0, "random")
    p = capacity.predict(_spec(50, 100.0, "random"), capacity.DEFAULT_COSTS)
    assert p.cores_needed > 2
    assert check.main([str(path), "--realtime", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"realtime: needs {p.cores_needed} cores to keep ticks on time, this host has 2" in err
    assert check.main([str(path), "--quiet"]) == 0  # without --realtime: only the file's own checks


def test_check_realtime_uses_the_calibration(tmp_path, monkeypatch, capsys) -> None:
    """With a calibration of this host in XDG_CACHE_HOME the prediction says so and uses its costs."""
    monkeypatch.setattr(capacity, "available_cores", lambda: 64)
    capacity.save_calibration(60e-6, 140e-6, {}, capacity.calibration_path())
    path = _file(tmp_path, 5, 50.0)
    assert check.main([str(path), "--realtime", "--no-record"]) == 0
    out = capsys.readouterr().out
    assert "not recording; costs: calibrated on " in out
    p = capacity.predict(_spec(5, 50.0), capacity.load_costs(), record=False)
    assert f"CPU per tick: simulator {p.sim_cpu_s * 1e3:.2f} ms" in out


def test_check_realtime_bad_calibration_is_invalid(tmp_path, capsys) -> None:
    """An unreadable calibration file: exit 2 naming the file."""
    cal = capacity.calibration_path()
    cal.parent.mkdir(parents=True)
    cal.write_text("{not json")
    assert check.main([str(_file(tmp_path, 5, 50.0)), "--realtime"]) == 2
    assert f"calibration {cal}: unreadable" in capsys.readouterr().err
