"""What a host holds in realtime: the CPU per tick of a formation's processes, from its messages.

A realtime run is one simulator process and one process per agent. Per control tick (rate f):

- each agent takes its velocity and one relative pose per tree neighbour, and ``/clock`` every
  ``f / clock_rate`` ticks, and publishes one wrench;
- the simulator publishes all of those, ground truth (at every tick while recording, else at the
  record rate), the display topics (markers, funnels, ``/tf``, at the marker rate), and takes every
  wrench; while recording it also writes each of those messages into the bag.

The model charges each message a CPU cost in the process that sends or takes it, one cost for the
simulator (``sim_message_s``: it publishes a burst per tick) and one for an agent
(``agent_message_s``: every message wakes it), plus the simulator's own work per tick (physics,
sensing, shadow controllers, funnel check) and what each process does per wall second whatever
the rate (graph watch, display, diagnostics). Without a calibration
the costs are :data:`DEFAULT_COSTS` (their derivation is in its comment); ``formation-check
--calibrate`` measures the host's cost per message with the floor of a realtime run (its messages
with no work, :mod:`formation_sim.launch.calibrate`) and scales every cost of a process by the
ratio of its measured message cost to the default one (:func:`calibrated`).

Ticks stay on time while the processes use at most :data:`UTILISATION` of the cores they run on:
the cores needed are ``ceil(total CPU per tick / (period * UTILISATION))``, and the simulator, one
thread, must itself stay under ``UTILISATION`` of one core. ROS-free: no rclpy here.
"""

from __future__ import annotations

import json
import math
import os
import socket
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from formation_core.errors import CalibrationError

if TYPE_CHECKING:
    from formation_core.formation import FormationSpec

#: the share of a core the processes may use and still keep their ticks on time. The messages alone
#: of 20 agents at 100 Hz used 59-69 % of two cores and missed 2-10 % of the ticks (BENCHMARKS.md,
#: "What two cores hold"); the 5-agent preset at 100 Hz, well under half, kept 99-100 %.
UTILISATION = 0.5
#: the simulator's /clock rate in realtime [Hz of sim time] (formation_sim.node.runner.REALTIME_CLOCK_RATE)
REALTIME_CLOCK_RATE = 10.0
#: the display rate of markers, funnels and /tf [Hz of sim time] (formation-launch --marker-rate default)
MARKER_RATE = 30.0
#: display messages per display instant: markers, funnels, /tf
DISPLAY_MESSAGES = 3


@dataclass(frozen=True)
class Costs:
    """CPU per message, per tick and per wall second [s] on one host; ``source`` says where they come from."""

    #: CPU of the simulator per message it publishes or takes [s]
    sim_message_s: float
    #: CPU of an agent per message it takes or publishes (its checks and controller included) [s]
    agent_message_s: float
    #: the simulator's own work per tick beyond its messages (physics, sensing, shadow controllers,
    #: funnel check, the tick's wait) [s]
    sim_tick_s: float
    #: the simulator's work per wall second and agent, whatever the rate (the graph watch of every
    #: agent's topics, display frames, diagnostics) [s]
    sim_second_per_agent_s: float
    #: an agent's work per wall second (graph watch, diagnostics, deadline checks) [s]
    agent_second_s: float
    #: one bag write, while recording [s]
    bag_write_s: float
    source: str = "built-in defaults (BENCHMARKS.md)"


#: Built-in costs. Message costs, from BENCHMARKS.md's floor (``benchmarks/floor_bench.py --rate``:
#: the messages alone, /clock every 10 ticks, two-core reference host, quiet): for 20 agents at
#: 100 Hz the simulator took 2.7-3.3 ms per tick for 58.1 published and 20 taken messages (38.4 µs
#: each at the 3.0 ms midpoint) and each agent 0.46-0.52 ms for 2.9 + 0.1 taken and 1 published
#: (122 µs each at 0.49 ms); for 50 agents at 50 Hz the simulator 7.95 ms for 148.1 + 50 (40.1 µs)
#: and each agent 0.54 ms for 4.06 (133 µs). The defaults are the means: 39 µs and 128 µs.
#: The rest, what a run adds to its messages, is a least-squares fit to realtime runs of 5 and 10
#: agents at 50 and 100 Hz and 20 agents at 50 Hz, not recording, on the same host (BENCHMARKS.md,
#: "What a host holds": the CPU of each process between two progress lines, less its messages at
#: the costs above): the simulator 0.90 ms per tick and 2.6 ms per agent and wall second (its
#: per-agent work per tick came out at -2 µs: none); an agent 8.6 ms per wall second (per tick,
#: 5 µs: none beyond its messages). A bag write is 3.6 µs (BENCHMARKS.md, "Where a step goes now").
DEFAULT_COSTS = Costs(
    sim_message_s=39e-6,
    agent_message_s=128e-6,
    sim_tick_s=0.90e-3,
    sim_second_per_agent_s=2.6e-3,
    agent_second_s=8.6e-3,
    bag_write_s=3.6e-6,
)


