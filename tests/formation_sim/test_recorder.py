"""The judge on hand-built trajectories: exact first violation, margins and settle times, verdicts.

Every trajectory starts from the formation at rest in its desired shape (e_k = 0, ψ_k = 0 on every
edge: margin 1 everywhere), and one edge or agent is pushed across one funnel at one sample.
Expected values are computed here from the formation's numbers with the paper's formulas.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from formation_core.formation import FormationSpec
from formation_core.spec import load_formation
from formation_core.verdict import ExitCode, Incomplete
from formation_sim.core.judge import Judge, judge
from formation_sim.core.loop import initial_rho_v0
from formation_sim.core.rates import rate_needs
from formation_sim.core.recorder import RunRecorder
from formation_sim.views.outputs import format_summary, tls_reason, verdict_line, write_outputs

pytestmark = pytest.mark.numeric

T = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
#: the margins are formed from e/ρ_e with a few float operations: equal to 1e-12
TOL = 1e-12


@pytest.fixture(scope="module")
def spec(paper_path_module: Path) -> FormationSpec:
    return load_formation(paper_path_module)


@pytest.fixture(scope="module")
def paper_path_module() -> Path:
    return Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


def rho_e(spec: FormationSpec, k: int, t: float) -> float:
    """Normalised ρ_e(t) = (1 − ρ∞/C_max)·exp(−l t) + ρ∞/C_max (docs/controller.md, "Normalisation of ρ_e")."""
    e = spec.edges[k]
    floor = e.rho_e_inf / max(e.c_col, e.c_con)
    return (1.0 - floor) * math.exp(-e.decay_e * t) + floor


def rho_psi(spec: FormationSpec, k: int, t: float) -> float:
    e = spec.edges[k]
    return (e.rho_psi_0 - e.rho_psi_inf) * math.exp(-e.decay_psi * t) + e.rho_psi_inf


def rot_z(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def desired_shape(spec: FormationSpec) -> tuple[np.ndarray, np.ndarray]:
    """p (N,3), R (N,3,3) with every edge at e = 0 and ψ = 0 (heads placed along distinct axes)."""
    index = {a.id: a.index for a in spec.agents}
    n = len(spec.agents)
    p = np.zeros((n, 3))
    R = np.zeros((n, 3, 3))
    R[0] = np.eye(3)
    placed = {0}
    directions = [np.array(d, dtype=float) for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (-1, 0, 0), (0, -1, 0))]
    while len(placed) < n:
        for k, e in enumerate(spec.edges):
            i, j = index[e.tail], index[e.head]
            if i in placed and j not in placed:
                # ψ = ½ tr(I − R_desᵀ R_jᵀ R_i) = 0  ⇔  R_j = R_i R_desᵀ
                p[j] = p[i] + e.d_des * directions[k % len(directions)]
                R[j] = R[i] @ e.R_des.T
                placed.add(j)
            elif j in placed and i not in placed:
                p[i] = p[j] - e.d_des * directions[k % len(directions)]
                R[i] = R[j] @ e.R_des
                placed.add(i)
    return p, R


def trajectory(spec: FormationSpec) -> tuple[np.ndarray, np.ndarray]:
    p, R = desired_shape(spec)
    return np.repeat(p[None], len(T), axis=0), np.repeat(R[None], len(T), axis=0)


def set_distance_error(spec: FormationSpec, p: np.ndarray, k: int, e_k: float) -> None:
    """Move edge k's head along the edge so that ‖p_head − p_tail‖² − d² = e_k."""
    edge = spec.edges[k]
    i, j = spec.agent(edge.tail).index, spec.agent(edge.head).index
    u = (p[j] - p[i]) / np.linalg.norm(p[j] - p[i])
    p[j] = p[i] + math.sqrt(edge.d_des**2 + e_k) * u


def set_orientation_error(spec: FormationSpec, R: np.ndarray, k: int, psi: float) -> None:
    """R_head = R_tail R_desᵀ Rz(θ) gives ψ = 1 − cos θ."""
    edge = spec.edges[k]
    i, j = spec.agent(edge.tail).index, spec.agent(edge.head).index
    R[j] = R[i] @ edge.R_des.T @ rot_z(math.acos(1.0 - psi))


