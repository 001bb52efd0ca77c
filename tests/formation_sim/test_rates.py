"""The control rate an agent needs: a pure function of (M, γ, ρ_v), against the closed form of docs/controller.md."""

from __future__ import annotations

import numpy as np
import pytest

from formation_core import funnels
from formation_core.spec import load_formation
from formation_sim.core.loop import initial_rho_v0
from formation_sim.core.rates import mass_matrix, rate_need, rate_needs

pytestmark = pytest.mark.numeric

RNG = np.random.default_rng(11)


def test_diagonal_mass_matrix_gives_the_closed_form() -> None:
    """M = diag(m I, J) with diagonal J: f_s = max_ℓ 2γ / (M_ℓℓ ρ_v,ℓ²) (docs/controller.md), to 1e-12."""
    for _ in range(50):
        m, J = RNG.uniform(0.05, 2.0), RNG.uniform(0.01, 1.0, size=3)
        gamma, rho = RNG.uniform(1, 20), RNG.uniform(0.05, 3.0, size=6)
        M_diag = np.array([m, m, m, *J])
        expected = np.max(2 * gamma / (M_diag * rho**2))
        # the need is the largest eigenvalue of M⁻¹K by LAPACK (backward stable, any BLAS): the largest is
        # of the order of the matrix's norm, so it carries some c·n·u ≈ 1e-15 relative
        assert rate_need(mass_matrix(m, np.diag(J)), gamma, rho) == pytest.approx(expected, rel=1e-12)


def test_rate_need_is_vectorised_over_time_and_rotation_invariant() -> None:
    """A stack of ρ_v gives one need each; a full inertia matrix R diag(J) Rᵀ with equal ρ_v per axis
    has the need of diag(J) (eigenvalues of J⁻¹ are invariant)."""
    from scipy.spatial.transform import Rotation

    J = np.array([0.1, 0.4, 0.9])
    Q = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    rho = np.array([[1.0] * 3 + [0.5] * 3, [0.2] * 6])
    diag = rate_need(mass_matrix(1.0, np.diag(J)), 10.0, rho)
    full = rate_need(mass_matrix(1.0, Q @ np.diag(J) @ Q.T), 10.0, rho)
    assert diag.shape == (2,)
    # Q diag(J) Qᵀ rounds (3-term sums), the inverse amplifies by κ(J) = 9, then the eigenvalues as above
    np.testing.assert_allclose(full, diag, rtol=1e-10)


def test_paper_needs_are_the_closed_form_at_both_ends(paper_path) -> None:
    """formation-check's numbers for the paper preset: the closed form on ρ_v(0) and ρ_v(T)."""
    spec = load_formation(paper_path)
    T = spec.simulation.duration
    rho_v0s = initial_rho_v0(spec)
    for a, rho_v0, need in zip(spec.agents, rho_v0s, rate_needs(spec, rho_v0s)):
        vf = a.controller.velocity_funnel
        M_diag = np.array([a.dynamics.mass] * 3 + list(np.diag(a.dynamics.inertia)))
        for t, value in ((0.0, need.at_start), (T, need.at_end)):
            rho = funnels.rho(t, rho_v0, np.array(vf.rho_inf), np.array(vf.decay))
            # as in test_diagonal_mass_matrix_gives_the_closed_form, plus one exp in ρ_v
            assert value == pytest.approx(np.max(2 * a.controller.gamma / (M_diag * rho**2)), rel=1e-12)
    needs = rate_needs(spec, initial_rho_v0(spec))  # docs/controller.md: about 0.5 kHz at t = 0 and 3 kHz at t = 5 s
    assert 400 < max(n.at_start for n in needs) < 700 and 2500 < max(n.at_end for n in needs) < 3500
