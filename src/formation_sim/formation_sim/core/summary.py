"""summary.json, typed (docs/outputs.md): what every runner writes at the end of a run.

:class:`RunSummary` holds the keys the run recorder writes for every run (the verdict, the margins
per edge and agent, the clearance, the links, the faults) and, not required, the keys each runner
adds (:class:`RunnerKeys`: the headless runner its controller, a ROS 2 run its timing, security,
witness and launch, an analysis its bag). Times in s, rates in Hz, forces in N, torques in N·m,
latencies in ms where the key says so. A summary read back from a file is JSON: these types say what
it holds when this code wrote it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NotRequired, TypedDict

from formation_core.faults import Faults


class FirstViolation(TypedDict):
    """The first sample outside a funnel: when, which funnel (``kind``), where and which channel."""

    t: float
    kind: str
    channel: str
    edge: NotRequired[str]  # distance and orientation funnels: the edge "tail-head"
    agent: NotRequired[str]  # velocity funnels
    pair: NotRequired[str]  # a contact that fails the run


class EdgeResult(TypedDict):
    """One edge's smallest margins and settling times (None: never inside the steady band)."""

    min_margin_e: float | None
    min_margin_psi: float | None
    settle_time_e: float | None
    settle_time_psi: float | None


class AgentResult(TypedDict):
    """One agent's peak wrench and smallest velocity margin (None: not known, e.g. a bag without it)."""

    peak_force: float
    peak_torque: float
    min_margin_v: float | None


class Contact(TypedDict):
    """Two bodies that touched: their ids, when first, and their smallest clearance [m]."""

    pair: list[str]
    first_t: float
    min: float


class FirstContact(TypedDict):
    t: float
    pair: list[str]


class Clearance(TypedDict):
    """The smallest clearance of any two bodies [m] (None: fewer than two), which pair and when, and
    every contact, with the formation's contact policy (``report`` or ``fail``)."""

    policy: str
    min: float | None
    pair: list[str] | None
    t: float | None
    first_contact: FirstContact | None
    contacts: list[Contact]


class LinkAge(TypedDict):
    """The age [s] of the sample a receiver held at each control step (None: it never held one)."""

    min: float | None
    median: float | None
    p99: float | None
    max: float | None


class LinkStats(TypedDict):
    """One channel's (or one link's) samples and the ages of the samples held."""

    sent: int
    lost: int
    delivered: int
    superseded: int  # arrived after a newer sample
    steps_without_sample: int
    loss_rate: float | None  # None: nothing sent
    age: LinkAge


class WorstLink(TypedDict):
    channel: str
    link: str
    age_p99: float | None
    loss_rate: float


class LatencyReport(TypedDict):
    """Wall time from a step's publication to an agent's answer [ms]."""

    p50: float
    p99: float
    max: float
    samples: int


class LinkReport(TypedDict):
    """summary.json's ``links`` with a link model: per channel, per link (``by_link``), the worst link."""

    poses: NotRequired[LinkStats]
    velocity: NotRequired[LinkStats]
    wrench: NotRequired[LinkStats]
    worst: WorstLink | None
    by_link: dict[str, dict[str, LinkStats]]
    real_latency_ms: NotRequired[LatencyReport | None]  # realtime: the real network under the links


class LagReport(TypedDict):
    """Realtime: how far the simulator's ticks ran behind the wall clock [s]."""

    max: float
    mean: float
    final: float
    late_ticks_fraction: float


class LaunchReport(TypedDict):
    """formation-launch: the ROS environment of the run and where its wall time went [s]."""

    ros_domain_id: int
    discovery_range: str
    transport: str
    discovery: str
    network_namespace: bool
    processes: int
    scheduling: str
    wall_start_s: float | None
    wall_stepping_s: float | None
    wall_stop_s: float | None
    wall_sim_outputs_s: float | None
    wall_figures_s: float | None
    secure: NotRequired[Mapping[str, object]]  # --secure: TLS transport, ports, whether the keys were made for it


#: What an analysed bag says was run (mode, control rate [Hz], duration [s]), where each came from
#: (``from``: per setting "bag" (its custom data), "recording" (the stamps) or "formation file"), the
#: formation file's own values, and every disagreement (``notes``). ``from`` is a Python keyword,
#: hence the functional form.
BagRunSettings = TypedDict(
    "BagRunSettings",
    {
        "mode": str,
        "control_rate": float,
        "duration": float,
        "from": dict[str, str],
        "formation_file": dict[str, str | float | None],
        "notes": list[str],
    },
)


class AgentRerunResult(TypedDict):
    equal: bool
    max_abs_diff: float
    compared: int


class BagReport(TypedDict):
    """formation-analyze: what the bag held and lacked, and how the controllers' re-runs compared."""

    path: str
    recovered_without_metadata: bool
    repaired: str | None
    lost: list[str]
    truncated: bool
    ground_truth_samples: int
    ground_truth_expected: int
    settings: BagRunSettings
    ground_truth_gaps: int
    ground_truth_missing: list[list[float]]
    missing: list[str]
    ground_truth_rate: float | None
    steps_between_ground_truth: int
    topics: dict[str, int]
    log_time: str
    velocity_margins: str
    wrenches_from_rerun: dict[str, int]  # per agent: recorded wrenches missing, taken from its re-run
    recorder_counts: dict[str, object] | None
    rerun: dict[str, AgentRerunResult]
    analysis_time: NotRequired[float]


class RunnerKeys(TypedDict, total=False):
    """The keys a runner adds to the recorder's (docs/outputs.md names each)."""

    outputs: list[str]  # the files written
    controller: str  # headless: sampled or continuous
    physics_rate: float
    source: str  # formation-analyze: "bag"
    bag: BagReport
    # ROS 2 runs (the simulator)
    steps: int
    clock_rate: float
    ground_truth_rate: float
    velocity_margins: str
    security: Mapping[str, object]  # formation_deploy.publisher_watch's report, merged over processes
    witness: Mapping[str, object]  # how each agent's answers were judged in lockstep
    last_answer_t: dict[str, float | None]
    resends: int
    duplicate_answers: int
    latency_ms: LatencyReport
    on_time_fraction: dict[str, float]
    on_time_fraction_all: float
    answered_fraction_all: float
    realtime_lag_s: LagReport
    discovery_s: float
    missing: list[str]  # agents that never matched
    wrong_answers: list[str]  # agents the witness refused
    recorder: Mapping[str, object]  # the simulator's bag: messages received, written, not recorded
    # formation-launch
    launch: LaunchReport
    agent_faults_unknown: list[str]


class RunSummary(RunnerKeys):
    """summary.json: the recorder's keys (every run), then the runner's (:class:`RunnerKeys`)."""

    formation: str
    formation_file: str
    mode: str
    control_rate: float
    verdict: str  # PASS, FAIL or INCOMPLETE
    incomplete_reason: str | None
    exit_status: int
    requested_duration: float | None
    duration: float | None
    samples: int
    wall_time: float | None
    real_time_factor: float | None
    funnels_held: bool | None  # None: INCOMPLETE without a violation
    first_violation: FirstViolation | None
    worst_margin: float
    faults: Faults
    clearance: Clearance
    links: LinkReport | None
    edges: dict[str, EdgeResult]
    agents: dict[str, AgentResult]