def test_desired_shape_has_margin_one_everywhere(spec: FormationSpec) -> None:
    """The reference trajectory: every edge at e = 0, ψ = 0: margins exactly 1, settled from t = 0, PASS."""
    p, R = trajectory(spec)
    j = judge(spec, T, p, R)
    assert j.first_violation is None
    np.testing.assert_allclose(j.min_margin_e, 1.0, atol=TOL)
    np.testing.assert_allclose(j.min_margin_psi, 1.0, atol=TOL)
    assert j.settle_e == [0.0] * len(spec.edges) and j.settle_psi == [0.0] * len(spec.edges)


def test_connectivity_crossed_from_above(spec: FormationSpec) -> None:
    """e_1 above C_con ρ_e at t = 0.2 s only: distance, edge 1-2, connectivity, margin 1 − 1.01."""
    p, R = trajectory(spec)
    edge = spec.edges[0]
    e_k = 1.01 * edge.c_con * rho_e(spec, 0, 0.2)
    set_distance_error(spec, p[2], 0, e_k)
    j = judge(spec, T, p, R)
    assert j.first_violation is not None
    assert j.first_violation.as_dict() == {"t": 0.2, "kind": "distance", "edge": edge.name, "channel": "connectivity"}
    assert j.min_margin_e[0] == pytest.approx(-0.01, abs=1e-9)  # sqrt then square: 1e-9 of e_k
    np.testing.assert_allclose(j.min_margin_e[1:], 1.0, atol=TOL)
    # back at e = 0 from t = 0.3 s: settled since then (the band is [−C_col, C_con]·ρ∞/C_max)
    assert j.settle_e[0] == 0.3 and j.settle_e[1:] == [0.0] * (len(spec.edges) - 1)


def test_collision_crossed_from_below(spec: FormationSpec) -> None:
    """e_2 below −C_col ρ_e from t = 0.3 s on: distance, edge 1-3, collision, margin 1 − 1.02, never settled."""
    p, R = trajectory(spec)
    edge = spec.edges[1]
    for s in (3, 4):
        set_distance_error(spec, p[s], 1, -1.02 * edge.c_col * rho_e(spec, 1, T[s]))
    j = judge(spec, T, p, R)
    assert j.first_violation.as_dict() == {"t": 0.3, "kind": "distance", "edge": edge.name, "channel": "collision"}
    assert j.min_margin_e[1] == pytest.approx(-0.02, abs=1e-9)  # sqrt then square, as above
    assert j.settle_e[1] is None  # outside the band at the last sample


def test_orientation_past_rho_psi(spec: FormationSpec) -> None:
    """ψ_3 = 1.05 ρ_ψ(0.1 s): orientation, edge 3-4, channel psi, margin −0.05."""
    p, R = trajectory(spec)
    edge = spec.edges[2]
    set_orientation_error(spec, R[1], 2, 1.05 * rho_psi(spec, 2, 0.1))
    j = judge(spec, T, p, R)
    assert j.first_violation.as_dict() == {"t": 0.1, "kind": "orientation", "edge": edge.name, "channel": "psi"}
    assert j.min_margin_psi[2] == pytest.approx(-0.05, abs=1e-9)  # acos then cos
    assert j.settle_psi[2] == 0.2


def test_settle_time_is_the_entry_into_the_steady_band(spec: FormationSpec) -> None:
    """ψ_4 at twice its steady bound ρ_ψ∞ until 0.2 s (inside the funnel), half of it after: settled at 0.3 s."""
    p, R = trajectory(spec)
    edge = spec.edges[3]
    for s in range(len(T)):
        psi = 2.0 * edge.rho_psi_inf if T[s] <= 0.2 else 0.5 * edge.rho_psi_inf
        assert psi < rho_psi(spec, 3, T[s])  # still inside the funnel: no violation
        set_orientation_error(spec, R[s], 3, psi)
    j = judge(spec, T, p, R)
    assert j.first_violation is None
    assert j.settle_psi[3] == 0.3
    expected = min(1.0 - (2.0 * edge.rho_psi_inf) / rho_psi(spec, 3, t) for t in T[:3])
    assert j.min_margin_psi[3] == pytest.approx(expected, abs=1e-9)  # acos then cos, as above


