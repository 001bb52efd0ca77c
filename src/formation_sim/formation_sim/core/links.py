"""Links: how each measurement reaches its agent and each wrench the plant (docs/links.md).

A link carries samples of one stream: an agent's relative pose of one neighbour (an edge end), an
agent's velocity, or an agent's wrench on its way to the plant. At control step k (t_k = k / f):

1. **Sampling.** The sensor samples at the first control step at or after each multiple of
   1/rate: at step k when ``floor(k·rate/f) > floor((k−1)·rate/f)`` (every step without a rate).
2. **Loss.** A sample is lost with the loss model's probability: independent, or Gilbert–Elliott
   (a good and a bad state, each with its own loss probability; after each sample the state
   changes with ``p_good_bad`` or ``p_bad_good``; the link starts good).
3. **Delay.** A sample that is not lost arrives ``ceil((delay + jitter)·f)`` steps later (a
   latency of exactly m periods: m steps; 0: the same step). Jitter is drawn per sample: uniform
   on [0, max], or exponential with its mean truncated to [0, max] (inverse CDF).
4. **Hold.** The receiver holds the newest sample it has (by sampling step): a sample that arrives
   after a newer one is dropped (``superseded``). Its age at step k is k minus the held sample's
   step. A measurement older than the agent's ``measurement_timeout`` is missing (the agent's
   fault policy: zero wrench); a wrench older than ``simulation.command_timeout`` is replaced by
   zero, and before the first wrench arrives the plant applies zero.

Every step draws three uniforms per link (loss, state change, jitter), used or not, from a stream
of its own spawned from ``simulation.seed``: the same file and seed give the same deliveries in
every mode, and a link model changes no other draw. Ideal links (every sample, at once, none lost)
hand every step's sample through unchanged, so a file with no link model runs as without this
module (:attr:`formation_core.formation.FormationSpec.has_links`: the runs then skip it altogether).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, cast

import numpy as np

from formation_core.formation import MeasurementLink, SimulatorView, WrenchLink
from formation_core.numba_kernels import formula, kernel
from formation_sim.core.summary import LinkAge, LinkReport, LinkStats, WorstLink

#: columns of :attr:`Links.params`
P_RATIO, P_DELAY, P_JITTER, P_J_MEAN, P_J_MAX, P_LOSS, P_GOOD_BAD, P_BAD_GOOD, P_LOSS_GOOD, P_LOSS_BAD = range(10)
P_TIMEOUT = 10  # the receiver's largest usable age [steps]
N_PARAMS = 11
JITTER_CODES = {"none": 0, "uniform": 1, "exponential": 2}
LOSS_CODES = {"none": 0, "independent": 1, "gilbert_elliott": 2}
#: columns of :attr:`Links.counts`
C_SENT, C_LOST, C_ARRIVED, C_SUPERSEDED, C_EMPTY = range(5)
COUNT_NAMES = ("sent", "lost", "delivered", "superseded", "steps_without_sample")
#: a ratio or delay within this of an integer counts as that integer (float products of decimal rates)
EPS = 1e-9
#: the channels, in the order of a :class:`LinkSet` and of its uniforms
CHANNELS = ("poses", "velocity", "wrench")
#: values a sample carries: a relative pose (p, the message's quaternion, R decoded from it, in range),
#: a twist, a wrench
POSE_WIDTH, TWIST_WIDTH = 17, 6


class Links(NamedTuple):
    """The links of one channel, one row per link, and everything in flight on them."""

    params: np.ndarray  # (n, N_PARAMS)
    values: np.ndarray  # (S, n, W) the samples by sampling step modulo S
    arrive_step: np.ndarray  # (S, n) int: the step a slot of arrivals is for (−1: none)
    arrive_sample: np.ndarray  # (S, n) int: the newest sample arriving then
    arrive_count: np.ndarray  # (S, n) int: how many samples arrive then
    held: np.ndarray  # (n, W) the newest sample received
    held_step: np.ndarray  # (n,) int: its sampling step (−1: none yet)
    bad: np.ndarray  # (n,) bool: Gilbert–Elliott state
    counts: np.ndarray  # (n, 5) int: sent, lost, delivered, superseded, steps without a sample
    ages: np.ndarray  # (n, B) int: steps spent at each age [steps] of the held sample (last bin: B − 1 or more)
    age_max: np.ndarray  # (n,) int: the largest age [steps]
    now: np.ndarray  # (n, W) scratch: this step's samples


class LinkSet(NamedTuple):
    """Every link of a run: relative poses by edge end, velocities and wrenches by agent."""

    poses: Links
    velocity: Links
    wrench: Links
    control_rate: float


@formula
def sampled_at(k, ratio):
    """Whether a sensor of rate ``ratio``·f samples at control step k."""
    if k == 0 or ratio >= 1.0:
        return True
    return math.floor(k * ratio + EPS) > math.floor((k - 1) * ratio + EPS)


@formula
def delay_steps(prm, u, control_rate):
    """Steps from sampling to arrival of one sample: its latency (constant plus jitter drawn from ``u``) in
    control periods, rounded up."""
    extra = 0.0
    if prm[P_JITTER] == 1.0:
        extra = prm[P_J_MAX] * u
    elif prm[P_JITTER] == 2.0:
        mean = prm[P_J_MEAN]
        extra = -mean * math.log(1.0 - u * (1.0 - math.exp(-prm[P_J_MAX] / mean)))
    steps = (prm[P_DELAY] + extra) * control_rate
    return max(0, math.ceil(steps - EPS))


@formula
def lose(links, i, u_loss, u_state):
    """Whether link i loses the sample it takes now (and the Gilbert–Elliott state's change after it)."""
    prm = links.params[i]
    if prm[P_LOSS] == 1.0:
        return u_loss < prm[P_LOSS_GOOD]
    if prm[P_LOSS] == 2.0:
        lost = u_loss < (prm[P_LOSS_BAD] if links.bad[i] else prm[P_LOSS_GOOD])
        if links.bad[i]:
            if u_state < prm[P_BAD_GOOD]:
                links.bad[i] = False
        elif u_state < prm[P_GOOD_BAD]:
            links.bad[i] = True
        return lost
    return False


@formula
def carry(links, k, now, uniforms, control_rate):
    """Step k of every link of a channel: sample ``now`` (n, W), send, deliver, hold, count, and the held
    samples' ages; ``uniforms`` (n, 3) are this step's draws."""
    S = links.values.shape[0]
    W = links.values.shape[2]
    bins = links.ages.shape[1]
    for i in range(links.params.shape[0]):
        prm = links.params[i]
        if sampled_at(k, prm[P_RATIO]):
            links.counts[i, C_SENT] += 1
            if lose(links, i, uniforms[i, 0], uniforms[i, 1]):
                links.counts[i, C_LOST] += 1
            else:
                slot = k % S
                for w in range(W):
                    links.values[slot, i, w] = now[i, w]
                d = k + delay_steps(prm, uniforms[i, 2], control_rate)
                a = d % S
                if links.arrive_step[a, i] != d:
                    links.arrive_step[a, i] = d
                    links.arrive_sample[a, i] = k
                    links.arrive_count[a, i] = 1
                else:
                    links.arrive_sample[a, i] = max(links.arrive_sample[a, i], k)
                    links.arrive_count[a, i] += 1
        a = k % S
        if links.arrive_step[a, i] == k:
            s = links.arrive_sample[a, i]
            count = links.arrive_count[a, i]
            links.counts[i, C_ARRIVED] += count
            if s > links.held_step[i]:
                for w in range(W):
                    links.held[i, w] = links.values[s % S, i, w]
                links.held_step[i] = s
                links.counts[i, C_SUPERSEDED] += count - 1
            else:
                links.counts[i, C_SUPERSEDED] += count
        if links.held_step[i] < 0:
            links.counts[i, C_EMPTY] += 1
        else:
            age = k - links.held_step[i]
            links.ages[i, min(age, bins - 1)] += 1
            links.age_max[i] = max(links.age_max[i], age)


@formula
def usable(links, i, k):
    """Whether link i holds a sample at step k that is not older than its receiver's time-out."""
    return links.held_step[i] >= 0 and k - links.held_step[i] <= links.params[i, P_TIMEOUT]


@formula
def receive_measurements(links, k, uniforms, p_rel, q_rel, R_rel, in_range, v_measured, first_end):
    """Step k's measurements (the sensors' values in p_rel … v_measured) replaced by what each agent holds;
    ``uniforms`` (n_links, 3) are the step's draws of every link (:func:`draw_rows`). A pose older than
    the agent's time-out, or never received, is missing; with its velocity too old or never received,
    all of the agent's poses are (its fault policy answers zero)."""
    poses, velocity = links.poses, links.velocity
    n_ends = p_rel.shape[0]
    n = v_measured.shape[0]
    for e in range(n_ends):
        now = poses.now[e]
        for x in range(3):
            now[x] = p_rel[e, x]
        for x in range(4):
            now[3 + x] = q_rel[e, x]
        for x in range(3):
            for y in range(3):
                now[7 + 3 * x + y] = R_rel[e, x, y]
        now[16] = 1.0 if in_range[e] else 0.0
    for i in range(n):
        for c in range(6):
            velocity.now[i, c] = v_measured[i, c]
    carry(poses, k, poses.now, uniforms[0:n_ends], links.control_rate)
    carry(velocity, k, velocity.now, uniforms[n_ends : n_ends + n], links.control_rate)
    for i in range(n):
        fresh_v = usable(velocity, i, k)
        for c in range(6):
            v_measured[i, c] = velocity.held[i, c]
        for e in range(first_end[i], first_end[i + 1]):
            held = poses.held[e]
            in_range[e] = fresh_v and usable(poses, e, k) and held[16] > 0.5
            for x in range(3):
                p_rel[e, x] = held[x]
            for x in range(4):
                q_rel[e, x] = held[3 + x]
            for x in range(3):
                for y in range(3):
                    R_rel[e, x, y] = held[7 + 3 * x + y]


@formula
def deliver_wrenches(links, k, uniforms, commanded, applied):
    """Step k's commanded wrenches (N, 6) onto the wrench links; ``applied`` receives what the plant applies:
    the newest wrench received, zero before the first and once it is older than the time-out."""
    wrench = links.wrench
    n = commanded.shape[0]
    n_other = uniforms.shape[0] - n
    for i in range(n):
        for c in range(6):
            wrench.now[i, c] = commanded[i, c]
    carry(wrench, k, wrench.now, uniforms[n_other:], links.control_rate)
    for i in range(n):
        fresh = usable(wrench, i, k)
        for c in range(6):
            applied[i, c] = wrench.held[i, c] if fresh else 0.0


@formula
def link_ages_into(links, k, out):
    """Every link's held sample's age at step k [s] into ``out`` (n_links,): poses, velocities, wrenches; NaN
    where nothing is held yet."""
    j = 0
    for ch in (links.poses, links.velocity, links.wrench):
        for i in range(ch.held_step.shape[0]):
            out[j] = np.nan if ch.held_step[i] < 0 else (k - ch.held_step[i]) / links.control_rate
            j += 1


@kernel
def receive_step(links, k, uniforms, p_rel, q_rel, R_rel, in_range, v_measured, first_end):
    """:func:`receive_measurements` from Python (a simulator stepping one control step at a time)."""
    receive_measurements(links, k, uniforms, p_rel, q_rel, R_rel, in_range, v_measured, first_end)


@kernel
def deliver_step(links, k, uniforms, commanded, applied, ages):
    """:func:`deliver_wrenches` from Python, and every link's age after it into ``ages`` (n_links,) [s]
    (one call: each call from Python unpacks every array of the links)."""
    deliver_wrenches(links, k, uniforms, commanded, applied)
    link_ages_into(links, k, ages)


@kernel
def ages_step(links, k, out):
    """:func:`link_ages_into` from Python."""
    link_ages_into(links, k, out)


# --- building ---------------------------------------------------------------------------------


def link_params(link: MeasurementLink | WrenchLink, control_rate: float, timeout: float) -> np.ndarray:
    """One row of :attr:`Links.params` for ``link`` at ``control_rate`` [Hz]; ``timeout`` [s]: the largest
    age its receiver uses."""
    row = np.zeros(N_PARAMS)
    rate = getattr(link, "rate", None)
    row[P_RATIO] = 1.0 if rate is None else min(1.0, rate / control_rate)
    row[P_DELAY] = link.delay
    jitter = getattr(link, "jitter", None)
    if jitter is not None:
        row[P_JITTER] = JITTER_CODES[jitter.model]
        row[P_J_MEAN] = jitter.params.get("mean", 0.0)
        row[P_J_MAX] = jitter.params.get("max", 0.0)
    row[P_LOSS] = LOSS_CODES[link.loss.model]
    params = link.loss.params
    if link.loss.model == "independent":
        row[P_LOSS_GOOD] = params["probability"]
    elif link.loss.model == "gilbert_elliott":
        row[P_GOOD_BAD], row[P_BAD_GOOD] = params["p_good_bad"], params["p_bad_good"]
        row[P_LOSS_GOOD], row[P_LOSS_BAD] = params["loss_good"], params["loss_bad"]
    row[P_TIMEOUT] = math.floor(timeout * control_rate + EPS)
    return row


def longest_delay_steps(params: np.ndarray, control_rate: float) -> int:
    """The most steps any sample of these links can take to arrive."""
    longest = 0
    for row in params:
        worst = row.copy()
        worst[P_JITTER] = 1.0 if row[P_JITTER] else 0.0  # the jitter's largest value, whatever its distribution
        longest = max(longest, delay_steps(worst, 1.0, control_rate))
    return longest


def new_links(params: np.ndarray, width: int, control_rate: float) -> Links:
    """Empty links (nothing sent, nothing held) with these parameters, carrying samples of ``width`` values."""
    n = params.shape[0]
    slots = longest_delay_steps(params, control_rate) + 2
    bins = int(params[:, P_TIMEOUT].max(initial=0)) + slots + 2
    return Links(
        np.ascontiguousarray(params, dtype=np.float64),
        np.zeros((slots, n, width)),
        np.full((slots, n), -1, dtype=np.int64),
        np.full((slots, n), -1, dtype=np.int64),
        np.zeros((slots, n), dtype=np.int64),
        np.zeros((n, width)),
        np.full(n, -1, dtype=np.int64),
        np.zeros(n, dtype=np.bool_),
        np.zeros((n, len(COUNT_NAMES)), dtype=np.int64),
        np.zeros((n, bins), dtype=np.int64),
        np.zeros(n, dtype=np.int64),
        np.zeros((n, width)),
    )


def end_links(view: SimulatorView) -> list[tuple[int, MeasurementLink]]:
    """(observer's index, link) of every edge end, in the controllers' order: agent by agent, its edges in
    file order (formation_core.formation.agent_view); an edge's own link of the end, else the observer's."""
    out = []
    for i, a in enumerate(view.agents):
        for e in view.edges:
            if e.tail == a.id:
                out.append((i, e.links.tail or a.links.poses))
            elif e.head == a.id:
                out.append((i, e.links.head or a.links.poses))
    return out


def first_ends(view: SimulatorView) -> np.ndarray:
    """(N + 1,) int: agent i's edge ends are first_end[i] … first_end[i + 1] − 1."""
    counts = np.bincount([i for i, _ in end_links(view)], minlength=len(view.agents))
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def new_link_set(view: SimulatorView) -> LinkSet:
    """The links of a run of ``view``, nothing in flight."""
    rate = float(view.simulation.control_rate)
    agents = view.agents
    poses = [link_params(link, rate, agents[i].controller.measurement_timeout) for i, link in end_links(view)]
    velocity = [link_params(a.links.velocity, rate, a.controller.measurement_timeout) for a in agents]
    wrench = [link_params(a.links.wrench, rate, view.simulation.command_timeout) for a in agents]
    return LinkSet(
        new_links(np.array(poses).reshape(-1, N_PARAMS), POSE_WIDTH, rate),
        new_links(np.array(velocity), TWIST_WIDTH, rate),
        new_links(np.array(wrench), TWIST_WIDTH, rate),
        rate,
    )


def no_links() -> LinkSet:
    """A stand-in of the same types for a run without a link model (never stepped)."""
    empty = np.zeros((0, N_PARAMS))
    return LinkSet(
        new_links(empty, POSE_WIDTH, 1.0), new_links(empty, TWIST_WIDTH, 1.0), new_links(empty, TWIST_WIDTH, 1.0), 1.0
    )


def n_links(links: LinkSet) -> int:
    """Rows of one step's uniforms: every pose link, then every velocity link, then every wrench link."""
    return sum(ch.params.shape[0] for ch in links[:3])


def link_stream(seed_seq: np.random.SeedSequence) -> np.random.Generator:
    """The links' own stream: the third child of the run's seed sequence (the plant's and the
    measurements' are the first two, so a link model changes no other draw)."""
    return np.random.default_rng(seed_seq.spawn(3)[2])


def draw_rows(rng: np.random.Generator, steps: int, links: LinkSet) -> np.ndarray:
    """(steps, n_links, 3) uniforms in [0, 1): ``steps`` control steps' draws, in stream order."""
    return rng.random((steps, n_links(links), 3))


def channel_rows(links: LinkSet) -> Sequence[tuple[str, int, int]]:
    """(channel, first row, rows) of each channel in a step's uniforms."""
    out, first = [], 0
    for name, ch in zip(CHANNELS, links[:3]):
        out.append((name, first, ch.params.shape[0]))
        first += ch.params.shape[0]
    return out


# --- what a run says about its links ----------------------------------------------------------


def link_names(view: SimulatorView) -> dict[str, list[str]]:
    """Each link's name per channel: ``observer->target`` for a pose, the agent's id for a velocity or wrench."""
    ends = []
    for a in view.agents:
        for e in view.edges:
            if e.tail == a.id:
                ends.append(f"{a.id}->{e.head}")
            elif e.head == a.id:
                ends.append(f"{a.id}->{e.tail}")
    ids = [a.id for a in view.agents]
    return {"poses": ends, "velocity": ids, "wrench": list(ids)}


def _age_stats(ages: np.ndarray, age_max: int, control_rate: float) -> LinkAge:
    """Minimum, median, 99th percentile and maximum [s] of an age histogram (steps spent at each age)."""
    total = int(ages.sum())
    if total == 0:
        return {"min": None, "median": None, "p99": None, "max": None}
    cumulative = np.cumsum(ages)

    def quantile(q: float) -> float:
        return min(int(np.searchsorted(cumulative, q * total)), age_max) / control_rate

    return {
        "min": int(np.flatnonzero(ages)[0]) / control_rate,
        "median": quantile(0.5),
        "p99": quantile(0.99),
        "max": age_max / control_rate,
    }


def _stats(counts: np.ndarray, ages: np.ndarray, age_max: int, control_rate: float) -> LinkStats:
    sent = int(counts[C_SENT])
    return {
        "sent": sent,
        "lost": int(counts[C_LOST]),
        "delivered": int(counts[C_ARRIVED]),
        "superseded": int(counts[C_SUPERSEDED]),
        "steps_without_sample": int(counts[C_EMPTY]),
        "loss_rate": int(counts[C_LOST]) / sent if sent else None,
        "age": _age_stats(ages, age_max, control_rate),
    }


def link_summary(links: LinkSet, view: SimulatorView) -> LinkReport:
    """summary.json's ``links`` (docs/outputs.md): per channel its links' counts together (sent, lost,
    delivered, superseded, steps without a sample, loss rate) and the held samples' ages over every
    control step [s]; each link alone under ``by_link``; and the worst link (the largest 99th
    percentile of age, then the largest loss rate)."""
    rate = links.control_rate
    names = link_names(view)
    per_channel: dict[str, LinkStats] = {}
    by_link: dict[str, dict[str, LinkStats]] = {}
    candidates = []
    for channel, ch in zip(CHANNELS, links[:3]):
        if ch.params.shape[0] == 0:
            continue
        width = ch.ages.shape[1]
        per_channel[channel] = _stats(ch.counts.sum(axis=0), ch.ages.sum(axis=0)[:width], int(ch.age_max.max()), rate)
        by_link[channel] = {}
        for i, name in enumerate(names[channel]):
            stats = _stats(ch.counts[i], ch.ages[i], int(ch.age_max[i]), rate)
            by_link[channel][name] = stats
            p99 = stats["age"]["p99"]
            candidates.append((math.inf if p99 is None else p99, stats["loss_rate"] or 0.0, channel, name))
    worst: WorstLink | None = None
    if candidates:
        p99, loss_rate, channel, name = max(candidates)
        worst = {"channel": channel, "link": name, "age_p99": None if p99 == math.inf else p99, "loss_rate": loss_rate}
    # the channels' keys are CHANNELS' names, known to be a LinkReport's only at run time
    return cast(LinkReport, {**per_channel, "worst": worst, "by_link": by_link})


def link_ages(links: LinkSet, k: int) -> np.ndarray:
    """(n_links,) every link's held sample's age at step k [s] (NaN: none yet), from Python."""
    out = np.zeros(n_links(links))
    ages_step(links, k, out)
    return out
