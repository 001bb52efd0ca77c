"""The Newton-Euler plant, its RKMK4 integrator, the signal models and the measurements."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from formation_core.formation import SignalModel, simulator_view
from formation_core.rotations import orthonormality_error
from formation_core.spec import formation_from_dict, load_formation
from formation_sim.core.disturbances import signal_params, signals_at
from formation_sim.core.measurement import MeasurementModel
from formation_sim.core.plant import Plant, PlantState
from formation_sim.core.simulation import Measurements

pytestmark = pytest.mark.numeric


def tumbling_body(gravity=(0.0, 0.0, 0.0)):
    """Two agents (the plant needs a formation); agent a has an asymmetric inertia."""
    agent = {"radius": 0.5, "sensing_radius": 5.0}
    doc = {
        "simulation": {"gravity": list(gravity)},
        "agents": [
            {
                "id": "a",
                "position": [0, 0, 0],
                "angular_velocity": [3.0, 0.2, -1.0],
                "linear_velocity": [1, 0, 0],
                "dynamics": {"mass": 2.0, "inertia": [0.1, 0.2, 0.3]},
                **agent,
            },
            {"id": "b", "position": [2, 0, 0], "dynamics": {"mass": 1.0, "inertia": [0.1, 0.1, 0.1]}, **agent},
        ],
        "edges": [{"tail": "a", "head": "b", "distance": 1.5}],
    }
    view = simulator_view(formation_from_dict(doc))
    plant = Plant(view)
    return plant, plant.initial_state(view)


def integrate(plant: Plant, s: PlantState, u: np.ndarray, h: float, T: float) -> PlantState:
    for k in range(round(T / h)):
        s = plant.step(k * h, s, u, h)
    return s


def test_rotation_stays_in_so3() -> None:
    """Fast tumbling for 5 000 steps: ‖RᵀR − I‖_F stays within rounding (the Lie-group step keeps R on
    SO(3); an integrator of R's entries would leave it by its truncation error, some 1e-8 here)."""
    plant, s = tumbling_body()
    steps = 5000
    s = integrate(plant, s, np.zeros((2, 6)), 1e-3, 5.0)
    # each step multiplies R by exp(hΩ) (orthonormal to some 6u) in 3-term sums (some 6u more): even if every
    # step's rounding went the same way, 12u per step; 2e-14 is measured here
    assert orthonormality_error(s.R) < steps * 12 * 2.0**-53


def test_torque_free_body_conserves_energy_and_momentum() -> None:
    """No input: kinetic energy and world angular momentum R J ω are conserved (to 1e-9)."""
    plant, s0 = tumbling_body()
    s = integrate(plant, s0, np.zeros((2, 6)), 1e-3, 2.0)
    J = plant.inertia[0]

    def energy(st):
        w = st.v[0, 3:]
        return 0.5 * w @ J @ w + 0.5 * plant.mass[0] * st.v[0, :3] @ st.v[0, :3]

    # RK4's truncation over 5 s at h = 1e-3 (not a rounding: platform independent)
    assert energy(s) == pytest.approx(energy(s0), rel=1e-9)
    np.testing.assert_allclose(s.R[0] @ J @ s.v[0, 3:], s0.R[0] @ J @ s0.v[0, 3:], atol=1e-9)
    # free translation: the world velocity R v_L is constant
    np.testing.assert_allclose(s.R[0] @ s.v[0, :3], s0.R[0] @ s0.v[0, :3], atol=1e-9)


def test_integrator_converges_at_fourth_order() -> None:
    """Halving the step divides the error by about 16 (RKMK4), with input and coupling."""
    plant, s0 = tumbling_body()
    u = np.array([[0.5, -0.2, 0.1, 0.05, -0.02, 0.03], [0, 0, 0, 0, 0, 0]])
    ref = integrate(plant, s0, u, 5e-4, 1.0)
    errs = []
    for h in (2e-2, 1e-2, 5e-3):
        s = integrate(plant, s0, u, h, 1.0)
        errs.append(np.abs(s.R - ref.R).max() + np.abs(s.p - ref.p).max() + np.abs(s.v - ref.v).max())
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert all(12 < r < 20 for r in ratios), ratios


def test_gravity_free_fall() -> None:
    """gravity [0, 0, −9.81]: p_z = −½ g t² for a body at rest (RK4 is exact for this)."""
    plant, s = tumbling_body(gravity=(0, 0, -9.81))
    s.v[:] = 0.0
    s = integrate(plant, s, np.zeros((2, 6)), 1e-3, 1.0)
    # RK4 is exact for a quadratic: only 1000 steps' roundings of |p| ≤ 5 (ulp 8.9e-16), < 1e-12 even if
    # they all went one way
    np.testing.assert_allclose(s.p[:, 2], -0.5 * 9.81, atol=1e-12)
    np.testing.assert_allclose(s.p[1, :2], [2, 0], atol=1e-12)


def test_paper_disturbance_is_the_printed_formula(paper_path: Path) -> None:
    """w_i = A sin(‖p_1‖₁ tr(R_i) ω t + φ) v_i with the first agent's position (literal reading)."""
    spec = load_formation(paper_path)
    view = simulator_view(spec)
    plant = Plant(view)
    s = plant.initial_state(view)
    s.p[0] = [0.5, -1.0, 2.0]
    rng = np.random.default_rng(1)
    s.v[:] = rng.normal(size=s.v.shape)
    t = 1.7
    w = plant.disturbance(t, s)
    for i, a in enumerate(spec.agents):
        prm = a.dynamics.disturbance.params
        gain = prm["amplitude"] * np.sin(3.5 * np.trace(s.R[i]) * prm["frequency"] * t + prm["phase"])
        # the same formula in the same order; only sin may differ (libm in the kernel, numpy's SIMD path
        # here: a few ulps at an argument whose sine is not small)
        np.testing.assert_allclose(w[i], gain * s.v[i], rtol=1e-14)


def test_random_signal_is_seeded_and_bounded() -> None:
    models = [SignalModel("random", {"bound": (0.3,) * 6, "max_frequency": 2.0, "components": 4})] * 3
    a = signal_params(models, np.random.default_rng(9))
    b = signal_params(models, np.random.default_rng(9))
    z = np.zeros((3, 3))
    R = np.tile(np.eye(3), (3, 1, 1))
    ts = np.linspace(0, 20, 2001)
    va = np.array([signals_at(a, t, z, R, np.zeros((3, 6))) for t in ts])
    vb = np.array([signals_at(b, t, z, R, np.zeros((3, 6))) for t in ts])
    np.testing.assert_array_equal(va, vb)
    assert np.abs(va).max() <= 0.3 + 1e-12  # components scaled to sum to the bound: a few roundings of 0.3
    assert np.abs(va).max() > 0.1


def test_measurements_respect_the_sensing_radius(paper_path: Path) -> None:
    """A neighbour beyond agent i's sensing radius is not measured; the rest are R_iᵀ(p_j − p_i)."""
    spec = load_formation(paper_path)
    view = simulator_view(spec)
    model = MeasurementModel(view, np.random.default_rng(0))
    p = np.array([a.position for a in spec.agents])
    R = np.array([a.R_world_body for a in spec.agents])

    def measure() -> dict:  # by agent and neighbour, the ends in range
        return Measurements(0.0, 0, 0, *model.measure(p, R), np.zeros((len(p), 6)), model.ends).relative_poses

    meas = measure()
    assert set(meas["3"]) == {"1", "4", "5"}
    unit = 2.0**-53
    # two computations of 3-term sums of products, in any order (γ₃ each), after one rounded difference
    bound = 2 * 3 * unit / (1 - 3 * unit) * (np.abs(R[1]).T @ np.abs(p[0] - p[1])) + unit * np.abs(R[1]).T @ (
        np.abs(p[0]) + np.abs(p[1])
    )
    assert np.all(np.abs(meas["2"]["1"][0] - R[1].T @ (p[0] - p[1])) <= bound)
    # the rotation also goes through the published quaternion and back (a square root and about ten
    # roundings of entries ≤ 1 each way): within 32 ulp(1)
    np.testing.assert_allclose(meas["2"]["1"][1], R[1].T @ R[0], atol=32 * 2.0**-52)
    p[3] = p[2] + [4.5, 0, 0]  # agent 4 leaves the 4 m sensing radius of agent 3
    meas = measure()
    assert set(meas["3"]) == {"1", "5"} and "3" not in meas["4"]


def test_plant_saturates_the_actuators() -> None:
    """A 1e8 N / 1e8 N·m command is applied at the actuator limits (100 N, 100 N·m), direction kept."""
    plant, s = tumbling_body()
    u = np.zeros((2, 6))
    u[0] = [1e8, 0.0, 0.0, 0.0, 0.0, -1e8]
    applied = plant.saturate(u)
    assert applied[0] == pytest.approx([100.0, 0, 0, 0, 0, -100.0], abs=1e-12)  # 100·(x/‖x‖): ulp(100) = 1.4e-14
    assert applied[1] == pytest.approx(np.zeros(6), abs=0.0)
    # the integrator applies the same: one step with 1e8 N equals one step with 100 N
    s_big = plant.step(0.0, s, u, 1e-3)
    s_lim = plant.step(0.0, s, applied, 1e-3)
    assert np.array_equal(s_big.v, s_lim.v) and np.array_equal(s_big.p, s_lim.p)


def test_plant_leaves_a_wrench_within_limits_untouched() -> None:
    """Below the limits the applied wrench is bit-identical (the presets never saturate)."""
    plant, _ = tumbling_body()
    u = [[3.0, -4.0, 0.5, 0.1, 0.2, 0.3], [0.0] * 6]
    assert np.array_equal(plant.saturate(np.array(u)), u)
