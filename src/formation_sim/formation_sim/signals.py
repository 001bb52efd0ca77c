"""Disturbance w_i(x, v, t) and velocity noise n_i(x, t) models, vectorised over agents.

Models (formation file ``dynamics.disturbance`` / ``dynamics.velocity_noise``):

- ``none``: 0;
- ``paper``: ``A·sin(‖p_ref‖₁·tr(R_i)·ω·t + φ)·v_i`` with p_ref the first agent's position
  (the paper, literally) or the agent's own;
- ``constant``: a fixed body-frame 6-vector;
- ``random``: a seeded sum of sinusoids per channel, bounded by ``bound`` (smooth, so its
  derivative is bounded as the paper assumes).

All values are body-frame 6-vectors [force or linear, torque or angular] in SI units.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from formation_msgs_py.spec import SignalModel


class SignalBank:
    """One signal model per agent, evaluated for all agents at once."""

    def __init__(self, models: Sequence[SignalModel], rng: np.random.Generator) -> None:
        n = len(models)
        self.paper_amp = np.zeros(n)
        self.paper_freq = np.zeros(n)
        self.paper_phase = np.zeros(n)
        self.paper_ref_self = np.zeros(n, dtype=bool)
        self.constant = np.zeros((n, 6))
        self.random_amp = np.zeros((n, 6, 1))
        self.random_freq = np.zeros((n, 6, 1))
        self.random_phase = np.zeros((n, 6, 1))
        self.active = any(m.model != "none" for m in models)
        self.has_paper = any(m.model == "paper" for m in models)
        randoms = [(i, m) for i, m in enumerate(models) if m.model == "random"]
        if randoms:
            kmax = max(m.params["components"] for _, m in randoms)
            self.random_amp = np.zeros((n, 6, kmax))
            self.random_freq = np.zeros((n, 6, kmax))
            self.random_phase = np.zeros((n, 6, kmax))
        for i, m in enumerate(models):
            if m.model == "paper":
                self.paper_amp[i] = m.params["amplitude"]
                self.paper_freq[i] = m.params["frequency"]
                self.paper_phase[i] = m.params["phase"]
                self.paper_ref_self[i] = m.params["position_reference"] == "self"
            elif m.model == "constant":
                self.constant[i] = m.params["value"]
            elif m.model == "random":
                k = m.params["components"]
                weights = rng.uniform(0.2, 1.0, size=(6, k))
                weights /= weights.sum(axis=1, keepdims=True)
                self.random_amp[i, :, :k] = weights * np.asarray(m.params["bound"])[:, None]
                self.random_freq[i, :, :k] = 2 * np.pi * rng.uniform(0.05, 1.0, size=(6, k)) * m.params["max_frequency"]
                self.random_phase[i, :, :k] = rng.uniform(0, 2 * np.pi, size=(6, k))
        self.has_random = bool(randoms)

    def evaluate(self, t: float, p: np.ndarray, R: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N, 6) signal at time t (s) for positions p (N,3), rotations R (N,3,3), twists v (N,6)."""
        out = self.constant.copy() if self.active else np.zeros_like(v)
        if self.has_paper:
            ref = np.where(self.paper_ref_self, np.abs(p).sum(axis=1), np.abs(p[0]).sum())
            trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
            gain = self.paper_amp * np.sin(ref * trace * self.paper_freq * t + self.paper_phase)
            out += gain[:, None] * v
        if self.has_random:
            out += np.sum(self.random_amp * np.sin(self.random_freq * t + self.random_phase), axis=2)
        return out
