"""The per-agent controller against the paper's equations, from local measurements only."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formation_agent.controller import ERROR, OK, AgentController, MissingMeasurementError
from formation_agent.roundoff import BoundedController
from formation_core.formation import FormationSpec, agent_view
from formation_core.rotations import vee
from formation_core.so3 import exp_so3
from formation_core.spec import load_formation

pytestmark = pytest.mark.numeric

RNG = np.random.default_rng(5)


@pytest.fixture
def spec(paper_path: Path) -> FormationSpec:
    return load_formation(paper_path)


def exp_rows(theta: np.ndarray) -> np.ndarray:
    """exp_so3 of every row of (n, 3) rotation vectors."""
    return np.array([exp_so3(row) for row in theta])


def world(spec: FormationSpec) -> tuple[np.ndarray, np.ndarray]:
    return np.array([a.position for a in spec.agents]), np.array([a.R_world_body for a in spec.agents])


def measurements(spec: FormationSpec, p: np.ndarray, R: np.ndarray, agent: str) -> dict:
    """Noise-free relative poses agent ``agent`` receives: (R_iᵀ(p_j − p_i), R_iᵀR_j)."""
    idx = {a.id: a.index for a in spec.agents}
    i = idx[agent]
    return {
        ie.neighbour: (R[i].T @ (p[idx[ie.neighbour]] - p[i]), R[i].T @ R[idx[ie.neighbour]])
        for ie in agent_view(spec, agent).edges
    }


def edge_errors(spec, p, R):
    idx = {a.id: a.index for a in spec.agents}
    out = []
    for e in spec.edges:
        t, h = idx[e.tail], idx[e.head]
        d = p[h] - p[t]
        A = R[t].T @ R[h] @ e.R_des
        out.append((d @ d - e.d_des**2, 0.5 * np.trace(np.eye(3) - e.R_des.T @ R[h].T @ R[t]), vee(A - A.T)))
    return out


def test_tail_and_head_agree_on_every_edge(spec) -> None:
    """The sign convention: both ends of an edge compute the same e_k and ψ_k from their own view."""
    p, R = world(spec)
    outs = {
        a.id: AgentController(agent_view(spec, a.id)).compute(0.3, measurements(spec, p, R, a.id), np.zeros(6))
        for a in spec.agents
    }
    truth = edge_errors(spec, p, R)
    for k, e in enumerate(spec.edges):
        for agent in (e.tail, e.head):
            slot = [ie.edge.index for ie in agent_view(spec, agent).edges].index(k)
            # q and Q from the same p, R by other 3-term sums (any order): e = ‖q‖² − d² of lengths ≤ 10 m
            # carries some 1e-14, ψ (entries ≤ 1) some 1e-15
            assert outs[agent].e[slot] == pytest.approx(truth[k][0], abs=1e-12)
            assert outs[agent].psi[slot] == pytest.approx(truth[k][1], abs=1e-12)


def test_norm_of_e_R_is_4psi_2_minus_psi() -> None:
    """‖e_R‖² = 4ψ(2 − ψ) (the paper prints 2ψ(2 − ψ): docs/controller.md, "Errors in the paper")."""
    Q = Rotation.random(500, random_state=3).as_matrix()
    R_des = Rotation.random(500, random_state=4).as_matrix()
    A = Q @ R_des
    e_R = vee(A - np.swapaxes(A, 1, 2))
    psi = 0.5 * (3 - np.trace(A, axis1=1, axis2=2))
    # an identity, both sides from the same A (entries ≤ 1): a few roundings of values ≤ 16
    np.testing.assert_allclose(np.sum(e_R**2, axis=1), 4 * psi * (2 - psi), atol=1e-12)


def test_error_rates_match_finite_differences(spec) -> None:
    """ė_k = 2 qᵀ(R_k1ᵀR_k2 v_k2 − v_k1) and ψ̇_k = ½ e_Rᵀ(R_k1ᵀR_k2 ω_k2 − ω_k1) (eq. errors derivative)."""
    p, R = world(spec)
    idx = {a.id: a.index for a in spec.agents}
    v = RNG.normal(size=(len(p), 6))
    h = 1e-6

    def moved(s: float):
        return p + s * np.einsum("nij,nj->ni", R, v[:, :3]), R @ exp_rows(s * v[:, 3:])

    plus, minus = edge_errors(spec, *moved(h)), edge_errors(spec, *moved(-h))
    for k, e in enumerate(spec.edges):
        t, hd = idx[e.tail], idx[e.head]
        q = R[t].T @ (p[hd] - p[t])
        Q = R[t].T @ R[hd]
        e_dot = 2 * q @ (Q @ v[hd, :3] - v[t, :3])
        e_R = edge_errors(spec, p, R)[k][2]
        psi_dot = 0.5 * e_R @ (Q @ v[hd, 3:] - v[t, 3:])
        # central differences: O(h²) truncation, 1e-10/h rounding → tolerance 1e-6
        assert (plus[k][0] - minus[k][0]) / (2 * h) == pytest.approx(e_dot, abs=1e-6)
        assert (plus[k][1] - minus[k][1]) / (2 * h) == pytest.approx(psi_dot, abs=1e-6)


def vector_form_v_des(spec: FormationSpec, p: np.ndarray, R: np.ndarray, t: float) -> np.ndarray:
    """v_des of every agent from the paper's vector form (eq. control design vectors) with D_R."""
    N, K = len(spec.agents), len(spec.edges)
    idx = {a.id: a.index for a in spec.agents}
    D = np.zeros((N, K))
    for k, e in enumerate(spec.edges):
        D[idx[e.head], k], D[idx[e.tail], k] = 1.0, -1.0
    R_bar = np.zeros((3 * N, 3 * N))
    for i in range(N):
        R_bar[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = R[i]
    R_hat = np.zeros((3 * K, 3 * K))
    F_p = np.zeros((3 * K, K))
    sig_e = np.zeros(K)
    sig_psi = np.zeros(K)
    e_R = np.zeros(3 * K)
    for k, (e, (ek, psik, eRk)) in enumerate(zip(spec.edges, edge_errors(spec, p, R))):
        t_i, h_i = idx[e.tail], idx[e.head]
        R_hat[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = R[t_i]
        F_p[3 * k : 3 * k + 3, k] = 2 * (p[h_i] - p[t_i])
        rho_e, rho_psi = e.rho_e(t), e.rho_psi(t)
        xi = ek / rho_e
        eps = math.log((1 + xi / e.c_col) / (1 - xi / e.c_con))
        sig_e[k] = (1 / (e.c_col + xi) + 1 / (e.c_con - xi)) / rho_e * eps
        sig_psi[k] = 1 / (1 - psik / rho_psi) / rho_psi
        e_R[3 * k : 3 * k + 3] = eRk
    D_R = R_bar.T @ np.kron(D, np.eye(3)) @ R_hat
    Delta = np.kron(np.diag([a.controller.delta for a in spec.agents]), np.eye(3))
    v_L = -Delta @ D_R @ R_hat.T @ F_p @ sig_e
    omega = -Delta @ D_R @ np.kron(np.diag(sig_psi), np.eye(3)) @ e_R
    return np.hstack([v_L.reshape(N, 3), omega.reshape(N, 3)])


@pytest.mark.parametrize("seed", range(5))
def test_per_agent_law_equals_vector_form(spec, seed) -> None:
    """eq. vel_i_des per agent = eq. control design vectors with D_R = R̄ᵀ(D⊗I)R̂."""
    rng = np.random.default_rng(seed)
    p, R = world(spec)
    # stay inside the funnels: edge 3-4 starts 8 % from its bound
    p = p + rng.normal(scale=0.02, size=p.shape)
    R = R @ exp_rows(rng.normal(scale=0.05, size=(len(p), 3)))
    t = rng.uniform(0, 0.05)
    expected = vector_form_v_des(spec, p, R, t)
    for a in spec.agents:
        ctrl = BoundedController(agent_view(spec, a.id))
        out = ctrl.compute(t, measurements(spec, p, R, a.id), np.zeros(6))
        # two correct computations of one formula in other orders: within the step's round-off tolerance
        # (formation_agent.roundoff), the vector form's matrix products being as exact as the edges' sums
        assert np.all(np.abs(np.array(out.v_des) - expected[a.index]) <= ctrl.tolerances()["v_des"])


@pytest.mark.parametrize("seed", range(10))
def test_wrench_is_invariant_under_rigid_motion_of_the_formation(spec, seed) -> None:
    """Relative information only: moving and turning the whole formation changes no wrench."""
    rng = np.random.default_rng(100 + seed)
    p, R = world(spec)
    v = rng.normal(scale=0.3, size=(len(p), 6))
    G = Rotation.random(random_state=seed).as_matrix()
    offset = rng.uniform(-100, 100, size=3)
    p2, R2 = p @ G.T + offset, G @ R
    t = rng.uniform(0, 2)
    for a in spec.agents:
        u1 = AgentController(agent_view(spec, a.id)).compute(t, measurements(spec, p, R, a.id), v[a.index]).wrench
        u2 = AgentController(agent_view(spec, a.id)).compute(t, measurements(spec, p2, R2, a.id), v[a.index]).wrench
        # rounding of p up to 1e2 m propagates to ~1e-13 relative
        np.testing.assert_allclose(u2, u1, rtol=1e-9, atol=1e-9)


def test_following_v_des_decreases_the_transformed_errors(spec) -> None:
    """With v = v_des (kinematics only) V = ½Σε_e² + Σε_ψ decreases at every step (paper's proof, step I)."""
    p, R = world(spec)
    ctrls = {a.id: AgentController(agent_view(spec, a.id)) for a in spec.agents}
    dt, t = 1e-3, 0.0

    def lyapunov(p, R, t):
        V = 0.0
        for e, (ek, psik, _) in zip(spec.edges, edge_errors(spec, p, R)):
            xi = ek / e.rho_e(t)
            V += 0.5 * math.log((1 + xi / e.c_col) / (1 - xi / e.c_con)) ** 2 - math.log(1 - psik / e.rho_psi(t))
        return V

    V0 = V_prev = lyapunov(p, R, t)
    e0 = np.array([x[0] for x in edge_errors(spec, p, R)])
    for _ in range(300):
        v = np.array([ctrls[a.id].compute(t, measurements(spec, p, R, a.id), np.zeros(6)).v_des for a in spec.agents])
        p = p + dt * np.einsum("nij,nj->ni", R, v[:, :3])
        R = R @ exp_rows(dt * v[:, 3:])
        # frozen funnels (t fixed): the flow alone must make V decrease
        V = lyapunov(p, R, t)
        assert V < V_prev
        V_prev = V
    e1 = np.array([x[0] for x in edge_errors(spec, p, R)])
    assert V < 0.9 * V0
    assert np.abs(e1).sum() < np.abs(e0).sum()


def test_outside_a_funnel_the_wrench_is_finite_and_the_level_error(spec) -> None:
    """Past every bound (ξ_e beyond C_con, ψ beyond ρ_ψ, |ξ_v| > 1): finite, saturated wrench."""
    view = agent_view(spec, 1)
    ctrl = AgentController(view)
    p, R = world(spec)
    meas = measurements(spec, p, R, "1")
    first = ctrl.compute(0.0, meas, np.zeros(6))
    assert first.level in (OK, 1)
    far = {j: (np.array(pj) * 3.0, Rj) for j, (pj, Rj) in meas.items()}
    out = ctrl.compute(4.0, far, np.full(6, 50.0))
    assert out.level == ERROR
    assert all(math.isfinite(x) for x in out.wrench)
    assert min(out.margin_e) < 0 and min(out.margin_v) < 0
    nan = {j: (np.array([np.nan, 0, 0]), Rj) for j, (_, Rj) in meas.items()}
    bad = ctrl.compute(4.0, nan, np.zeros(6))
    assert bad.level == ERROR and bad.wrench == (0.0,) * 6


def test_missing_neighbour_is_named(spec) -> None:
    ctrl = AgentController(agent_view(spec, 3))
    p, R = world(spec)
    meas = measurements(spec, p, R, "3")
    del meas["4"]
    with pytest.raises(MissingMeasurementError, match="neighbour\\(s\\) 4"):
        ctrl.compute(0.0, meas, np.zeros(6))
    fault = ctrl.fault_output(0.0, "stale")
    assert fault.level == ERROR and fault.wrench == (0.0,) * 6


def test_rho_v0_is_set_at_the_first_step(spec) -> None:
    """ρ_v,0 = 2|e_v(0)| + 1 per channel (docs/controller.md, "The velocity funnel's start"), then held."""
    ctrl = AgentController(agent_view(spec, 2))
    p, R = world(spec)
    v = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.05])
    out = ctrl.compute(0.0, measurements(spec, p, R, "2"), v)
    # the same operations in the same order on the same numbers: the same bits
    np.testing.assert_array_equal(ctrl.rho_v0, 2 * np.abs(v - np.array(out.v_des)) + 1)
    # ρ_v(0) = (ρ_v0 − ρ∞)·e⁰ + ρ∞ rounds twice before the division: a few ulps
    np.testing.assert_allclose(out.xi_v, (v - np.array(out.v_des)) / np.array(ctrl.rho_v0), rtol=1e-12)


