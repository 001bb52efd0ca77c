"""The run core: the closed loop of a whole formation stepped many control steps at a time, compiled.

Per control step k (t_k = k / control_rate) :func:`run_steps` does what the ROS 2 lockstep run
does, step for step: the measurements of step k (relative poses with their noise, noisy
twists), every agent's controller (:func:`formation_sim.team.team_step`, with the fault policy),
the step's ground truth, wrenches and velocity-funnel margins into the recording buffers, then
``substeps`` physics steps: with the wrenches held (``sampled``, zero-order hold) or with the
controller evaluated on every integrator stage (``continuous``, the paper's law). It returns to
Python after a buffer's worth of steps, at the first step with a fault while none is recorded
yet (so the recorder sees faults and funnel checks in the order the streaming runs record them),
or when a state is no longer finite (naming the agent).

:func:`run_closed_loop` drives it for a formation and a :class:`RunRecorder`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from formation_agent.controller import (
    ERROR,
    REASON_MESSAGES,
    AgentGains,
    EdgeGains,
    FunnelStart,
    Outputs,
    gains,
    new_funnel_start,
    new_outputs,
)
from formation_msgs_py.compiled import kernel
from formation_msgs_py.spec import FormationSpec, agent_view, simulator_view
from formation_sim.measurement import Sensing, relative_poses
from formation_sim.plant import (
    PlantParams,
    body_rates,
    chart_rates,
    measured_velocity,
    rkmk4_combine,
    rkmk4_stage,
    rkmk4_step,
    saturate,
)
from formation_sim.report import RunRecorder
from formation_sim.simulation import Simulation
from formation_sim.team import note_errors, note_missing, team_step

#: run_steps' reasons to return early
EVENT_NONE, EVENT_FAULT, EVENT_NON_FINITE = 0, 1, 2
#: (t, real-time factor, worst margin so far)
ProgressFn = Callable[[float, float, float], None]


class ClosedLoop(NamedTuple):
    """Everything the compiled loop reads or updates besides the plant state."""

    plant: PlantParams
    sensing: Sensing
    agents: AgentGains
    ends: EdgeGains
    start: FunnelStart
    out: Outputs
    p_rel: np.ndarray  # (n_ends, 3) scratch: the step's measurements
    R_rel: np.ndarray  # (n_ends, 3, 3)
    in_range: np.ndarray  # (n_ends,) bool
    noise: np.ndarray  # (draws, 2, n_links, 3) standard normal draws, or (1, 0, 0, 3) without noise
    cursor: np.ndarray  # (1,) int: next row of ``noise``


class Buffers(NamedTuple):
    """Every control step's sample, a chunk at a time (rows 0..n-1 of a call)."""

    t: np.ndarray  # (C,)
    p: np.ndarray  # (C, N, 3)
    R: np.ndarray  # (C, N, 3, 3)
    v: np.ndarray  # (C, N, 6)
    u: np.ndarray  # (C, N, 6)
    margin_v: np.ndarray  # (C, N, 6)
    level: np.ndarray  # (C, N)
    reason: np.ndarray  # (C, N)
    in_range: np.ndarray  # (C, n_ends) bool: the end's neighbour was measured


def new_buffers(rows: int, n_agents: int, n_ends: int) -> Buffers:
    return Buffers(
        np.zeros(rows),
        np.zeros((rows, n_agents, 3)),
        np.zeros((rows, n_agents, 3, 3)),
        np.zeros((rows, n_agents, 6)),
        np.zeros((rows, n_agents, 6)),
        np.zeros((rows, n_agents, 6)),
        np.zeros((rows, n_agents), dtype=np.int64),
        np.zeros((rows, n_agents), dtype=np.int64),
        np.zeros((rows, n_ends), dtype=np.bool_),
    )


@kernel
def sense_and_control(loop, t, p, R, v):
    """The measurements at t (consuming one noise draw) and every agent's answer, into ``loop.out``."""
    if loop.noise.shape[1] == 0:
        draws = loop.noise[0]
    else:
        draws = loop.noise[loop.cursor[0]]
        loop.cursor[0] += 1
    relative_poses(p, R, loop.sensing, draws, loop.p_rel, loop.R_rel, loop.in_range)
    v_measured = measured_velocity(t, p, R, v, loop.plant.noise)
    team_step(t, loop.p_rel, loop.R_rel, loop.in_range, v_measured, loop.agents, loop.ends, loop.start, loop.out)


