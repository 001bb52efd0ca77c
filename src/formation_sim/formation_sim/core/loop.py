"""The run core: the closed loop of a whole formation stepped many control steps at a time, compiled.

Per control step k (t_k = k / control_rate) :func:`run_sampled` does what the ROS 2 lockstep run
does, step for step: the measurements of step k (relative poses with their noise, their rotations
through the messages' quaternions, noisy twists), every agent's controller at the time an agent
reads off the step's stamp (:func:`formation_msgs_py.codec.control_time`;
:func:`formation_sim.core.team.team_step`, with the fault policy), the step's ground truth,
wrenches and velocity-funnel margins into the recording buffers, every funnel checked on ground
truth (:func:`check_step`, the :class:`Watch`), then ``substeps``
physics steps with the wrenches held (zero-order hold); :func:`run_continuous` evaluates the
controller on every integrator stage instead (the paper's law, sub-stepped to within RK4's
stability limit: :func:`continuous_substeps`); two kernels, so that a sampled run does not compile
the continuous one. Each returns to Python after a buffer's worth of steps, at the first
violation when the run stops there, or when a state is no longer finite (naming the agents).
Python then hands the buffers to the recorder (the decimated trajectory,
the faults) and names the first violation (:meth:`formation_sim.core.judge.Judge.violation_at`).

:func:`run_closed_loop` drives it for a formation and a :class:`RunRecorder`.

Over 500 lines: every kernel of the closed loop with the buffer and watch layouts they share (the
``W_*`` offsets, compiled into the kernels as constants); numba keys a kernel's cache on the sources
it compiles, so keeping the loop in one module keeps one key for it.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from formation_agent.controller import (
    ERROR,
    LEVEL,
    MARGIN_V,
    REASON,
    START_RHO_V0,
    U,
    gains,
    new_funnel_start,
    new_outputs,
)
from formation_core import funnels
from formation_core.formation import FormationSpec, agent_view, simulator_view
from formation_core.numba_kernels import INTERPRETED, formula, kernel, kernel_cached
from formation_core.so3 import flat_rows, matrix_rows, vec3
from formation_msgs_py.codec import control_time, step_stamp_ns
from formation_sim.core.judge import (
    CheckedSteps,
    EdgeSample,
    Judge,
    edge_errors,
    edge_margins,
    in_contact,
    in_steady_band,
    outside,
    pair_clearance,
    settle,
)
from formation_sim.core.links import (
    LinkSet,
    deliver_wrenches,
    link_ages_into,
    link_summary,
    n_links,
    no_links,
    receive_measurements,
)
from formation_sim.core.measurement import Sensing, relative_poses
from formation_sim.core.plant import (
    PlantParams,
    body_chart_rates,
    body_rates,
    chart_rates,
    measured_velocity_into,
    new_workspace,
    rkmk4_combine,
    rkmk4_stage,
    rkmk4_step,
    saturate_into,
)
from formation_sim.core.rates import rate_needs
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.core.state_checks import non_finite_agents
from formation_sim.core.team import note_errors, note_missing, step_faults, team_step

#: why a chunk ended early (run_sampled, run_continuous)
EVENT_NONE, EVENT_NON_FINITE = 0, 1
#: (t, real-time factor, worst margin so far)
ProgressFn = Callable[[float, float, float], None]


class ClosedLoop(NamedTuple):
    """Everything the compiled loop reads or updates besides the plant state."""

    plant: PlantParams
    sensing: Sensing
    first_end: np.ndarray  # (N+1,) agent i owns ends first_end[i]:first_end[i+1]
    agents: np.ndarray  # (N, AGENT_COLUMNS) formation_agent.controller's gains
    ends: np.ndarray  # (n_ends, END_COLUMNS)
    start: np.ndarray  # (N, 7) the velocity funnels' start
    out: np.ndarray  # (N, OUT_COLUMNS) the step's wrenches, margins, levels
    edge_out: np.ndarray  # (n_ends, 6)
    p_rel: np.ndarray  # (n_ends, 3) scratch: the step's measurements
    q_rel: np.ndarray  # (n_ends, 4) the messages' quaternions
    R_rel: np.ndarray  # (n_ends, 3, 3) decoded from them
    in_range: np.ndarray  # (n_ends,) bool
    v_measured: np.ndarray  # (N, 6) scratch: the step's noisy twists
    u: np.ndarray  # (N, 6) scratch: the step's commanded wrenches (columns U of ``out``)
    noise: np.ndarray  # (draws, 2, n_links, 3) standard normal draws, or (1, 0, 0, 3) without noise
    cursor: np.ndarray  # (1,) int: next row of ``noise``
    links_on: bool  # a link model (formation_sim.core.links): the step's measurements and wrenches through it
    links: LinkSet
    link_draws: np.ndarray  # (steps, n_links, 3) the links' uniforms of the chunk's steps
    link_cursor: np.ndarray  # (1,) int: next row of ``link_draws``


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
    e: np.ndarray  # (C, K) the edges' errors on ground truth, and their funnels
    psi: np.ndarray  # (C, K)
    rho_e: np.ndarray  # (C, K)
    rho_psi: np.ndarray  # (C, K)
    link_age: np.ndarray  # (C, n_links) [s] each link's held sample's age (NaN: none), with a link model


def new_buffers(rows: int, n_agents: int, n_ends: int, n_edges: int, n_links: int = 0) -> Buffers:
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
        np.zeros((rows, n_edges)),
        np.zeros((rows, n_edges)),
        np.zeros((rows, n_edges)),
        np.zeros((rows, n_edges)),
        np.zeros((rows, n_links)),
    )


#: Columns of ``Watch.edges``: d_k², R_des (9, row-major), the funnels' constants, the steady bands.
W_D2, W_R_DES = 0, 1
W_C_COL, W_C_CON, W_FLOOR_E, W_DECAY_E, W_RHO_PSI_0, W_RHO_PSI_INF, W_DECAY_PSI = range(10, 17)
W_BAND_LO, W_BAND_HI, W_BAND_PSI = 17, 18, 19


class Watch(NamedTuple):
    """Every funnel checked on ground truth at every control step, compiled, with the rules of
    :class:`formation_sim.core.judge.Judge` (which names the first violation): running minimum
    margins, settle times (NaN: none) and peak wrenches, as :class:`formation_sim.core.recorder.CheckedSteps`."""

    pairs: np.ndarray  # (K, 2) tail, head
    edges: np.ndarray  # (K, 20)
    checked: CheckedSteps
    bodies: np.ndarray  # (P, 2) every pair of bodies i < j
    r_sum: np.ndarray  # (P,) their radii's sum [m]
    contact_fails: bool  # simulation.contact: fail (a contact is a violation)


def new_watch(spec: FormationSpec, judge: Judge) -> Watch:
    edges = np.zeros((len(spec.edges), 20))
    band_lo, band_hi, band_psi = judge.edges.steady_band()
    for k, (row, e) in enumerate(zip(edges, spec.edges)):
        row[W_D2] = e.d_des**2
        row[W_R_DES : W_R_DES + 9] = np.asarray(e.R_des, dtype=np.float64).ravel()
        row[W_C_COL], row[W_C_CON] = e.c_col, e.c_con
        row[W_FLOOR_E], row[W_DECAY_E] = funnels.rho_e_floor(e.c_col, e.c_con, e.rho_e_inf), e.decay_e
        row[W_RHO_PSI_0], row[W_RHO_PSI_INF], row[W_DECAY_PSI] = e.rho_psi_0, e.rho_psi_inf, e.decay_psi
        row[W_BAND_LO], row[W_BAND_HI], row[W_BAND_PSI] = band_lo[k], band_hi[k], band_psi[k]
    K, N, P = len(spec.edges), len(spec.agents), len(judge.pairs.names)
    checked = CheckedSteps(
        min_margin_e=np.full(K, np.inf),
        min_margin_psi=np.full(K, np.inf),
        min_margin_v=np.full(N, np.inf),
        settle_e=np.full(K, np.nan),
        settle_psi=np.full(K, np.nan),
        peak_force=np.zeros(N),
        peak_torque=np.zeros(N),
        min_clearance=np.full(P, np.inf),
        min_clearance_t=np.full(P, np.nan),
        contact_t=np.full(P, np.nan),
    )
    pairs = np.stack([judge.edges.tail, judge.edges.head], axis=1).astype(np.int64)
    bodies = np.stack([judge.pairs.i, judge.pairs.j], axis=1).astype(np.int64)
    return Watch(pairs, edges, checked, bodies, judge.pairs.r_sum.copy(), judge.contact_fails)


@formula
def check_step(watch, buf, n, t, p, R, out):
    """The funnels at step n of the chunk on ground truth (e, ψ, ρ into ``buf``); True if one is left
    (the judge's formulas and rule: :func:`formation_core.funnels.edge_errors`, ``edge_margins``, ``outside``)."""
    c = watch.checked
    left = False
    for k in range(watch.pairs.shape[0]):
        g, i, j = watch.edges[k], watch.pairs[k, 0], watch.pairs[k, 1]
        e, psi = edge_errors(
            vec3(p[i]), vec3(p[j]), matrix_rows(R[i]), matrix_rows(R[j]), g[W_D2], flat_rows(g, W_R_DES)
        )
        rho_e, rho_psi, _, m_e, m_psi = edge_margins(
            t, e, psi, g[W_C_COL], g[W_C_CON], g[W_FLOOR_E], g[W_DECAY_E],
            g[W_RHO_PSI_0], g[W_RHO_PSI_INF], g[W_DECAY_PSI],
        )  # fmt: skip
        buf.e[n, k], buf.psi[n, k], buf.rho_e[n, k], buf.rho_psi[n, k] = e, psi, rho_e, rho_psi
        c.min_margin_e[k] = min(c.min_margin_e[k], m_e)
        c.min_margin_psi[k] = min(c.min_margin_psi[k], m_psi)
        inside_e, inside_psi = in_steady_band(e, psi, g[W_BAND_LO], g[W_BAND_HI], g[W_BAND_PSI])
        c.settle_e[k] = settle(c.settle_e[k], t, inside_e)
        c.settle_psi[k] = settle(c.settle_psi[k], t, inside_psi)
        left = left or outside(m_e) or outside(m_psi)
    for i in range(out.shape[0]):
        m_v = out[i, MARGIN_V]
        for ch in range(1, 6):
            m_v = min(m_v, out[i, MARGIN_V + ch])
        c.min_margin_v[i] = min(c.min_margin_v[i], m_v)
        left = left or outside(m_v)
        force = np.sqrt(out[i, U] * out[i, U] + out[i, U + 1] * out[i, U + 1] + out[i, U + 2] * out[i, U + 2])
        torque = np.sqrt(out[i, U + 3] * out[i, U + 3] + out[i, U + 4] * out[i, U + 4] + out[i, U + 5] * out[i, U + 5])
        c.peak_force[i] = max(c.peak_force[i], force)
        c.peak_torque[i] = max(c.peak_torque[i], torque)
    return check_clearances(watch, t, p) or left


@formula
def check_clearances(watch, t, p):
    """Every pair of bodies at t [s] (the judge's formula and rule: :func:`formation_sim.core.judge.pair_clearance`,
    ``in_contact``): each pair's smallest clearance and its first contact; True if a contact fails the run."""
    c = watch.checked
    fails = False
    for k in range(watch.bodies.shape[0]):
        i, j = watch.bodies[k, 0], watch.bodies[k, 1]
        clearance = pair_clearance(vec3(p[i]), vec3(p[j]), watch.r_sum[k])
        if clearance < c.min_clearance[k]:
            c.min_clearance[k] = clearance
            c.min_clearance_t[k] = t
        if in_contact(clearance):
            if np.isnan(c.contact_t[k]):
                c.contact_t[k] = t
            fails = fails or watch.contact_fails
    return fails


@formula
def sense_and_control(loop, k, t, t_control, p, R, v):
    """The measurements of control step k at plant time t (consuming one noise draw), through the links if
    any, and every agent's answer at its time ``t_control`` [s], into ``loop.out``; the wrenches the plant
    applies (the answers, through the wrench links if any) into ``loop.u``."""
    if loop.noise.shape[1] == 0:
        draws = loop.noise[0]
    else:
        draws = loop.noise[loop.cursor[0]]
        loop.cursor[0] += 1
    relative_poses(p, R, loop.sensing, draws, loop.p_rel, loop.q_rel, loop.R_rel, loop.in_range)
    measured_velocity_into(t, p, R, v, loop.plant.noise, loop.v_measured)
    if loop.links_on:
        uniforms = loop.link_draws[loop.link_cursor[0]]
        loop.link_cursor[0] += 1
        receive_measurements(
            loop.links, k, uniforms, loop.p_rel, loop.q_rel, loop.R_rel, loop.in_range, loop.v_measured, loop.first_end
        )
    team_step(
        t_control, loop.p_rel, loop.R_rel, loop.in_range, loop.v_measured,
        loop.first_end, loop.agents, loop.ends, loop.start, loop.out, loop.edge_out,
    )  # fmt: skip
    for i in range(loop.u.shape[0]):
        for c in range(6):
            loop.u[i, c] = loop.out[i, U + c]
    if loop.links_on:
        deliver_wrenches(loop.links, k, uniforms, loop.u, loop.u)


@formula
def continuous_step(loop, t, p, R, v, h, work):
    """One RKMK4 step (as :func:`formation_sim.core.plant.rkmk4_step`) with the controller at every stage."""
    sense_and_control(loop, -1, t, t, p, R, v)  # no links in continuous mode (the file refuses them)
    saturate_into(loop.u, loop.plant, work.u)
    body_rates(t, p, R, v, work.u, loop.plant, work.p_dot[0], work.v_dot[0])
    body_chart_rates(v, work)
    for k in range(3):
        c = h if k == 2 else 0.5 * h
        rkmk4_stage(c, p, R, v, k, work)
        sense_and_control(loop, -1, t + c, t + c, work.p, work.R, work.v)
        saturate_into(loop.u, loop.plant, work.u)
        body_rates(t + c, work.p, work.R, work.v, work.u, loop.plant, work.p_dot[k + 1], work.v_dot[k + 1])
        chart_rates(k + 1, work)
    rkmk4_combine(h, p, R, v, work)


@formula
def all_finite_state(p, R, v):
    """True while every entry of the state is finite (the caller names the agents otherwise)."""
    total = 0.0  # NaN or inf in any entry makes the sum non-finite
    for i in range(p.shape[0]):
        for x in range(3):
            total += p[i, x] + R[i, x, 0] + R[i, x, 1] + R[i, x, 2]
        for x in range(6):
            total += v[i, x]
    return np.isfinite(total)


@formula
def record_step(buf, n, t, p, R, v, out, in_range):
    """Row n of the buffers: the step's ground truth, wrenches, velocity margins, levels and ranges."""
    buf.t[n] = t
    for i in range(p.shape[0]):
        for x in range(3):
            buf.p[n, i, x] = p[i, x]
            for y in range(3):
                buf.R[n, i, x, y] = R[i, x, y]
        for c in range(6):
            buf.v[n, i, c] = v[i, c]
            buf.u[n, i, c] = out[i, U + c]
            buf.margin_v[n, i, c] = out[i, MARGIN_V + c]
        buf.level[n, i] = out[i, LEVEL]
        buf.reason[n, i] = out[i, REASON]
    for k in range(in_range.shape[0]):
        buf.in_range[n, k] = in_range[k]


@formula
def control_step(loop, watch, buf, n, k, t_plant, t, p, R, v, first_outside):
    """Step n of a chunk, control step k, at its time t [s] (the plant's ``t_plant``): measurements,
    controllers, the sample recorded and every funnel checked; returns the chunk's first step outside a
    funnel so far (−1: none)."""
    sense_and_control(loop, k, t_plant, t, p, R, v)
    record_step(buf, n, t, p, R, v, loop.out, loop.in_range)
    if loop.links_on:
        link_ages_into(loop.links, k, buf.link_age[n])
    if check_step(watch, buf, n, t, p, R, loop.out) and first_outside < 0:
        return n
    return first_outside


@kernel
def run_sampled(loop, watch, p, R, v, work, k0, k_stop, k_last, control_rate, t_control, substeps, h, stop, buf):
    """Control steps k0 … k_stop − 1, each followed by ``substeps`` RKMK4 steps with its wrenches held
    (none after step k_last); (p, R, v) in place. ``t_control`` holds every step's time, its stamp's
    (:func:`chunk_control_times`: the controllers', the record's), the plant's being k / control_rate.

    Returns (steps done, event, the chunk's first step outside a funnel or −1): ``EVENT_NON_FINITE``
    when the state is no longer finite; with ``stop`` the chunk ends at its first violation.
    """
    first_outside = -1
    for n in range(k_stop - k0):
        t = (k0 + n) / control_rate
        first_outside = control_step(loop, watch, buf, n, k0 + n, t, t_control[n], p, R, v, first_outside)
        if k0 + n == k_last or (stop and first_outside >= 0):
            return n + 1, EVENT_NONE, first_outside
        for s in range(substeps):
            rkmk4_step(t + s * h, p, R, v, loop.u, h, loop.plant, work)
        if not all_finite_state(p, R, v):
            return n + 1, EVENT_NON_FINITE, first_outside
    return k_stop - k0, EVENT_NONE, first_outside


@kernel
def run_continuous(loop, watch, p, R, v, work, k0, k_stop, k_last, control_rate, t_control, substeps, h, stop, buf):
    """:func:`run_sampled` with the controller evaluated at every stage of every physics step, at the
    plant's time (the paper's law: no messages, no stamps; ``t_control`` is not read)."""
    first_outside = -1
    for n in range(k_stop - k0):
        t = (k0 + n) / control_rate
        first_outside = control_step(loop, watch, buf, n, k0 + n, t, t, p, R, v, first_outside)
        if k0 + n == k_last or (stop and first_outside >= 0):
            return n + 1, EVENT_NONE, first_outside
        for s in range(substeps):
            continuous_step(loop, t + s * h, p, R, v, h, work)
        if not all_finite_state(p, R, v):
            return n + 1, EVENT_NON_FINITE, first_outside
    return k_stop - k0, EVENT_NONE, first_outside


def chunk_control_times(k0: int, k_stop: int, control_rate: float) -> np.ndarray:
    """The controllers' time [s] of steps k0 … k_stop − 1: each step's stamp as an agent reads it
    (:func:`formation_msgs_py.codec.control_time` of :func:`formation_msgs_py.codec.step_stamp_ns`)."""
    return np.array([control_time(step_stamp_ns(k, control_rate)) for k in range(k0, k_stop)])


def closed_loop(spec: FormationSpec, sim: Simulation) -> ClosedLoop:
    """The compiled loop's inputs for ``spec``, with the plant and measurement model of ``sim``."""
    first_end, agents, ends = gains([agent_view(spec, a) for a in spec.agent_ids])
    n, n_ends = len(agents), len(ends)
    return ClosedLoop(
        sim.plant.params,
        sim.sensors.sensing,
        first_end,
        agents,
        ends,
        new_funnel_start(n),
        *new_outputs(n, n_ends),
        np.zeros((n_ends, 3)),
        np.zeros((n_ends, 4)),
        np.zeros((n_ends, 3, 3)),
        np.zeros(n_ends, dtype=np.bool_),
        np.zeros((n, 6)),
        np.zeros((n, 6)),
        sim.sensors.draw_noise(1),
        np.zeros(1, dtype=np.int64),
        sim.links is not None,
        sim.links if sim.links is not None else no_links(),
        np.zeros((1, n_links(sim.links) if sim.links is not None else 0, 3)),
        np.zeros(1, dtype=np.int64),
    )


def compile_in_two_processes(spec: FormationSpec) -> None:
    """On a cold numba cache (no :func:`run_sampled` in it), compile the controllers' kernel
    (:func:`formation_sim.core.team.team_step`) in a second process while this one compiles the plant
    and measurement kernels, both into the shared cache; :func:`run_sampled` then loads them and
    compiles only itself. A first run takes the longer of the two parts, not their sum (numba's
    compiler lock rules out threads). No-op when the cache has run_sampled, or interpreted; if the
    second process fails, this one compiles team_step itself when it needs it.
    """
    if INTERPRETED or kernel_cached(run_sampled):
        return
    helper = subprocess.Popen(
        [sys.executable, "-c", "from formation_sim.core.team import load_team_step; load_team_step()"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        Simulation(simulator_view(spec))  # its warm-up compiles rkmk4_step, relative_poses, measured_velocity_into
    finally:
        helper.wait()


def first_step(spec: FormationSpec) -> np.ndarray:
    """``start`` (N, 7) after every agent's first step on the initial measurements: the run core's
    step 0, without physics (the velocity funnels as the agents set them)."""
    compile_in_two_processes(spec)
    sim = Simulation(simulator_view(spec), warm_up=False)
    loop = closed_loop(spec, sim)._replace(links_on=False)  # the funnels as set on the sensors' first values
    n, n_ends = loop.agents.shape[0], loop.ends.shape[0]
    buf = new_buffers(1, n, n_ends, len(spec.edges))
    s = sim.state
    rate = float(spec.simulation.control_rate)
    run_sampled(
        loop, new_watch(spec, Judge(spec)), s.p, s.R, s.v, new_workspace(n), 0, 1, 0, rate,
        chunk_control_times(0, 1, rate), 1, 1.0 / rate, False, buf,
    )  # fmt: skip
    return loop.start


def initial_rho_v0(spec: FormationSpec) -> np.ndarray:
    """ρ_v0 (N,6) as every agent sets it at its first step, on the initial measurements.

    An agent that misses a neighbour at t = 0 answers the fault wrench and sets no funnel then;
    its ``auto`` funnel is taken as the offset alone (e_v(0) = 0).
    """
    rho_v0 = first_step(spec)[:, START_RHO_V0:].copy()
    for i, a in enumerate(spec.agents):
        if np.isnan(rho_v0[i, 0]):
            vf = a.controller.velocity_funnel
            rho_v0[i] = vf.auto_offset if vf.rho_0 is None else vf.rho_0
    return rho_v0


#: Fraction of RK4's stability limit used: the linearisation at ξ_v = 0 underestimates the gain
#: r_v(ξ)/2 near the funnel's bound.
STABILITY_FRACTION = 0.5


def continuous_substeps(spec: FormationSpec, file_substeps: int) -> int:
    """Physics steps per control period for the continuous closed loop: at least the file's, and enough
    for every agent's RK4 stability limit (:attr:`formation_sim.core.rates.RateNeed.physics_step`)."""
    h_max = STABILITY_FRACTION * min(n.physics_step for n in rate_needs(spec, initial_rho_v0(spec)))
    return max(file_substeps, math.ceil(1.0 / (spec.simulation.control_rate * h_max)))


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
    substeps: int | None = None,
) -> tuple[float, str]:
    """Run ``spec`` for ``simulation.duration`` into ``recorder``: (wall time [s], why it is incomplete or "").

    Every control step is checked (:func:`check_step`, ``recorder.add_checked``); faults are recorded as the streaming
    runs record them (:func:`formation_sim.core.team.note_missing` before a step's funnel check,
    :func:`formation_sim.core.team.note_errors` after it). A state that stops being finite ends the
    run, incomplete, naming the agents (as :func:`formation_sim.core.state_checks.advance_checked`).
    ``substeps`` overrides the physics steps per control period (default: the file's, and in
    continuous mode at least :func:`continuous_substeps`).
    """
    started = time.perf_counter()
    if not continuous:
        compile_in_two_processes(spec)
    sim_spec = spec.simulation
    sim = Simulation(simulator_view(spec), warm_up=False)
    loop = closed_loop(spec, sim)
    ids = spec.agent_ids
    n_steps = round(sim_spec.duration * sim_spec.control_rate)
    # about 8 MB of buffers per chunk, and progress at least every 2000 steps
    chunk = chunk or int(np.clip(8e6 / (len(ids) * 8 * 36), 100, 2000))
    neighbours = [ie.neighbour for a in ids for ie in agent_view(spec, a).edges]
    buf = new_buffers(chunk, len(ids), len(neighbours), len(spec.edges), n_links(loop.links) if loop.links_on else 0)
    watch = new_watch(spec, recorder.judge)
    if substeps is None:  # physics steps per control period
        substeps = continuous_substeps(spec, sim.substeps) if continuous else sim.substeps
    h = 1.0 / (sim_spec.control_rate * substeps)
    draws_per_step = 1 + (4 * substeps if continuous else 0)
    p, R, v = sim.state.p, sim.state.R, sim.state.v  # advanced in place
    work = new_workspace(len(ids))
    run_chunk = run_continuous if continuous else run_sampled
    k = 0
    incomplete = ""
    last_report = started
    while k <= n_steps:
        loop = _refill_noise(loop, sim, chunk * draws_per_step)
        k_stop = min(k + chunk, n_steps + 1)
        if loop.links_on:  # exactly the chunk's steps: the stream as a step-by-step simulator draws it
            loop = loop._replace(link_draws=sim.draw_link_uniforms(k_stop - k), link_cursor=np.zeros(1, dtype=np.int64))
        rate = float(sim_spec.control_rate)
        done, event, j = run_chunk(
            loop, watch, p, R, v, work, k, k_stop, n_steps, rate, chunk_control_times(k, k_stop, rate),
            substeps, h, stop_on_violation, buf,
        )  # fmt: skip
        violation = None
        if j >= 0 and recorder.first_violation is None:
            violation = recorder.judge.violation_at(float(buf.t[j]), buf.p[j], buf.R[j], buf.margin_v[j])
        rows = slice(0, done)
        edges = EdgeSample(buf.e[rows], buf.psi[rows], buf.rho_e[rows], buf.rho_psi[rows])
        start = recorder.judge.samples
        recorder.add_checked(
            buf.t[rows], buf.p[rows], buf.R[rows], buf.v[rows], buf.u[rows], edges, watch.checked, violation
        )
        if loop.links_on:
            recorder.add_link_ages(buf.link_age[rows], start)
        for j in np.flatnonzero(buf.level[:done].max(axis=1) == ERROR):  # the fault policy's record
            t = float(buf.t[j])
            missing, errors = step_faults(loop.first_end, neighbours, buf.in_range[j], buf.level[j], buf.reason[j])
            note_missing(recorder, t, ids, missing)
            note_errors(recorder, t, ids, errors)
        k += done
        if event == EVENT_NON_FINITE:  # the run stops; the non-finite state is never recorded
            bad = ", ".join(non_finite_agents(ids, p, R, v))
            incomplete = f"t={k / sim_spec.control_rate:.6f} s: non-finite plant state of agent(s) {bad}"
            break
        if stop_on_violation and recorder.first_violation is not None:
            break
        now = time.perf_counter()
        if progress is not None and now - last_report > 1.0:
            progress(k / sim_spec.control_rate, k / sim_spec.control_rate / (now - started), recorder.worst_margin())
            last_report = now
    if loop.links_on:
        recorder.links = link_summary(loop.links, sim.view)
    return time.perf_counter() - started, incomplete