def test_wrench_is_bounded_by_the_controller_limits(spec) -> None:
    """A 1e6 m relative translation saturates every funnel, yet the wrench stays within 100 N / 100 N·m."""
    p, R = world(spec)
    meas = measurements(spec, p, R, "1")
    far = {j: (np.array([1e6, 0.0, 0.0]), Rj) for j, (_, Rj) in meas.items()}
    ctrl = AgentController(agent_view(spec, "1"))
    ctrl.compute(0.0, meas, np.zeros(6))  # the first step sets the velocity funnel from e_v(0)
    out = ctrl.compute(1e-4, far, np.array([1e3, 0, 0, 0, 0, 1e3]))
    assert out.level == ERROR
    force, torque = np.linalg.norm(out.wrench[:3]), np.linalg.norm(out.wrench[3:])
    assert force <= 100.0 * (1 + 1e-12) and torque <= 100.0 * (1 + 1e-12)
    assert force == pytest.approx(100.0, rel=1e-12)  # saturated, not zeroed: the scaling's few roundings


def test_controller_limits_default_to_the_actuators_and_never_exceed_them(paper_path: Path) -> None:
    """controller.max_force: null takes dynamics.max_force; a larger value is an error naming both."""
    import yaml

    from formation_core.errors import FormationSpecError
    from formation_core.spec import formation_from_dict

    doc = yaml.safe_load(paper_path.read_text())
    doc["agents"][0]["dynamics"]["max_force"] = 40.0
    spec = formation_from_dict(doc)
    assert spec.agents[0].controller.max_force == 40.0 and spec.agents[1].controller.max_force == 100.0
    doc["agents"][0]["controller"] = {"max_force": 50.0}
    with pytest.raises(FormationSpecError, match=r"agents\[0\]\.controller\.max_force: 50 exceeds .*max_force 40"):
        formation_from_dict(doc)


