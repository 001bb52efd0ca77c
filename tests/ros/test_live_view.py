"""--foxglove: a lockstep run serves its display topics to a Foxglove WebSocket client."""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path

from live_client import wait_and_receive
from process_hygiene import stop_group
from ros_helpers import PAPER, executable

from formation_bag.foxglove_server import DIAGNOSTIC_ARRAY, MARKER_ARRAY
from formation_bag.writer import typestore
from formation_core.spec import load_formation
from formation_msgs_py import topics

MARKERS = "/" + topics.MARKERS


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_lockstep_run_serves_markers_of_every_agent(ros_env: dict[str, str], tmp_path: Path) -> None:
    """formation-launch --foxglove 127.0.0.1:PORT: a client subscribed to the markers and /diagnostics
    receives a MarkerArray with a body and a label per agent and the agents' DiagnosticArray."""
    port = _free_port()
    out = tmp_path / "out"
    # long enough to be running when the client subscribes; stopped (SIGINT) once it has received
    cmd = [executable("formation-launch"), str(PAPER), "--out", str(out), "--duration", "5", "--no-record"]
    cmd += ["--no-plots", "--foxglove", f"127.0.0.1:{port}"]
    log = tmp_path / "launch.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=ros_env, start_new_session=True)
    try:
        got = wait_and_receive(
            f"ws://127.0.0.1:{port}", [MARKERS, topics.DIAGNOSTICS], alive=lambda: proc.poll() is None, timeout=240.0
        )
    finally:
        stop_group(proc)
    text = log.read_text(errors="replace")
    assert f"live view on ws://127.0.0.1:{port}" in text, text[-3000:]
    assert got.channels[MARKERS]["schemaName"] == MARKER_ARRAY
    store = typestore()
    msg = store.deserialize_cdr(got.messages[MARKERS][0][1], MARKER_ARRAY)
    ids = load_formation(PAPER).agent_ids
    labels = sorted(m.text for m in msg.markers if m.ns == "labels")
    assert sorted(m.id for m in msg.markers if m.ns == "bodies") == list(range(len(ids)))
    assert labels == sorted(ids)
    diag = store.deserialize_cdr(got.messages[topics.DIAGNOSTICS][0][1], DIAGNOSTIC_ARRAY)
    assert {s.hardware_id for s in diag.status} <= {topics.agent_frame(a) for a in ids}
    assert diag.status
