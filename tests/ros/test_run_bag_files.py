"""A recorded lockstep run's files: OUT/view.mcap for viewers, and a bag that a killed simulator
leaves for ``formation-bag repair`` with at most the last second lost (docs/bags.md)."""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import struct
import subprocess
import time
from pathlib import Path

import pytest
import yaml
from ros_helpers import PAPER, executable, kill_hard, remove_segments

from formation_bag import messages as m
from formation_bag.reader import Bag

DISPLAY_PERIOD = 1 / 30  # s: the simulator's default marker_rate
STEP = 1e-4  # s: the paper preset's 10 kHz control period
CLOCK_PERIOD = 1e-3  # s: /clock at the preset's record rate (1 kHz, the simulator's default --clock-rate)


def _launch(env: dict[str, str], out: Path, duration: str) -> subprocess.Popen:
    cmd = [
        executable("formation-launch"),
        str(PAPER),
        "--out",
        str(out),
        "--no-plots",
        "--quiet",
        "--duration",
        duration,
    ]
    return subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )


def _mcap_log_times(path: Path) -> dict[str, list[int]]:
    """Log times per topic of one MCAP file, read with the independent ``mcap`` reader."""
    from mcap.reader import make_reader

    out: dict[str, list[int]] = {}
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append(message.log_time)
    return out