# --- each test kills the mutant it is named after (tests/mutants.py) ----------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_mutant_wrench_sign_flipped__the_wrench_opposes_the_transformed_velocity_error(spec, seed) -> None:
    """u_i,c = −γ ρ_v⁻¹ r_v(ξ_v) T_v(ξ_v): in every channel the wrench has the sign opposite to ξ_v (r_v > 0 and
    T_v has the sign of ξ_v), inside the funnel and saturated alike, and the actuator limit keeps the signs."""
    rng = np.random.default_rng(300 + seed)
    p, R = world(spec)
    p = p + rng.normal(scale=0.02, size=p.shape)
    R = R @ exp_rows(rng.normal(scale=0.05, size=(len(p), 3)))
    for a in spec.agents:
        ctrl = AgentController(agent_view(spec, a.id))
        meas = measurements(spec, p, R, a.id)
        ctrl.compute(0.0, meas, np.zeros(6))  # sets ρ_v0 = 2|e_v(0)| + 1
        for t in rng.uniform(0.0, 0.5, size=4):
            v = rng.normal(scale=1.5, size=6)  # some channels past their funnel: saturated
            out = ctrl.compute(t, meas, v)
            xi, u = np.array(out.xi_v), np.array(out.wrench)
            assert np.all(xi != 0.0)
            np.testing.assert_array_equal(np.sign(u), -np.sign(xi))