@kernel
def continuous_step(loop, t, p, R, v, h):
    """One RKMK4 step (as :func:`formation_sim.plant.rkmk4_step`) with the controller at every stage."""
    half = 0.5 * h
    sense_and_control(loop, t, p, R, v)
    pd1, vd1 = body_rates(t, p, R, v, saturate(loop.out.u, loop.plant), loop.plant)
    K1 = np.ascontiguousarray(v[:, 3:])
    th2, p2, R2, v2 = rkmk4_stage(half, p, R, v, pd1, vd1, K1)
    sense_and_control(loop, t + half, p2, R2, v2)
    pd2, vd2 = body_rates(t + half, p2, R2, v2, saturate(loop.out.u, loop.plant), loop.plant)
    K2 = chart_rates(th2, v2)
    th3, p3, R3, v3 = rkmk4_stage(half, p, R, v, pd2, vd2, K2)
    sense_and_control(loop, t + half, p3, R3, v3)
    pd3, vd3 = body_rates(t + half, p3, R3, v3, saturate(loop.out.u, loop.plant), loop.plant)
    K3 = chart_rates(th3, v3)
    th4, p4, R4, v4 = rkmk4_stage(h, p, R, v, pd3, vd3, K3)
    sense_and_control(loop, t + h, p4, R4, v4)
    pd4, vd4 = body_rates(t + h, p4, R4, v4, saturate(loop.out.u, loop.plant), loop.plant)
    K4 = chart_rates(th4, v4)
    return rkmk4_combine(h, p, R, v, (pd1, pd2, pd3, pd4), (vd1, vd2, vd3, vd4), (K1, K2, K3, K4))


@kernel
def first_non_finite(p, R, v):
    """Index of the first agent whose state is not finite, or −1."""
    for i in range(p.shape[0]):
        if not (np.all(np.isfinite(p[i])) and np.all(np.isfinite(R[i])) and np.all(np.isfinite(v[i]))):
            return i
    return -1


@kernel
def run_steps(loop, p, R, v, k0, k_stop, k_last, control_rate, substeps, h, continuous, stop_at_fault, buf):
    """Control steps k0 … k_stop − 1 (no physics after step k_last); (steps done, event, agent, p, R, v)."""
    n = 0
    for k in range(k0, k_stop):
        t = k / control_rate
        sense_and_control(loop, t, p, R, v)
        out = loop.out
        buf.t[n] = t
        buf.p[n] = p
        buf.R[n] = R
        buf.v[n] = v
        buf.u[n] = out.u
        buf.margin_v[n] = out.margin_v
        buf.level[n] = out.level
        buf.reason[n] = out.reason
        buf.in_range[n] = loop.in_range
        fault = np.any(out.level == ERROR)
        n += 1
        if k == k_last:
            break
        u = out.u.copy()
        for s in range(substeps):
            if continuous:
                p, R, v = continuous_step(loop, t + s * h, p, R, v, h)
            else:
                p, R, v = rkmk4_step(t + s * h, p, R, v, u, h, loop.plant)
        bad = first_non_finite(p, R, v)
        if bad >= 0:
            return n, EVENT_NON_FINITE, bad, p, R, v
        if fault and stop_at_fault:
            return n, EVENT_FAULT, -1, p, R, v
    return n, EVENT_NONE, -1, p, R, v


def closed_loop(spec: FormationSpec, sim: Simulation) -> ClosedLoop:
    """The compiled loop's inputs for ``spec``, with the plant and measurement model of ``sim``."""
    agents, ends = gains([agent_view(spec, a) for a in spec.agent_ids])
    n, n_ends = len(spec.agents), len(ends.d2)
    return ClosedLoop(
        sim.plant.params,
        sim.sensors.sensing,
        agents,
        ends,
        new_funnel_start(n),
        new_outputs(n, n_ends),
        np.zeros((n_ends, 3)),
        np.zeros((n_ends, 3, 3)),
        np.zeros(n_ends, dtype=np.bool_),
        sim.sensors.draw_noise(1),
        np.zeros(1, dtype=np.int64),
    )


