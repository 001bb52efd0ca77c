"""Faults counted, not sampled: every fault of a run per agent and kind, with its first and last
occurrence (summary.json ``faults``; docs/outputs.md), and the strict, atomic JSON every output uses.

Who counts what (kinds):

- the simulator (formation_sim.node.sim_node): ``resent_step`` (lockstep: a step published again to an
  agent that had not answered), :data:`ANSWER_MISMATCH` (lockstep: an answer that differed from
  the witness, the simulator's run of that agent's controller on what the agent received: bit for
  bit where the agent computes as the simulator can, else beyond the round-off bound; not applied,
  the step stays unanswered: formation_sim.node.witness),
  ``stale_command`` (realtime: a tick applied an agent's older wrench, its answer to the last step
  was not in), ``zero_wrench`` (realtime: that wrench was older than
  ``command_timeout`` and replaced by zero), ``late_tick`` (realtime, agent ``simulator``: a tick
  more than half a period late), ``refused_wrench_<kind>`` (formation_msgs_py.wrench_checks), and from its
  shadow of the controllers ``measurement`` (a neighbour out of sensing range) and ``controller``
  (saturated: outside a funnel);
- each agent (formation_agent.agent_node, written to its ``faults_file`` when it stops and merged by
  formation-launch): ``clock_jump`` (/clock went back: counted, nothing reset), ``reset``
  (simulation time restarted: /clock and the measurements went back together, as a bag replayed in
  a loop does; controller and watchdogs reset), ``refused_<kind>`` (formation_msgs_py.measurement_checks;
  ``refused_past_stamp``: a velocity stamped before the agent's time that is no resend, refused by
  its synchroniser without an answer), ``missing_pose`` (answered without a neighbour's
  relative pose after ``pose_wait``: out of range or lost; answered with a zero wrench);
- the recorder: messages published but not in the bag, per topic (summary.json ``recorder``).

Times are simulation seconds. None of these is a funnel violation.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

#: lockstep: an agent's answer differed from the witness (its controller run by the simulator)
ANSWER_MISMATCH = "answer_mismatch"


class FaultRecord(TypedDict):
    """One kind of fault of one agent as summary.json holds it: count, first and last time [s] and detail."""

    count: int
    first_t: float
    last_t: float
    first: str
    last: str


#: summary.json's ``faults``: {agent: {kind: record}}
Faults = dict[str, dict[str, FaultRecord]]


@dataclass
class FaultCount:
    """How often one kind of fault happened to one agent: count, first and last time [s]."""

    count: int
    first_t: float
    last_t: float
    first_detail: str
    last_detail: str

    def as_dict(self) -> FaultRecord:
        return {
            "count": self.count,
            "first_t": self.first_t,
            "last_t": self.last_t,
            "first": self.first_detail,
            "last": self.last_detail,
        }


@dataclass
class FaultLog:
    """Every fault counted per agent and kind (stale command, zero wrench, missing measurement, …)."""

    counts: dict[tuple[str, str], FaultCount] = field(default_factory=dict)

    def add(self, t: float, agent: str, kind: str, detail: str = "", n: int = 1) -> bool:
        """Count ``n`` faults at t [s]; True if it is this agent's first of this kind."""
        return self._combine(agent, kind, FaultCount(n, t, t, detail, detail))

    def merge(self, faults: Faults) -> None:
        """Add the counts of another log's :meth:`as_dict` (another process's faults)."""
        for agent, kinds in faults.items():
            for kind, c in kinds.items():
                count = FaultCount(c["count"], c["first_t"], c["last_t"], c.get("first", ""), c.get("last", ""))
                self._combine(agent, kind, count)

    def _combine(self, agent: str, kind: str, new: FaultCount) -> bool:
        c = self.counts.get((agent, kind))
        if c is None:
            self.counts[(agent, kind)] = new
            return True
        c.count += new.count
        if new.first_t < c.first_t:
            c.first_t, c.first_detail = new.first_t, new.first_detail
        if new.last_t >= c.last_t:
            c.last_t, c.last_detail = new.last_t, new.last_detail
        return False

    def as_dict(self) -> Faults:
        out: Faults = {}
        for (agent, kind), c in sorted(self.counts.items()):
            out.setdefault(agent, {})[kind] = c.as_dict()
        return out


def fault_lines(faults: Faults) -> list[str]:
    """One console line per agent and kind: count, first and last occurrence."""
    lines = []
    for agent, kinds in faults.items():
        for kind, c in kinds.items():
            first = f"first t={c['first_t']:.4f} s" + (f" ({c['first']})" if c.get("first") else "")
            last = ""
            if c["count"] > 1:
                last = f", last t={c['last_t']:.4f} s" + (f" ({c['last']})" if c.get("last") else "")
            lines.append(f"  fault: agent {agent}: {kind} x{c['count']}: {first}{last}")
    return lines


