"""The supervisor's children: their scheduling policy (no ROS; each child is a short Python script)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from formation_sim.launch.supervisor import Supervisor, policy_name

#: prints the policy of its main thread and of a thread it starts afterwards (Fast DDS's, in a node)
_POLICIES = """
import os, threading
seen = []
t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(threading.get_native_id())))
t.start(); t.join()
print(os.sched_getscheduler(0), seen[0], flush=True)
"""


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="SCHED_BATCH is Linux's")
@pytest.mark.parametrize("batch", [True, False])
def test_children_run_under_the_chosen_policy_with_every_thread(tmp_path: Path, batch: bool) -> None:
    sup = Supervisor(dict(os.environ), tmp_path, batch=batch)
    child = sup.start("probe", "sim", [sys.executable, "-c", _POLICIES])
    try:
        assert sup.wait([child], 30.0)
    finally:
        sup.stop([child], 1.0, lambda _: None)  # by PID, also when the assertion failed
    assert child.returncode == 0
    main, thread = (int(x) for x in child.log.read_text().split())
    # the launcher's own policy is what a child without batch keeps (SCHED_OTHER unless run under chrt)
    want = os.SCHED_BATCH if batch else os.sched_getscheduler(0)
    assert (main, thread) == (want, want)
    # what processes.json shows: batch, or the launcher's own policy
    assert child.policy == ("SCHED_BATCH" if batch else policy_name(os.getpid()))
    assert sup.process_table(tmp_path)[0]["policy"] == child.policy
