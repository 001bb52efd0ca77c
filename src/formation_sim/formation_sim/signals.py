"""Disturbance w_i(x, v, t) and velocity noise n_i(x, t) models, one evaluator per agent.

Models (formation file ``dynamics.disturbance`` / ``dynamics.velocity_noise``):

- ``none``: 0;
- ``paper``: ``A·sin(‖p_ref‖₁·tr(R_i)·ω·t + φ)·v_i`` with p_ref the first agent's position
  (the paper, literally) or the agent's own;
- ``constant``: a fixed body-frame 6-vector;
- ``random``: a seeded sum of sinusoids per channel, bounded by ``bound`` (smooth, so its
  derivative is bounded as the paper assumes).

All values are body-frame 6-vectors [force or linear, torque or angular] in SI units. The
evaluators use Python floats: the plant calls them at every integrator stage for every agent,
where numpy's per-call overhead would dominate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from formation_msgs_py.spec import SignalModel

#: (t [s], ‖p_1‖₁, ‖p_i‖₁, tr(R_i), v_i) -> 6 values, for one agent
AgentSignal = Callable[[float, float, float, float, Sequence[float]], list[float]]


def _paper(amplitude: float, frequency: float, phase: float, own_position: bool) -> AgentSignal:
    sin = math.sin

    def evaluate(t: float, ref_first: float, ref_self: float, trace: float, v: Sequence[float]) -> list[float]:
        ref = ref_self if own_position else ref_first
        g = amplitude * sin(ref * trace * frequency * t + phase)
        return [g * x for x in v]

    return evaluate


def _constant(value: Sequence[float]) -> AgentSignal:
    value = [float(x) for x in value]

    def evaluate(t: float, ref_first: float, ref_self: float, trace: float, v: Sequence[float]) -> list[float]:
        return list(value)

    return evaluate


def _random(bound: Sequence[float], max_frequency: float, components: int, rng: np.random.Generator) -> AgentSignal:
    weights = rng.uniform(0.2, 1.0, size=(6, components))
    weights /= weights.sum(axis=1, keepdims=True)
    amp = (weights * np.asarray(bound, dtype=np.float64)[:, None]).tolist()
    freq = (2 * np.pi * rng.uniform(0.05, 1.0, size=(6, components)) * max_frequency).tolist()
    phase = rng.uniform(0, 2 * np.pi, size=(6, components)).tolist()
    channels = [tuple(zip(amp[c], freq[c], phase[c])) for c in range(6)]
    sin = math.sin

    def evaluate(t: float, ref_first: float, ref_self: float, trace: float, v: Sequence[float]) -> list[float]:
        out = []
        for ch in channels:  # plain loops: several times cheaper than nested generators here
            acc = 0.0
            for a, f, ph in ch:
                acc += a * sin(f * t + ph)
            out.append(acc)
        return out

    return evaluate


def make_signal(model: SignalModel, rng: np.random.Generator) -> AgentSignal | None:
    """The evaluator of one agent's model (None for ``none``)."""
    prm = model.params
    if model.model == "none":
        return None
    if model.model == "paper":
        return _paper(prm["amplitude"], prm["frequency"], prm["phase"], prm["position_reference"] == "self")
    if model.model == "constant":
        return _constant(prm["value"])
    if model.model == "random":
        return _random(prm["bound"], prm["max_frequency"], prm["components"], rng)
    raise ValueError(f"unknown signal model {model.model!r}")


class SignalBank:
    """One signal model per agent (draws of ``random`` models are seeded by ``rng``, in agent order)."""

    def __init__(self, models: Sequence[SignalModel], rng: np.random.Generator) -> None:
        self.signals: list[AgentSignal | None] = [make_signal(m, rng) for m in models]
        self.active = any(s is not None for s in self.signals)

    def evaluate(self, t: float, p: np.ndarray, R: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N, 6) signal at time t (s) for positions p (N,3), rotations R (N,3,3), twists v (N,6)."""
        out = np.zeros((len(self.signals), 6))
        if not self.active:
            return out
        l1 = np.abs(p).sum(axis=1).tolist()
        trace = (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]).tolist()
        vl = v.tolist()
        for i, sig in enumerate(self.signals):
            if sig is not None:
                out[i] = sig(t, l1[0], l1[i], trace[i], vl[i])
        return out