@dataclass(frozen=True)
class Prediction:
    """CPU per tick [s] of each process of a realtime run, and the cores it needs."""

    control_rate: float
    agents: int
    edges: int
    record: bool
    costs: Costs
    sim_messages: float  # messages the simulator publishes and takes per tick
    agent_messages: dict[str, float]  # per agent: messages taken and published per tick
    sim_cpu_s: float
    agent_cpu_s: dict[str, float]

    @property
    def period_s(self) -> float:
        return 1.0 / self.control_rate

    @property
    def total_cpu_s(self) -> float:
        return self.sim_cpu_s + sum(self.agent_cpu_s.values())

    @property
    def busy_cores(self) -> float:
        """Cores kept busy on average: total CPU per tick / period."""
        return self.total_cpu_s / self.period_s

    @property
    def cores_needed(self) -> int:
        """Cores for on-time ticks: busy cores / :data:`UTILISATION`, rounded up."""
        return max(1, math.ceil(self.busy_cores / UTILISATION - 1e-9))

    @property
    def simulator_fits(self) -> bool:
        """The simulator (one thread) uses at most :data:`UTILISATION` of one core."""
        return self.sim_cpu_s <= UTILISATION * self.period_s


def message_counts(
    spec: FormationSpec, *, record: bool = True, marker_rate: float = MARKER_RATE
) -> tuple[float, dict[str, float]]:
    """(messages the simulator publishes and takes per tick, {agent: messages it takes and publishes per tick})."""
    s = spec.simulation
    f = s.control_rate
    degree = {a.id: 0 for a in spec.agents}
    for e in spec.edges:
        degree[e.tail] += 1
        degree[e.head] += 1
    clock = min(s.record_rate, f, REALTIME_CLOCK_RATE) / f
    ground_truth = 1.0 if record else min(s.record_rate, f) / f
    display = DISPLAY_MESSAGES * min(marker_rate, f) / f if marker_rate > 0 else 0.0
    agents = {a: d + 1 + clock + 1 for a, d in degree.items()}  # poses, velocity, /clock; the wrench
    published = sum(d + 1 for d in degree.values()) + clock + ground_truth + display
    return published + len(degree), agents


def predict(
    spec: FormationSpec, costs: Costs = DEFAULT_COSTS, *, record: bool = True, marker_rate: float = MARKER_RATE
) -> Prediction:
    """CPU per tick of the simulator and of each agent of ``spec`` run in realtime at its control rate."""
    f = spec.simulation.control_rate
    n = len(spec.agents)
    sim_messages, agent_messages = message_counts(spec, record=record, marker_rate=marker_rate)
    sim_cpu = (
        costs.sim_message_s * sim_messages
        + costs.sim_tick_s
        + costs.sim_second_per_agent_s * n / f
        + (costs.bag_write_s * sim_messages if record else 0.0)
    )
    agent_cpu = {a: costs.agent_message_s * m + costs.agent_second_s / f for a, m in agent_messages.items()}
    return Prediction(f, n, len(spec.edges), record, costs, sim_messages, agent_messages, sim_cpu, agent_cpu)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; os.cpu_count where that is unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def report_lines(p: Prediction, cores: int) -> tuple[list[str], list[str]]:
    """(lines of the prediction, reasons this host cannot keep the ticks on time)."""
    ms = 1e3
    per_agent = list(p.agent_cpu_s.values())
    busiest = max(p.agent_cpu_s, key=p.agent_cpu_s.__getitem__)
    lines = [
        f"realtime capacity at {p.control_rate:g} Hz ({p.period_s * ms:.3g} ms per tick), "
        f"{'recording' if p.record else 'not recording'}; costs: {p.costs.source}",
        f"  messages per tick: simulator {p.sim_messages:.1f}, each agent "
        f"{min(p.agent_messages.values()):.1f}-{max(p.agent_messages.values()):.1f}",
        f"  CPU per tick: simulator {p.sim_cpu_s * ms:.2f} ms ({p.sim_cpu_s / p.period_s:.0%} of a core), "
        f"each agent {min(per_agent) * ms:.2f}-{max(per_agent) * ms:.2f} ms (busiest {busiest}), "
        f"all {p.total_cpu_s * ms:.2f} ms",
        f"  cores: {p.busy_cores:.2f} busy on average; {p.cores_needed} needed to keep ticks on time "
        f"(at most {UTILISATION:.0%} of each); this host has {cores}",
    ]
    unsafe = []
    if not p.simulator_fits:
        unsafe.append(
            f"realtime: the simulator alone needs {p.sim_cpu_s * ms:.2f} ms of CPU per "
            f"{p.period_s * ms:.3g} ms tick, more than {UTILISATION:.0%} of one core: no number of such cores "
            f"keeps these ticks on time (a core {p.sim_cpu_s / (UTILISATION * p.period_s):.2g}x as fast would; "
            "or lower the control rate)"
        )
    if p.cores_needed > cores:
        unsafe.append(
            f"realtime: needs {p.cores_needed} cores to keep ticks on time, this host has {cores} "
            "(run agents on other hosts, or lower the control rate)"
        )
    return lines, unsafe


