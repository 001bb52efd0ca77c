"""The supervisor's children: their scheduling policy (no ROS; each child is a short Python script)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from formation_sim.launch.supervisor import Supervisor, TlsFailures, policy_name, tls_failures

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


#: Fast DDS's console output in a process's log: two refused handshakes, and one cut by a peer still starting
FASTDDS_TLS = (
    b"\x1b[37;1m2026-12-03 09:31:04.021 \x1b[31;1m[\x1b[37;1mRTCP_TLS\x1b[31;1m Error] \x1b[37mHandshake failed: "
    b"EVP lib (asn1 encoding routines, ASN1_item_verify)\x1b[34;1m -> Function \x1b[36moperator()\x1b[m\n"
    b"[INFO] [1796290265.28] [agent_4.formation_agent]: agent 4: neighbours 3\n"
    b"2026-12-03 09:34:02.164 [RTCP_TLS Error] Handshake failed: Connection reset by peer -> Function operator()\n"
    b"2026-12-03 09:31:09.439 [RTCP_TLS Error] Handshake failed: certificate verify failed -> Function operator()\n"
)


def test_tls_failures_are_read_from_a_log(tmp_path: Path) -> None:
    """Fast DDS's TLS error lines, coloured or plain, are counted and the last one's text kept, but a
    handshake the network cut; a log without them, or none at all, gives None."""
    log = tmp_path / "agent_4.log"
    log.write_bytes(FASTDDS_TLS)
    assert tls_failures(log) == TlsFailures(2, "Handshake failed: certificate verify failed")
    log.write_bytes(b"".join(FASTDDS_TLS.splitlines(keepends=True)[1:3]))
    assert tls_failures(log) is None
    assert tls_failures(tmp_path / "missing.log") is None