def test_view_file_covers_the_whole_run_at_the_display_rate(ros_env: dict[str, str], tmp_path: Path) -> None:
    """A 0.2 s recorded lockstep run leaves OUT/view.mcap (mcap reader): /clock from 0 to the duration,
    markers, funnels and ground truth every display period, /diagnostics; the bag's metadata.yaml
    counts are the bag's own."""
    out = tmp_path / "out"
    proc = _launch(ros_env, out, "0.2")
    stdout, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, stdout
    view = _mcap_log_times(out / "view.mcap")
    # a display instant falls on the next publication: of /clock at most CLOCK_PERIOD later
    period_ns = (DISPLAY_PERIOD + CLOCK_PERIOD) * 1e9
    clock = view["/clock"]
    assert clock[0] <= DISPLAY_PERIOD * 1e9 and clock[-1] >= (0.2 - DISPLAY_PERIOD) * 1e9
    for topic in ("/clock", "/formation/ground_truth", "/formation/markers", "/formation/funnels"):
        times = view[topic]
        # 0.2 s at 30 Hz: instants 0, 1/30, …, 6/30 (the last is the duration itself)
        assert len(times) == 7, (topic, times)
        assert times[0] == 0 and max(b - a for a, b in itertools.pairwise(times)) <= period_ns, (topic, times)
    assert view["/diagnostics"], "no /diagnostics in the view file"
    assert not any(t.endswith(("/velocity", "/wrench")) or "relative_pose" in t for t in view)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["recorder"]["view"]["written"] == sum(len(v) for v in view.values())
    assert (out / "view.mcap").stat().st_size < 2_000_000  # a few MB for a whole 5 s run

    info = yaml.safe_load((out / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    stated = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    found: dict[str, int] = {}
    for name in info["relative_file_paths"]:
        for topic, times in _mcap_log_times(out / "bag" / name).items():
            found[topic] = found.get(topic, 0) + len(times)
    assert {t: n for t, n in stated.items() if n} == found
    assert info["message_count"] == sum(found.values())


def _flushed_until(path: Path, state: dict[str, int]) -> int | None:
    """Log time [ns] of the end of the last whole chunk the writer has put in the MCAP file at ``path``
    (read on from ``state['offset']``: records are op, uint64 length, body; a chunk's body starts with
    its first and last log time), or None."""
    try:
        with path.open("rb") as f:
            f.seek(state.setdefault("offset", 8))  # past the magic
            data = f.read()
    except FileNotFoundError:
        return None
    pos = 0
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        if pos + 9 + length > len(data):
            break  # written in part: read again later
        if op == 0x06:
            state["end"] = struct.unpack_from("<QQ", data, pos + 9)[1]
        pos += 9 + length
    state["offset"] += pos
    return state.get("end")


def _sim_pid(launcher: int) -> int | None:
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == launcher and b"formation_sim.node.sim_node" in cmd:
            return int(d.name)
    return None


@pytest.mark.slow
def test_sigkill_of_the_simulator_loses_at_most_a_second(ros_env: dict[str, str], tmp_path: Path) -> None:
    """SIGKILL of the simulator past 0.6 s of a 1 s recorded lockstep run: ``formation-bag repair``
    recovers every step up to the last chunk on disk when it was killed (≥ 0.6 s, within 1 s of the
    kill point) and the view file up to ≥ 0.5 s; formation-analyze says INCOMPLETE, naming the
    repair and the gap."""
    out = tmp_path / "out"
    proc = _launch(ros_env, out, "1")
    open_file = out / "bag" / ".bag_0" / ".bag_0.mcap"
    state: dict[str, int] = {}
    left: set[Path] = set()
    try:
        deadline = time.monotonic() + 300
        seen = None
        while (seen is None or seen < 0.6e9) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
            seen = _flushed_until(open_file, state)
        assert seen is not None and seen >= 0.6e9, f"run ended or too slow: {proc.poll()}, chunks up to {seen}"
        sim = _sim_pid(proc.pid)
        assert sim is not None
        left = kill_hard(sim)
        stdout, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # the launcher's own group (start_new_session): it and what it started
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    remove_segments(left)
    assert proc.returncode == 3, stdout  # the launcher names the dead simulator
    sim_log = (out / "logs" / "sim.log").read_text()
    progress = [float(x) for x in re.findall(r"progress t=([0-9.]+)", sim_log)]
    # once stepping, every progress line says how long is left (wall seconds at the rate so far)
    stepping = [ln for ln in sim_log.splitlines() if ln.startswith("progress t=") and " rtf=0.000 " not in ln]
    assert stepping and all(re.search(r" eta=\d+$", ln) for ln in stepping), sim_log

    r = subprocess.run([executable("formation-bag"), "repair", str(out / "bag")], capture_output=True, text=True)
    assert r.returncode == 0 and "messages recovered into bag_0.mcap" in r.stdout, r.stdout + r.stderr
    with Bag(out / "bag") as bag:
        stamps: dict[str, list[int]] = {}
        for msg in bag.messages(["/formation/ground_truth", "/agent_1/velocity", "/agent_5/wrench"]):
            stamps.setdefault(msg.topic, []).append(msg.log_time)
        repaired = bag.custom_data["repaired"]
        last = bag.end_time
    step_ns = round(STEP * 1e9)
    reached = stamps["/formation/ground_truth"][-1]
    assert last >= seen  # every chunk on disk at the kill is recovered
    assert reached >= seen - step_ns  # a step's ground truth is written after its measurements
    if progress:
        assert reached >= (progress[-1] - 1.0) * 1e9  # at most a second lost
    for topic, times in stamps.items():
        # every step from the first up to the last recovered ground truth (less its own step's answers)
        expected = list(range(0, reached - step_ns + 1, step_ns))
        assert sorted(set(times))[: len(expected)] == expected, topic
    assert "of log time recovered, the rest lost" in repaired

    # the view file: flushed every half second of simulated time, completed in place by repair
    r = subprocess.run([executable("formation-bag"), "repair", str(out / "view.mcap")], capture_output=True, text=True)
    assert r.returncode == 0 and "of log time recovered, the rest lost" in r.stdout, r.stdout + r.stderr
    clock = _mcap_log_times(out / "view.mcap")["/clock"]
    assert clock[0] == 0 and clock[-1] >= 0.5e9 and clock[-1] >= last - 1e9, clock
    assert max(b - a for a, b in itertools.pairwise(clock)) <= (DISPLAY_PERIOD + CLOCK_PERIOD) * 1e9

    r = subprocess.run(
        [executable("formation-analyze"), str(out / "bag"), "--out", str(tmp_path / "analysis"), "--no-plots"],
        capture_output=True,
        text=True,
        env=ros_env,
    )
    assert r.returncode == 4, r.stdout + r.stderr
    text = r.stdout + r.stderr
    assert "INCOMPLETE" in text and "bag repaired" in text, text
    first_missing = m.seconds(reached + step_ns)
    assert (
        f"ground truth: {round((1.0 - first_missing) / STEP) + 1} steps missing ({first_missing:.4f}-1.0000 s)" in text
    )