def test_mutant_torque_limited_by_max_force__force_and_torque_have_their_own_limits(paper_path: Path) -> None:
    """An agent whose controller.max_torque (5 N·m) differs from its max_force (100 N): a saturating error
    gives a torque of norm 5 and a force of norm 100; with the limits the other way round, 100 and 5."""
    import yaml

    from formation_core.spec import formation_from_dict

    for max_force, max_torque in ((100.0, 5.0), (5.0, 100.0)):
        doc = yaml.safe_load(paper_path.read_text())
        doc["agents"][0].setdefault("controller", {}).update(max_force=max_force, max_torque=max_torque)
        spec = formation_from_dict(doc)
        p, R = world(spec)
        meas = measurements(spec, p, R, spec.agents[0].id)
        ctrl = AgentController(agent_view(spec, spec.agents[0].id))
        ctrl.compute(0.0, meas, np.zeros(6))
        out = ctrl.compute(1e-4, meas, np.array([1e3, 1e3, 0.0, 0.0, 1e3, 1e3]))  # force and torque past their limits
        force, torque = np.linalg.norm(out.wrench[:3]), np.linalg.norm(out.wrench[3:])
        # the limit scales a norm to the limit: equal up to the rounding of the scaling
        assert force == pytest.approx(max_force, rel=1e-12) and torque == pytest.approx(max_torque, rel=1e-12)