# --- calibration file --------------------------------------------------------------------------


def calibration_path() -> Path:
    """``$XDG_CACHE_HOME/formation/capacity.json`` (``~/.cache`` without XDG_CACHE_HOME)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "formation" / "capacity.json"


def save_calibration(sim_message_s: float, agent_message_s: float, detail: dict[str, Any], path: Path) -> Path:
    """Write the measured message costs [s] with this host's name, cores and the date (UTC)."""
    doc = {
        "host": socket.gethostname(),
        "cpu_count": os.cpu_count(),
        "available_cores": available_cores(),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "sim_message_s": sim_message_s,
        "agent_message_s": agent_message_s,
        "measurement": detail,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def load_costs(path: Path | None = None) -> Costs:
    """The host's calibrated costs if ``path`` (default :func:`calibration_path`) exists for this
    host, else :data:`DEFAULT_COSTS`. A file of another host is ignored (defaults)."""
    path = path or calibration_path()
    if not path.exists():
        return DEFAULT_COSTS
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CalibrationError(
            f"calibration {path}: unreadable ({exc}); run formation-check --calibrate again"
        ) from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"calibration {path}: not a JSON object")
    if doc.get("host") != socket.gethostname():
        return replace(DEFAULT_COSTS, source=f"built-in defaults (BENCHMARKS.md; {path} is of host {doc.get('host')})")
    values = {}
    for key in ("sim_message_s", "agent_message_s"):
        x = doc.get(key)
        if not isinstance(x, (int, float)) or not math.isfinite(x) or not 0 < x < 1:
            raise CalibrationError(f"calibration {path}: {key} = {x!r} is not a cost in (0, 1) s")
        values[key] = float(x)
    source = f"calibrated on {doc['host']} {doc.get('date', '?')} ({path})"
    return calibrated(values["sim_message_s"], values["agent_message_s"], source)


def calibrated(sim_message_s: float, agent_message_s: float, source: str) -> Costs:
    """:data:`DEFAULT_COSTS` scaled to a host whose floor costs these per message [s]: each process's
    other terms by the same factor as its messages (a host half as fast per message is taken to be
    half as fast at the rest)."""
    d = DEFAULT_COSTS
    ks, ka = sim_message_s / d.sim_message_s, agent_message_s / d.agent_message_s
    return replace(
        d,
        sim_message_s=sim_message_s,
        agent_message_s=agent_message_s,
        sim_tick_s=d.sim_tick_s * ks,
        sim_second_per_agent_s=d.sim_second_per_agent_s * ks,
        bag_write_s=d.bag_write_s * ks,
        agent_second_s=d.agent_second_s * ka,
        source=source,
    )


# --- the calibration floor's formation: a chain of agents (the floor node and its launcher share it)


def chain_ids(n: int) -> list[str]:
    """The ids of the floor's ``n`` agents, in chain order."""
    return [f"c{k}" for k in range(n)]


def chain_neighbours(n: int) -> dict[str, list[str]]:
    """Each floor agent's tree neighbours in the chain of ``n``."""
    ids = chain_ids(n)
    return {a: [ids[k + d] for d in (-1, 1) if 0 <= k + d < n] for k, a in enumerate(ids)}
