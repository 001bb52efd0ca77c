"""Lockstep bags without ROS: the headless closed loop, with every message written to a bag.

A test fixture, for tests and benchmarks (benchmarks/bag_bench.py) of the analysis and the re-run
while no ROS run is at hand. Each control step k writes, in this order,
what the ROS 2 lockstep run publishes: ``/clock``,
``/formation/ground_truth``, every relative pose, every velocity (all stamped with step k's stamp),
then every agent's wrench with the same stamp. Each agent's controller computes from the *decoded*
messages (as the agent node decodes them) at the stamp's time, so the recorded wrenches are what an
agent node would publish; the agents are stepped by
:class:`formation_sim.core.team.AgentTeam`, with the fault policy of every other run. Log times are
synthetic: ``wall_step`` seconds per step from ``start_ns``, ``message_spacing`` apart within a step.
With ``display_every=N`` every N-th step also carries what a run's bag holds besides: an (empty)
/diagnostics array and /formation/markers and /formation/funnels messages, not analysed.

:func:`write_run_bag` returns the run's own summary (a RunRecorder filled as run_headless fills
it), which ``formation-analyze`` must reproduce from the bag.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formation_bag import messages as m
from formation_bag.contract import KEY_FORMATION_FILE, KEY_FORMATION_YAML
from formation_bag.writer import SegmentedBagWriter, make_qos
from formation_core.formation import FormationSpec, simulator_view
from formation_msgs_py import topics
from formation_sim.core.measurement import measurement_ends
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam


@dataclass
class SynthResult:
    summary: dict[str, Any]
    recorder: RunRecorder
    messages: int
    steps: int


def write_run_bag(
    spec: FormationSpec,
    bag: str | Path,
    *,
    formation_text: str | None = None,
    storage: str = "mcap",
    steps: int | None = None,
    segment_seconds: float | None = 2.0,
    wall_step: float = 1e-3,
    message_spacing: float = 1e-6,
    start_ns: int = 1_700_000_000 * m.NS_PER_S,
    stop_on_violation: bool = False,
    display_every: int | None = None,
) -> SynthResult:
    """Run ``spec`` (sampled control, lockstep) and record every docs/topics.md message in ``bag``."""
    sim_spec = spec.simulation
    sim = Simulation(simulator_view(spec))
    team = AgentTeam(spec)
    ids = [a.id for a in spec.agents]
    n_steps = round(sim_spec.duration * sim_spec.control_rate) if steps is None else steps
    record_every = max(1, round(sim_spec.control_rate / sim_spec.record_rate))
    recorder = RunRecorder(spec, record_every=record_every, mode="lockstep", control_rate=sim_spec.control_rate)
    custom = {
        "mode": "lockstep",
        "control_rate": repr(float(sim_spec.control_rate)),
        "duration": repr(n_steps / sim_spec.control_rate),
        "writer": "tests/formation_bag/synth.py",
    }
    if formation_text is not None:
        custom[KEY_FORMATION_YAML] = formation_text
        custom[KEY_FORMATION_FILE] = Path(spec.source).name
    enc = m.Encoder()
    gt_topic = m.absolute(topics.GROUND_TRUTH)
    edges = [(e.tail, e.head) for e in spec.edges]
    links = [(e.tail, e.head) for e in spec.edges] + [(e.head, e.tail) for e in spec.edges]
    ends = measurement_ends(simulator_view(spec))
    end_of = {pair: k for k, pair in enumerate(zip(ends.observer, ends.target))}
    count = 0
    started = time.perf_counter()
    with SegmentedBagWriter(bag, storage=storage, segment_seconds=segment_seconds, custom_data=custom) as w:
        display = {m.DIAGNOSTIC_ARRAY, m.MARKER_ARRAY, m.FLOAT64_MULTI_ARRAY}
        display_topics = {}
        for name, msgtype in m.formation_topics(ids, edges).items():
            if msgtype in display:
                display_topics[name] = msgtype
                if display_every is None:
                    continue  # not synthesised
            w.add_topic(name, msgtype, (make_qos(depth=1 if name == topics.CLOCK else 10),))
        step_ns = round(wall_step * m.NS_PER_S)
        space_ns = max(1, round(message_spacing * m.NS_PER_S))
        for k in range(n_steps + 1):
            meas = sim.sense()
            stamp = meas.ns
            log = start_ns + k * step_ns

            def put(topic: str, data: bytes) -> None:
                nonlocal log, count
                w.write(topic, log, data)
                log += space_ns
                count += 1

            s = sim.state
            put(topics.CLOCK, enc.clock(stamp))
            put(gt_topic, enc.poses(stamp, s.p.tolist(), s.R.tolist()))
            p_rel, R_rel = meas.p_rel.copy(), meas.R_rel.copy()
            for i, j in links:
                end = end_of[(i, j)]
                if not meas.in_range[end]:
                    continue
                data = enc.relative_pose(stamp, i, meas.p_rel[end], meas.q_rel[end])
                put(m.absolute(topics.relative_pose(i, j)), data)
                p_rel[end], R_rel[end] = m.decode_relative_pose(m.deserialize(data, m.POSE_STAMPED))
            vels = []
            for idx, a in enumerate(ids):
                data = enc.twist(stamp, a, meas.velocities[idx].tolist())
                put(m.absolute(topics.velocity(a)), data)
                vels.append(m.decode_twist(m.deserialize(data, m.TWIST_STAMPED)))
            received = meas.received(stamp, p_rel, R_rel, np.array(vels, dtype=np.float64))
            t = meas.t
            u, margin_v, errors = team.evaluate(received, recorder)
            for a, wrench in zip(ids, u.tolist()):
                put(m.absolute(topics.wrench(a)), enc.wrench(stamp, a, wrench))
            if display_every is not None and k % display_every == 0:
                for name, msgtype in display_topics.items():
                    put(name, enc.empty(stamp, msgtype))
            recorder.add(t, s.p, s.R, s.v, u, margin_v)
            team.note_errors(t, errors, recorder)
            if k == n_steps or (stop_on_violation and recorder.first_violation is not None):
                break
            sim.advance(u)
    wall = time.perf_counter() - started
    summary = recorder.summary(
        wall_time=wall,
        requested_duration=sim_spec.duration,
        extra={"controller": "sampled", "physics_rate": sim_spec.physics_rate},
    )
    return SynthResult(summary, recorder, count, k + 1)