def test_settle_times_of_a_stack_are_the_settle_rule_folded_per_sample(spec: FormationSpec) -> None:
    """Judge's settle times after stacks of samples (split anywhere) equal :func:`settle` applied sample by
    sample: one rule (the compiled loop's) in both forms. Seeded random inside/outside sequences."""
    from formation_sim.core.judge import settle

    rng = np.random.default_rng(3)
    K = len(spec.edges)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        t = np.arange(n) * 0.1
        inside = rng.random((n, K)) < 0.7
        j = Judge(spec)
        e = np.where(inside, 0.5 * (j.band_lo + j.band_hi), j.band_hi + 1.0)  # (n, K): in or out of the band
        psi = np.zeros((n, K))
        cuts = sorted(rng.choice(np.arange(1, n), size=min(n - 1, 3), replace=False).tolist()) if n > 1 else []
        for part in np.split(np.arange(n), cuts):
            j._settle(t[part], e[part], psi[part])
        for k in range(K):
            folded = np.nan
            for a, b in zip(t, inside[:, k]):
                folded = settle(folded, float(a), bool(b))
            assert j.settle_e[k] == (None if np.isnan(folded) else folded), (k, inside[:, k])
            assert j.settle_psi[k] == 0.0  # ψ inside from the first sample


def test_velocity_channel_and_edge_first_at_one_sample(spec: FormationSpec) -> None:
    """Agent 4's wy margin ≤ 0 at 0.1 s: velocity, agent 4, wy; an edge violated at the same sample wins."""
    p, R = trajectory(spec)
    n = len(spec.agents)
    margin_v = np.full((len(T), n, 6), 0.5)
    i4 = spec.agent("4").index
    margin_v[1, i4, 4] = -0.25
    j = judge(spec, T, p, R, margin_v)
    assert j.first_violation.as_dict() == {"t": 0.1, "kind": "velocity", "agent": "4", "channel": "wy"}
    assert j.min_margin_v[i4] == -0.25 and j.min_margin_v[spec.agent("1").index] == 0.5
    set_distance_error(spec, p[1], 0, 1.5 * spec.edges[0].c_con * rho_e(spec, 0, 0.1))
    assert judge(spec, T, p, R, margin_v).first_violation.kind == "distance"


def test_streaming_judge_equals_the_array_judge(spec: FormationSpec) -> None:
    """Fed one sample at a time, the judge finds the same violation, margins and settle times."""
    p, R = trajectory(spec)
    set_distance_error(spec, p[3], 0, 1.2 * spec.edges[0].c_con * rho_e(spec, 0, 0.3))
    set_orientation_error(spec, R[2], 2, 0.5 * rho_psi(spec, 2, 0.2))
    whole = judge(spec, T, p, R)
    stream = Judge(spec)
    for s in range(len(T)):
        stream.update(float(T[s]), p[s], R[s])
    assert stream.first_violation == whole.first_violation
    np.testing.assert_array_equal(stream.min_margin_e, whole.min_margin_e)
    np.testing.assert_array_equal(stream.min_margin_psi, whole.min_margin_psi)
    assert stream.settle_e == whole.settle_e and stream.settle_psi == whole.settle_psi


def _recorder(spec: FormationSpec, n: int, **kw) -> RunRecorder:
    rec = RunRecorder(spec, control_rate=10.0)
    p, R = trajectory(spec)
    for s in range(n):
        rec.add(float(T[s]), p[s], R[s], np.zeros((len(spec.agents), 6)), np.ones((len(spec.agents), 6)), **kw)
    return rec