def _refill_noise(loop: ClosedLoop, sim: Simulation, draws: int) -> ClosedLoop:
    """Make sure ``draws`` more noise draws are at hand, continuing the measurement model's stream."""
    if not sim.sensors.noisy:
        return loop
    left = loop.noise[loop.cursor[0] :]
    if len(left) >= draws:
        return loop
    return loop._replace(
        noise=np.concatenate([left, sim.sensors.draw_noise(draws - len(left))]), cursor=np.zeros(1, dtype=np.int64)
    )


def run_closed_loop(
    spec: FormationSpec,
    recorder: RunRecorder,
    *,
    continuous: bool = False,
    stop_on_violation: bool = False,
    progress: ProgressFn | None = None,
    chunk: int | None = None,
) -> float:
    """Run ``spec`` for ``simulation.duration`` into ``recorder``; returns the wall time [s].

    Every control step is checked (``recorder.add_many``); faults are recorded as the streaming
    runs record them (:func:`formation_sim.team.note_missing` before a step's funnel check,
    :func:`formation_sim.team.note_errors` after it). A state that stops being finite ends the
    run with a ``plant`` fault naming the agent.
    """
    started = time.perf_counter()
    sim_spec = spec.simulation
    sim = Simulation(simulator_view(spec))
    loop = closed_loop(spec, sim)
    ids = spec.agent_ids
    n_steps = round(sim_spec.duration * sim_spec.control_rate)
    # about 8 MB of buffers per chunk, and progress at least every 2000 steps
    chunk = chunk or int(np.clip(8e6 / (len(ids) * 8 * 36), 100, 2000))
    neighbours = [ie.neighbour for a in ids for ie in agent_view(spec, a).edges]
    buf = new_buffers(chunk, len(ids), len(neighbours))
    draws_per_step = 1 + (4 * sim.substeps if continuous else 0)
    p, R, v = sim.state.p, sim.state.R, sim.state.v
    k = 0
    last_report = started
    while k <= n_steps:
        loop = _refill_noise(loop, sim, chunk * draws_per_step)
        watch = recorder.first_violation is None
        done, event, agent, p, R, v = run_steps(
            loop, p, R, v, k, min(k + chunk, n_steps + 1), n_steps, float(sim_spec.control_rate),
            sim.substeps, sim.h, continuous, watch, buf,
        )  # fmt: skip
        if watch and buf.level[done - 1].max() == ERROR:
            # a fault at the last step done: the checks before it, then its faults around its own check
            j = done - 1
            if j:
                recorder.add_many(*_samples(buf, slice(0, j)), stop_at_violation=stop_on_violation)
            if not (stop_on_violation and recorder.first_violation is not None):
                t = float(buf.t[j])
                first = loop.agents.first_end
                missing = {
                    i: [neighbours[e] for e in range(first[i], first[i + 1]) if not buf.in_range[j, e]]
                    for i in range(len(ids))
                    if not buf.in_range[j, first[i] : first[i + 1]].all()
                }
                note_missing(recorder, t, ids, missing)
                recorder.add_many(*_samples(buf, slice(j, done)))
                note_errors(recorder, t, ids, buf.level[j], [REASON_MESSAGES[r] for r in buf.reason[j]])
        else:
            recorder.add_many(*_samples(buf, slice(0, done)), stop_at_violation=stop_on_violation)
        k += done
        if event == EVENT_NON_FINITE:
            recorder.fault(k / sim_spec.control_rate, "plant", ids[agent], "non-finite state")
            break
        if stop_on_violation and recorder.first_violation is not None:
            break
        now = time.perf_counter()
        if progress is not None and now - last_report > 1.0:
            progress(k / sim_spec.control_rate, k / sim_spec.control_rate / (now - started), recorder.worst_margin())
            last_report = now
    sim.state.p, sim.state.R, sim.state.v = p, R, v
    return time.perf_counter() - started


def _samples(buf: Buffers, rows: slice) -> tuple[np.ndarray, ...]:
    return buf.t[rows], buf.p[rows], buf.R[rows], buf.v[rows], buf.u[rows], buf.margin_v[rows]
