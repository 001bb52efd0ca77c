"""Disturbance w_i(x, v, t) and velocity noise n_i(x, t) models of every agent, as kernel arrays.

Models (formation file ``dynamics.disturbance`` / ``dynamics.velocity_noise``):

- ``none``: 0;
- ``paper``: ``A·sin(‖p_ref‖₁·tr(R_i)·ω·t + φ)·v_i`` with p_ref the first agent's position
  (the paper, literally) or the agent's own;
- ``constant``: a fixed body-frame 6-vector;
- ``random``: a seeded sum of sinusoids per channel, bounded by ``bound`` (smooth, so its
  derivative is bounded as the paper assumes).

All values are body-frame 6-vectors [force or linear, torque or angular] in SI units.
:func:`signal_value` evaluates agent i's model inside the compiled plant and run core.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from formation_core.formation import SignalModel
from formation_core.numba_kernels import formula

NONE, PAPER, CONSTANT, RANDOM = 0, 1, 2, 3
_KINDS = {"none": NONE, "paper": PAPER, "constant": CONSTANT, "random": RANDOM}


class SignalParams(NamedTuple):
    """One model per agent: ``kind`` (N,) and the parameters of every kind (unused rows zero)."""

    kind: np.ndarray  # (N,) int
    paper: np.ndarray  # (N, 4): amplitude, frequency, phase, 1.0 if p_ref is the agent's own position
    constant: np.ndarray  # (N, 6)
    amplitude: np.ndarray  # (N, 6, C) random: per channel and component
    frequency: np.ndarray  # (N, 6, C) [rad/s]
    phase: np.ndarray  # (N, 6, C) [rad]

    @property
    def active(self) -> bool:
        return bool(np.any(self.kind != NONE))


def signal_params(models: Sequence[SignalModel], rng: np.random.Generator) -> SignalParams:
    """The arrays of ``models`` (draws of ``random`` models from ``rng``, in agent order)."""
    n = len(models)
    components = max([m.params["components"] for m in models if m.model == "random"], default=1)
    kind = np.zeros(n, dtype=np.int64)
    paper = np.zeros((n, 4))
    constant = np.zeros((n, 6))
    amp, freq, phase = (np.zeros((n, 6, components)) for _ in range(3))
    for i, m in enumerate(models):
        if m.model not in _KINDS:
            raise ValueError(f"unknown signal model {m.model!r}")
        kind[i] = _KINDS[m.model]
        prm = m.params
        if m.model == "paper":
            paper[i] = prm["amplitude"], prm["frequency"], prm["phase"], prm["position_reference"] == "self"
        elif m.model == "constant":
            constant[i] = prm["value"]
        elif m.model == "random":
            c = prm["components"]
            weights = rng.uniform(0.2, 1.0, size=(6, c))
            weights /= weights.sum(axis=1, keepdims=True)
            amp[i, :, :c] = weights * np.asarray(prm["bound"], dtype=np.float64)[:, None]
            freq[i, :, :c] = 2 * np.pi * rng.uniform(0.05, 1.0, size=(6, c)) * prm["max_frequency"]
            phase[i, :, :c] = rng.uniform(0, 2 * np.pi, size=(6, c))
    return SignalParams(kind, paper, constant, amp, freq, phase)


@formula
def random_channel(sig, i, c, t):
    """Channel c of agent i's ``random`` signal at t: Σ_m a_m sin(ω_m t + φ_m)."""
    acc = 0.0
    for m in range(sig.amplitude.shape[2]):
        acc += sig.amplitude[i, c, m] * np.sin(sig.frequency[i, c, m] * t + sig.phase[i, c, m])
    return acc


@formula
def signal_value(sig, i, t, ref_first, ref_self, trace, v):
    """Agent i's signal at t [s], a 6-tuple: ``ref_first``/``ref_self`` are ‖p_1‖₁/‖p_i‖₁, ``trace``
    tr(R_i), ``v`` the agent's twist (6,)."""
    kind = sig.kind[i]
    if kind == PAPER:
        amplitude, frequency, phase = sig.paper[i, 0], sig.paper[i, 1], sig.paper[i, 2]
        ref = ref_self if sig.paper[i, 3] > 0.5 else ref_first
        g = amplitude * np.sin(ref * trace * frequency * t + phase)
        return (g * v[0], g * v[1], g * v[2], g * v[3], g * v[4], g * v[5])
    if kind == CONSTANT:
        c = sig.constant[i]
        return (c[0], c[1], c[2], c[3], c[4], c[5])
    if kind == RANDOM:
        return (
            random_channel(sig, i, 0, t),
            random_channel(sig, i, 1, t),
            random_channel(sig, i, 2, t),
            random_channel(sig, i, 3, t),
            random_channel(sig, i, 4, t),
            random_channel(sig, i, 5, t),
        )
    return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@formula
def l1_norm(p, i):
    """‖p_i‖₁."""
    return abs(p[i, 0]) + abs(p[i, 1]) + abs(p[i, 2])


@formula
def signals_into(sig, t, p, R, v, out):
    """Add every agent's signal at t to ``out`` (N, 6), for positions p (N,3), rotations R (N,3,3), twists v (N,6)."""
    ref_first = l1_norm(p, 0)
    for i in range(p.shape[0]):
        if sig.kind[i] != NONE:
            w = signal_value(sig, i, t, ref_first, l1_norm(p, i), R[i, 0, 0] + R[i, 1, 1] + R[i, 2, 2], v[i])
            for c in range(6):
                out[i, c] += w[c]


def signals_at(sig: SignalParams, t: float, p: np.ndarray, R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Every agent's signal (N, 6) at t."""
    out = np.zeros((p.shape[0], 6))
    signals_into(sig, t, p, R, v, out)
    return out