def test_verdicts_and_strict_json(spec: FormationSpec, tmp_path: Path) -> None:
    """PASS over the whole duration; INCOMPLETE (exit 4) short of it or (130) interrupted; no NaN/Infinity."""
    full = _recorder(spec, len(T))
    s = full.summary(wall_time=1.0, requested_duration=0.4)
    assert (s["verdict"], s["exit_status"], s["funnels_held"]) == ("PASS", 0, True)
    # velocity margins unknown (no shadow controllers): null, not Infinity
    assert all(a["min_margin_v"] is None for a in s["agents"].values())
    short = _recorder(spec, 3).summary(wall_time=1.0, requested_duration=0.4)
    assert (short["verdict"], short["exit_status"], short["funnels_held"]) == ("INCOMPLETE", 4, None)
    assert short["incomplete_reason"] == "duration not reached: t=0.2 s of 0.4 s"
    stopped = _recorder(spec, 3).summary(
        wall_time=1.0, requested_duration=0.4, incomplete=Incomplete(ExitCode.INTERRUPTED, "interrupted (SIGINT)")
    )
    assert (stopped["verdict"], stopped["exit_status"]) == ("INCOMPLETE", 130)
    write_outputs(tmp_path, full, s, plots=False)
    text = (tmp_path / "summary.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text)["outputs"] == ["trajectory.npz", "summary.json"]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["summary.json", "trajectory.npz"]  # no temporaries


#: summary.json ``security`` of a realtime run with an outsider on agent 3's wrench (report policy)
SECURITY = {
    "policy": "report",
    "intruders": [
        {
            "topic": "/agent_3/wrench",
            "agent": "3",
            "node": "/outsider",
            "gid": "010f2a",
            "first_seen": 1.0,
            "last_seen": 4.0,
            "reason": "unexpected node",
        }
    ],
    "intruders_per_agent": {"3": 1},
    "refused_messages": {},
    "applied_while_intruder": {"/agent_3/wrench": 7},
    "withdrawn": [],
}


def test_an_intruder_makes_a_pass_untrusted_input(spec: FormationSpec) -> None:
    """Every funnel held beside an intruder: INCOMPLETE, exit 4, the reason and verdict line name it."""
    s = _recorder(spec, len(T)).summary(wall_time=1.0, requested_duration=0.4, extra={"security": SECURITY})
    assert (s["verdict"], s["exit_status"], s["funnels_held"]) == ("INCOMPLETE", 4, None)
    assert s["incomplete_reason"] == (
        "untrusted input: 1 intruder(s) (policy report): node /outsider gid 010f2a on /agent_3/wrench "
        "(7 applied, 0 refused)"
    )
    assert verdict_line(s).splitlines() == [
        "INCOMPLETE: untrusted input: 1 intruder(s) (policy report) "
        "(no violation in the 0.4 s checked, worst margin 1)",
        "  intruder: node /outsider gid 010f2a on /agent_3/wrench (7 applied, 0 refused)",
    ]
    assert "  intruder: node /outsider" in format_summary(s)
    clean = _recorder(spec, len(T)).summary(
        wall_time=1.0, requested_duration=0.4, extra={"security": {**SECURITY, "intruders": []}}
    )
    assert (clean["verdict"], clean["exit_status"]) == ("PASS", 0)


def test_an_intruder_turns_a_violation_into_untrusted_input(spec: FormationSpec) -> None:
    """A violation beside an intruder (refuse: the agent's own wrenches refused) is no FAIL: INCOMPLETE, exit 4;
    an interrupted run keeps 130."""
    p, R = trajectory(spec)
    set_distance_error(spec, p[2], 0, 1.01 * spec.edges[0].c_con * rho_e(spec, 0, 0.2))
    refused = {**SECURITY, "policy": "refuse", "refused_messages": {"/agent_3/wrench": 268}}
    refused["applied_while_intruder"] = {}

    def run(incomplete: Incomplete | None = None) -> dict:
        rec = RunRecorder(spec, control_rate=10.0)
        for s in range(len(T)):
            rec.add(float(T[s]), p[s], R[s], np.zeros((len(spec.agents), 6)), np.ones((len(spec.agents), 6)))
        return rec.summary(wall_time=1.0, requested_duration=0.4, incomplete=incomplete, extra={"security": refused})

    s = run()
    assert (s["verdict"], s["exit_status"]) == ("INCOMPLETE", 4)
    assert s["first_violation"]["t"] == 0.2  # kept: the data shows it, the verdict does not rest on it
    assert "(0 applied, 268 refused)" in s["incomplete_reason"]
    line = verdict_line(s).splitlines()[0]
    assert line.startswith("INCOMPLETE: untrusted input: 1 intruder(s) (policy refuse) (a violation seen at t=0.2000 s")
    stopped = run(Incomplete(ExitCode.INTERRUPTED, "interrupted (SIGINT)"))
    assert (stopped["verdict"], stopped["exit_status"]) == ("INCOMPLETE", 130)
    assert stopped["incomplete_reason"].startswith("interrupted (SIGINT); untrusted input: ")


def test_failed_tls_handshakes_are_named_under_every_verdict(spec: FormationSpec) -> None:
    """A secure run's failed TLS handshakes (security.tls_handshake_failures): a line per process under
    PASS, and named in an INCOMPLETE reason with the last error and what to check."""
    failures = {"agent_4": {"count": 8, "last": "Handshake failed: certificate verify failed"}}
    s = _recorder(spec, len(T)).summary(
        wall_time=1.0, requested_duration=0.4, extra={"security": {"tls_handshake_failures": failures}}
    )
    assert s["verdict"] == "PASS"  # a refused outsider is no reason to doubt the run's evidence
    assert verdict_line(s).splitlines()[1:] == [
        "  TLS: agent_4 failed 8 handshake(s), the last: Handshake failed: certificate verify failed"
    ]
    reason = tls_reason(s["security"])
    assert reason == (
        "TLS handshake failed (agent_4 8x in their logs; Handshake failed: certificate verify failed): a "
        "certificate the others refuse (another CA, expired or not yet valid; formation-keys check)"
    )
    assert tls_reason({"intruders": []}) is None and tls_reason(None) is None


def test_faults_are_counted_with_first_and_last(spec: FormationSpec) -> None:
    """Every fault is counted per agent and kind; the first and last times are kept; none is a violation."""
    rec = _recorder(spec, len(T))
    for t in (0.1, 0.2, 0.3):
        rec.fault(t, "zero_wrench", "2", f"last wrench {t:.1f} s old")
    rec.fault(0.2, "measurement", "3", "1")
    s = rec.summary(wall_time=1.0, requested_duration=0.4)
    assert s["verdict"] == "PASS"
    assert s["faults"]["2"]["zero_wrench"] == {
        "count": 3,
        "first_t": 0.1,
        "last_t": 0.3,
        "first": "last wrench 0.1 s old",
        "last": "last wrench 0.3 s old",
    }
    assert s["faults"]["3"]["measurement"]["count"] == 1


def test_rate_need_matches_the_closed_form(spec: FormationSpec) -> None:
    """docs/controller.md, "Sampled-data": f_s > 2γ / (M_ll ρ_v,l(t)²), largest channel, at t = 0 and at the end."""
    duration = spec.simulation.duration
    for need in rate_needs(spec, initial_rho_v0(spec)):
        a = spec.agent(need.agent_id)
        vf = a.controller.velocity_funnel
        assert np.allclose(a.dynamics.inertia, np.diag(np.diag(a.dynamics.inertia)))  # closed form: diagonal M
        m_ll = np.array([a.dynamics.mass] * 3 + list(np.diag(a.dynamics.inertia)))
        rho_end = (need.rho_v0 - np.array(vf.rho_inf)) * np.exp(-np.array(vf.decay) * duration) + np.array(vf.rho_inf)
        gamma = a.controller.gamma
        # a few roundings and one exp on each side: some 1e-15 relative
        assert need.at_start == pytest.approx(max(2 * gamma / (m_ll * need.rho_v0**2)), rel=1e-12)
        # ρ_v decreases monotonically: the need is largest at the end (rate_needs samples 401 times)
        assert need.at_end == pytest.approx(max(2 * gamma / (m_ll * rho_end**2)), rel=1e-12)


def test_recorder_queue_equals_one_check_per_sample(spec: FormationSpec) -> None:
    """RunRecorder.add queues samples and checks CHECK_BATCH at a time: across batch boundaries, with
    wrenches given late (set_inputs), results read mid-run (also between a sample and its wrenches),
    every figure equals a per-sample check (exactly: the same numpy operations on the same numbers)."""
    from formation_sim.core.recorder import CHECK_BATCH

    rng = np.random.default_rng(7)
    n_agents, steps = len(spec.agents), 2 * CHECK_BATCH + 9
    assert CHECK_BATCH + 3 < 90 < steps
    t = np.arange(steps) * 1e-3
    p0, R0 = trajectory(spec)
    p = p0[0] + rng.normal(scale=0.3, size=(steps, n_agents, 3))  # some samples leave a funnel
    R = np.repeat(R0[:1], steps, axis=0)
    v = rng.normal(size=(steps, n_agents, 6))
    u = rng.normal(scale=50.0, size=(steps, n_agents, 6))
    margin_v = rng.uniform(-0.2, 1.0, size=(steps, n_agents, 6))
    rec = RunRecorder(spec, record_every=10, control_rate=1000.0)
    stream = Judge(spec)
    for k in range(steps):
        if k == 90:  # a result read between a sample (a kept row: record_every 10) and its wrenches
            rec.add(float(t[k]), p[k], R[k], v[k], None, margin_v[k])
            stream.update(float(t[k]), p[k], R[k], margin_v[k])
            assert rec.first_violation == stream.first_violation
            rec.set_inputs(u[k])
            continue
        rec.add(float(t[k]), p[k], R[k], v[k], None, margin_v[k])
        rec.set_inputs(u[k])
        stream.update(float(t[k]), p[k], R[k], margin_v[k])
        if k == CHECK_BATCH + 3:  # a result read mid-run flushes a partial batch
            assert rec.worst_margin() == stream.worst_margin()
    assert rec.samples == steps and rec.t_last == t[-1]
    assert rec.first_violation == stream.first_violation and stream.first_violation is not None
    for name in ("min_margin_e", "min_margin_psi", "min_margin_v"):
        np.testing.assert_array_equal(getattr(rec.judge, name), getattr(stream, name))
    assert rec.judge.settle_e == stream.settle_e and rec.judge.settle_psi == stream.settle_psi
    np.testing.assert_array_equal(rec.peak_force, np.linalg.norm(u[..., :3], axis=2).max(axis=0))
    np.testing.assert_array_equal(rec.peak_torque, np.linalg.norm(u[..., 3:], axis=2).max(axis=0))
    rows = rec.arrays()
    kept = np.arange(0, steps, 10)
    np.testing.assert_array_equal(rows["t"], t[kept])
    np.testing.assert_array_equal(rows["p"], p[kept])
    np.testing.assert_array_equal(rows["u"], u[kept])
    e, psi = stream.edges.errors(p[kept], R[kept])
    np.testing.assert_array_equal(rows["e"], e)
    np.testing.assert_array_equal(rows["psi"], psi)


def test_set_inputs_needs_a_sample(spec: FormationSpec) -> None:
    rec = RunRecorder(spec)
    with pytest.raises(RuntimeError, match="no sample added yet"):
        rec.set_inputs(np.zeros((len(spec.agents), 6)))


# --- the judge at its boundaries: each test kills the mutant it is named after (tests/mutants.py) --------


def on_the_connectivity_bound(spec: FormationSpec, p: np.ndarray, R: np.ndarray) -> None:
    """Move edge 0's head along +x from its tail (at the origin) to a float distance whose distance margin
    at t = 0, by the judge's own formulas, is exactly 0: e exactly on C_con·ρ_e(0) (at t = 0 every exp is 1
    exactly, so the numpy and the compiled forms agree to the bit)."""
    edges = Judge(spec).edges
    i, j = edges.tail[0], edges.head[0]
    assert np.all(p[i] == 0.0) and p[j][0] > 0 and p[j][1] == p[j][2] == 0.0  # desired_shape: edge 0 along +x
    d = math.sqrt(spec.edges[0].d_des ** 2 + spec.edges[0].c_con * rho_e(spec, 0, 0.0))
    for step in sorted(range(-400, 401), key=abs):  # the floats nearest the bound first
        q = p.copy()
        q[j, 0] = d + step * math.ulp(d)
        e, psi = edges.errors(q, R)
        if edges.margins(0.0, e, psi)[3][0] == 0.0:
            p[j, 0] = q[j, 0]
            return
    raise AssertionError("no float distance puts edge 0 exactly on its connectivity bound")


def test_mutant_violation_at_margin_below_zero__an_error_exactly_on_a_funnel_bound_is_a_violation(
    spec: FormationSpec,
) -> None:
    """The funnel rule is margin ≤ 0, not < 0: e exactly on C_con·ρ_e at t = 0 is the first violation
    (numpy judge), and the run core's step check (the same rule, here as Python) leaves the funnel there."""
    from formation_agent.controller import MARGIN_V, OUT_COLUMNS
    from formation_sim.core.judge import outside
    from formation_sim.core.loop import check_step, new_buffers, new_watch

    assert outside(0.0) and outside(-0.0) and not outside(5e-324)
    p, R = trajectory(spec)
    on_the_connectivity_bound(spec, p[0], R[0])
    j = judge(spec, T, p, R)
    assert j.min_margin_e[0] == 0.0
    assert j.first_violation is not None
    edge = spec.edges[0].name
    assert j.first_violation.as_dict() == {"t": 0.0, "kind": "distance", "edge": edge, "channel": "connectivity"}
    n_agents = len(spec.agents)
    watch = new_watch(spec, Judge(spec))
    out = np.zeros((n_agents, OUT_COLUMNS))
    out[:, MARGIN_V : MARGIN_V + 6] = 1.0  # velocity margins well inside
    assert check_step(watch, new_buffers(1, n_agents, 0, len(spec.edges)), 0, 0.0, p[0], R[0], out)
    assert watch.checked.min_margin_e[0] == 0.0
    watch = new_watch(spec, Judge(spec))
    assert not check_step(watch, new_buffers(1, n_agents, 0, len(spec.edges)), 0, 0.0, p[1], R[1], out)


def test_mutant_velocity_margin_update_below_zero__a_velocity_margin_exactly_zero_is_a_violation(
    spec: FormationSpec,
) -> None:
    """Velocity margins known between samples (Judge.update_velocity): a channel exactly on its bound is
    the first violation, named by agent and channel; a margin just above 0 is not."""
    rec = RunRecorder(spec, control_rate=100.0)
    margin_v = np.ones((len(spec.agents), 6))
    margin_v[2, 4] = 5e-324  # the smallest positive margin: inside
    rec.update_velocity(0.01, margin_v)
    assert rec.first_violation is None
    margin_v[2, 4] = 0.0
    rec.update_velocity(0.02, margin_v)
    assert rec.first_violation is not None
    assert rec.first_violation.as_dict() == {"t": 0.02, "kind": "velocity", "agent": spec.agents[2].id, "channel": "wy"}
    assert rec.min_margin_v[2] == 0.0


def test_mutant_duration_short_by_one_and_a_half_periods__a_run_one_control_step_short_is_incomplete(
    spec: FormationSpec,
) -> None:
    """A run is complete within half a control period of the requested duration: its last sample one
    control step (10 ms at 100 Hz) short is INCOMPLETE (exit 3); 0.4 of a step short is complete (PASS)."""
    p, R = desired_shape(spec)
    v, u = np.zeros((len(spec.agents), 6)), np.zeros((len(spec.agents), 6))

    def outcome(t_last: float):
        rec = RunRecorder(spec, control_rate=100.0)
        for t in (0.0, 0.5, t_last):
            rec.add(t, p, R, v, u)
        return rec.outcome(1.0)

    short = outcome(0.99)
    assert short.exit_code == ExitCode.INCOMPLETE and "duration not reached" in short.reason
    assert outcome(0.996).exit_code == ExitCode.PASS
    assert outcome(1.0).exit_code == ExitCode.PASS