#: What each fault kind means, in words a reader of a run's summary needs (no code names)
MEANINGS = {
    "resent_step": "lockstep: an agent's answer had not arrived within the step timeout (a slow or "
    "stopped process), so the simulator sent that step's measurements again; the step is integrated "
    "only with the agent's answer, so the trajectory is the same as without the delay",
    "answer_mismatch": "lockstep: an agent's wrench differed from the witness (the simulator's own run of "
    "that agent's controller on what it was sent: bit for bit on the same platform, else beyond the "
    "round-off bound) and was not applied; the step was sent again. The same wrench again ends the run "
    "INCOMPLETE, exit 5 (wrong answer); an agent that then agreed was applied, the trajectory unchanged",
    "stale_command": "realtime: a tick applied the agent's previous wrench, its answer to the last "
    "step was not in yet (zero-order hold)",
    "zero_wrench": "realtime: the agent's last wrench was older than command_timeout and was replaced by zero",
    "late_tick": "realtime: a simulator tick ran more than half a control period after its wall-clock time",
    "measurement": "the agent had no relative pose of a neighbour: out of sensing range or, with a link model, "
    "none received yet, lost, or older than its measurement_timeout (docs/links.md)",
    "controller": "an error left its funnel between two control steps and the controller saturated "
    "(ERROR on /diagnostics)",
    "reset": "simulation time restarted (/clock and the measurements went back together, as a bag "
    "replayed in a loop does): the agent's controller and watchdogs started again",
    "clock_jump": "/clock went back (an outsider's /clock, or a replay that loops): counted; the agent "
    "takes its time from the measurements, so nothing was reset",
    "refused_past_stamp": "the agent refused a velocity stamped before its newest confirmed step that "
    "was no resend of a step (an outsider's, or a step long past): no answer, nothing reset",
    "missing_pose": "the agent answered without a neighbour's relative pose (out of range or lost), with a zero wrench",
    "refused_wrench_": "the simulator refused an agent's wrench (not finite, over the actuator limits, "
    "malformed, or for no step of the run) and applied a zero wrench for that step",
    "refused_": "the agent refused a measurement (not finite, not a rotation, out of sensing range, "
    "malformed, or stamped too far from its time) and answered that step with a zero wrench",
}


def fault_meanings(faults: Faults) -> list[str]:
    """One line per fault kind present in ``faults`` (summary.json's): what it means. A kind not in
    :data:`MEANINGS` is taken by its longest prefix there (``refused_wrench_non_finite``)."""
    kinds = sorted({kind for per_agent in faults.values() for kind in per_agent})
    lines = []
    for kind in kinds:
        key = kind if kind in MEANINGS else max((k for k in MEANINGS if kind.startswith(k)), key=len, default=None)
        if key is not None:
            lines.append(f"  {kind}: {MEANINGS[key]}")
    return ["  what the faults mean (none is a funnel violation):", *lines] if lines else []


# -- strict JSON, written atomically --------------------------------------------------------------


def strict_json(x: Any) -> Any:
    """A copy of ``x`` that ``json.dumps(allow_nan=False)`` accepts: numpy scalars to Python,
    NaN and ±inf to None (the summary's reasons say why a value is unknown)."""
    if isinstance(x, dict):
        return {str(k): strict_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict_json(v) for v in x]
    if hasattr(x, "tolist"):  # numpy arrays and scalars, without importing numpy here
        return strict_json(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return x


def write_atomic(path: Path, data: bytes, *, mode: int | None = None) -> None:
    """Write ``path`` under a temporary name in its directory, then rename it (raises OSError).

    The file gets ``mode``, or by default what the user's umask gives any new file (0666 & ~umask),
    like every other output; mkstemp alone would leave it 0600.
    """
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, _umask_mode() if mode is None else mode)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask_mode() -> int:
    """0666 & ~umask: the mode ``open(path, "w")`` gives a new file.

    The umask is read from /proc (setting it to read it would race with other threads creating files);
    where /proc has no ``Umask:`` line, by setting and restoring it.
    """
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            mask = next(int(line.split()[1], 8) for line in fh if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError, IndexError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def write_json(path: Path, obj: Any) -> None:
    """Strict JSON (no NaN/Infinity), written atomically."""
    write_atomic(path, (json.dumps(strict_json(obj), indent=2, allow_nan=False) + "\n").encode("utf-8"))
