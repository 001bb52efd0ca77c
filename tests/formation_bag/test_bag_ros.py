"""The recorder and replay nodes as processes (rclpy; own ROS domain, localhost discovery)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_helpers import PAPER, REPO, cpu_load, script
from process_hygiene import kill_hard, remove_segments

from formation_bag import messages as m
from formation_bag.dataset import load_run
from formation_bag.interop_check import check_bag
from formation_bag.reader import Bag
from formation_bag.record_node import parse_meta
from formation_bag.writer import SegmentedBagWriter
from formation_core.errors import BagFormatError
from formation_sim.offline.analysis import analyze_run


def _recorder(ros_procs, bag: Path, *extra: str, env: dict[str, str] | None = None):
    proc = ros_procs.start(
        [*script("formation-record"), "--out", str(bag), "--formation", str(PAPER), "--quiet", *extra], env
    )
    ros_procs.wait_line(proc, "formation-record: recording", 60)
    return proc


def _ground_truth_stamps(bag: Path) -> list[int]:
    with Bag(bag) as b:
        return [
            m.stamp_ns(m.deserialize(x.data, x.msgtype).header.stamp) for x in b.messages(["/formation/ground_truth"])
        ]


@pytest.mark.parametrize(("storage", "stop_signal"), [("mcap", signal.SIGINT), ("sqlite3", signal.SIGTERM)])
def test_record_round_trip(ros_procs, tmp_path: Path, storage: str, stop_signal: int) -> None:
    """Every published message is recorded; SIGINT/SIGTERM leave a complete, interoperable bag."""
    bag = tmp_path / "bag"
    rec = _recorder(ros_procs, bag, "--storage", storage, "--segment-seconds", "0.5")
    pub = ros_procs.start([*script("publisher.py"), "300", "300"])
    out, err = ros_procs.finish(pub, timeout=120)
    assert pub.returncode == 0, err
    published = json.loads(out.strip().splitlines()[-1])
    code = ros_procs.stop(rec, stop_signal)
    assert code == 0, ros_procs.finish(rec, 5)
    assert (bag / "metadata.yaml").exists() and not list(bag.glob(".*"))
    with Bag(bag) as b:
        assert not b.lost and not b.recovered
        counts = {name: t.count for name, t in b.topics.items() if t.count}
        custom = b.custom_data
    stats = json.loads(custom["recorder_counts"])
    # the recorder knows what was published (publication sequence numbers) and wrote all it received
    assert stats["published_total"] == published, (stats, err, ros_procs.finish(rec, 5))
    assert stats["written"] == stats["received"]
    assert counts == published  # recorded = published, topic by topic
    assert custom["formation_file"] == PAPER.name
    assert _ground_truth_stamps(bag) == [k * 1_000_000 for k in range(300)]
    report = check_bag(bag)
    assert report.ok, report.problems


def test_recorder_switches_to_best_effort_publishers(ros_procs, tmp_path: Path) -> None:
    """Subscribed (reliable) before the publishers exist, the recorder still records best-effort ones."""
    bag = tmp_path / "bag"
    rec = _recorder(ros_procs, bag)
    pub = ros_procs.start([*script("publisher.py"), "200", "200"], {"BAG_TEST_BEST_EFFORT": "1"})
    out, err = ros_procs.finish(pub, timeout=120)
    assert pub.returncode == 0, err
    time.sleep(0.5)
    assert ros_procs.stop(rec) == 0
    with Bag(bag) as b:
        counts = {name: t.count for name, t in b.topics.items()}
    # best effort may drop a message on a loaded machine; a reliable-only recorder would record none
    assert all(counts[t] >= 190 for t in json.loads(out.strip().splitlines()[-1]))


def test_recorder_sigkill_loses_at_most_the_last_segment(ros_procs, tmp_path: Path) -> None:
    """A recorder killed with SIGKILL leaves its closed segments readable and listed in metadata.yaml."""
    bag = tmp_path / "bag"
    segment = 0.5
    rec = _recorder(ros_procs, bag, "--segment-seconds", str(segment), "--log-time", "receive")
    pub = ros_procs.start([*script("publisher.py"), "3000", "200"])
    deadline = time.monotonic() + 60
    while (
        not (bag / "metadata.yaml").exists()
        or len(
            yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["relative_file_paths"]
        )
        < 2
    ):
        assert time.monotonic() < deadline, "no second segment within 60 s"
        time.sleep(0.05)
    time.sleep(0.3)
    killed_at = time.time_ns()
    left = kill_hard(rec.pid)
    rec.wait()
    remove_segments(left)
    ros_procs.stop(pub, signal.SIGINT)
    with Bag(bag) as b:
        assert not b.recovered and len(b.segments) >= 2
        assert len(b.lost) <= 1
        end = b.end_time
    stamps = _ground_truth_stamps(bag)
    assert stamps == [k * 1_000_000 for k in range(len(stamps))]  # nothing missing before the lost tail
    # the lost tail is at most the open segment (plus the time a segment takes to close)
    assert (killed_at - end) / 1e9 < segment + 0.5
    assert check_bag(bag).ok


def test_replay_schedule_follows_the_log_times() -> None:
    """Each message is sent at t0 + Δlog / rate (the deterministic schedule; wall-clock accuracy: BENCHMARKS.md)."""
    from formation_bag.replay_node import send_time

    start = 1_700_000_000 * m.NS_PER_S
    logs = [start + k * 10_000_000 for k in range(150)]
    # the same formula in two float orders: equal to 1e-12 s
    assert [send_time(5.0, lg, start, 1.0) for lg in logs] == pytest.approx(
        [5.0 + k * 0.01 for k in range(150)], abs=1e-12
    )
    assert send_time(5.0, start + 10_000_000, start, 2.0) == pytest.approx(5.005, abs=1e-12)
    assert send_time(0.0, start + 3 * m.NS_PER_S, start + m.NS_PER_S, 0.5) == 4.0


def test_replay_publishes_every_message_in_order(ros_procs, tmp_path: Path) -> None:
    """A 100 Hz bag replayed: every message arrives, in order, with its stamp."""
    bag = tmp_path / "bag"
    enc = m.Encoder()
    rng = np.random.default_rng(3)
    start = 1_700_000_000 * m.NS_PER_S
    with SegmentedBagWriter(bag) as w:
        w.add_topic("/agent_1/velocity", m.TWIST_STAMPED)
        for k in range(150):
            w.write("/agent_1/velocity", start + k * 10_000_000, enc.twist(k * 10_000_000, "1", rng.random(6).tolist()))
    sub = ros_procs.start([*script("subscriber.py"), "/agent_1/velocity", m.TWIST_STAMPED, "150", "60"])
    ros_procs.wait_line(sub, "ready", 60)
    rep = ros_procs.start([*script("formation-replay"), str(bag), "--wait-timeout", "30", "--wait-settle", "2"])
    out, _err = ros_procs.finish(sub, timeout=90)
    rep_out, rep_err = ros_procs.finish(rep, timeout=30)
    assert rep.returncode == 0, rep_err
    assert "published 150 messages" in rep_out
    got = json.loads(out.strip().splitlines()[-1])
    assert got["stamps"] == [k * 10_000_000 for k in range(150)]


def _formation_bag(bag: Path, steps: int, period_ns: int) -> dict[str, int]:
    """A bag of every closed-loop topic of the paper formation (and /diagnostics every 10th step),
    ``steps`` steps ``period_ns`` apart; returns its count per topic."""
    from formation_core.spec import load_formation

    spec = load_formation(PAPER)
    ids = list(spec.agent_ids)
    links = [(e.tail, e.head) for e in spec.edges] + [(e.head, e.tail) for e in spec.edges]
    enc = m.Encoder()
    rng = np.random.default_rng(11)
    start = 1_700_000_000 * m.NS_PER_S
    counts: dict[str, int] = {}
    with SegmentedBagWriter(bag) as w:

        def put(topic: str, msgtype: str, log: int, data: bytes) -> None:
            w.add_topic(topic, msgtype)
            w.write(topic, log, data)
            counts[topic] = counts.get(topic, 0) + 1

        for k in range(steps):
            stamp = k * period_ns
            log = start + stamp
            put("/clock", m.CLOCK, log, enc.clock(stamp))
            p = rng.standard_normal((len(ids), 3))
            put(
                "/formation/ground_truth",
                m.POSE_ARRAY,
                log,
                enc.poses(stamp, p.tolist(), [np.eye(3).tolist()] * len(ids)),
            )
            for i, j in links:
                put(
                    f"/agent_{i}/relative_pose/agent_{j}",
                    m.POSE_STAMPED,
                    log,
                    enc.relative_pose(stamp, i, rng.standard_normal(3), (0.0, 0.0, 0.0, 1.0)),
                )
            for a in ids:
                put(f"/agent_{a}/velocity", m.TWIST_STAMPED, log, enc.twist(stamp, a, rng.standard_normal(6)))
                put(f"/agent_{a}/wrench", m.WRENCH_STAMPED, log, enc.wrench(stamp, a, rng.standard_normal(6)))
            if k % 10 == 0:
                put("/diagnostics", m.DIAGNOSTIC_ARRAY, log, enc.empty(stamp, m.DIAGNOSTIC_ARRAY))
    return counts


@pytest.mark.parametrize("told", ["formation", "discovering"])
def test_recorder_started_before_a_replay_records_every_message(ros_procs, tmp_path: Path, told: str) -> None:
    """A recorder started before formation-replay, beside two busy loops, records every replayed message."""
    src = tmp_path / "src"
    replayed = _formation_bag(src, steps=200, period_ns=10_000_000)  # 2 s at 100 Hz, 4 020 messages
    bag = tmp_path / "bag"
    # told the formation, it subscribes to every topic at once (the ground truth last); else it
    # subscribes to each topic as it finds it on the graph (every 0.5 s)
    told_args = ["--formation", str(PAPER)] if told == "formation" else []
    with cpu_load(2):
        rec = ros_procs.start([*script("formation-record"), "--out", str(bag), "--quiet", *told_args])
        ros_procs.wait_line(rec, "formation-record: recording", 60)
        rep = ros_procs.start([*script("formation-replay"), str(src), "--quiet", "--wait-timeout", "120"])
        rep_out, rep_err = ros_procs.finish(rep, timeout=300)
        assert rep.returncode == 0, rep_out + rep_err
        assert ros_procs.stop(rec) == 0, ros_procs.finish(rec, 5)
    with Bag(bag) as b:
        recorded = {name: t.count for name, t in b.topics.items() if t.count}
    assert recorded == replayed, rep_out + rep_err


def test_replay_refuses_unknown_topic(short_bags) -> None:
    """Asking for a topic the bag does not have names it (exit 2, before any ROS work)."""
    from formation_bag.replay_node import main

    assert main([str(short_bags["mcap"][0]), "--topics", "/agent_9/velocity"]) == 2


def test_replay_window_and_rate(ros_procs, tmp_path: Path) -> None:
    """--start/--end select a window of the bag (by log time); --rate 2 plays it faster."""
    bag = tmp_path / "bag"
    enc = m.Encoder()
    start = 1_700_000_000 * m.NS_PER_S
    with SegmentedBagWriter(bag) as w:
        w.add_topic("/agent_2/velocity", m.TWIST_STAMPED)
        for k in range(200):
            w.write("/agent_2/velocity", start + k * 10_000_000, enc.twist(k * 10_000_000, "2", [float(k)] * 6))
    sub = ros_procs.start([*script("subscriber.py"), "/agent_2/velocity", m.TWIST_STAMPED, "51", "60"])
    ros_procs.wait_line(sub, "ready", 60)
    rep = ros_procs.start(
        [*script("formation-replay"), str(bag), "--start", "0.5", "--end", "1.0", "--rate", "2", "--wait-settle", "2"]
    )
    out, _ = ros_procs.finish(sub, timeout=90)
    rep_out, rep_err = ros_procs.finish(rep, timeout=30)
    assert rep.returncode == 0, rep_err
    assert "published 51 messages" in rep_out  # 0.50 s … 1.00 s inclusive
    got = json.loads(out.strip().splitlines()[-1])
    assert got["stamps"] == [k * 10_000_000 for k in range(50, 101)]


def test_decimation_option() -> None:
    """--decimate TOPIC=N parses globs and refuses malformed entries, naming them."""
    from formation_bag.record_node import parse_decimation, parse_meta
    from formation_core.errors import BagTopicError

    assert parse_decimation(["/agent_*/relative_pose/*=10", "/diagnostics=2"]) == [
        ("/agent_*/relative_pose/*", 10),
        ("/diagnostics", 2),
    ]
    for bad in ("/clock", "/clock=0", "=3", "/clock=x"):
        with pytest.raises(BagTopicError, match=re.escape(bad)):
            parse_decimation([bad])
    assert parse_meta(["mode=lockstep", "note=a=b"]) == {"mode": "lockstep", "note": "a=b"}


def test_meta_run_settings_are_checked(tmp_path: Path, capsys) -> None:
    """--meta mode/control_rate/duration are what the analysis takes over the file's: an invalid one is
    refused before anything starts (exit 2), naming it, and no bag is created."""
    from formation_bag.record_node import main

    assert parse_meta(["mode=realtime", "control_rate=100", "duration=30"])["duration"] == "30"
    for item, message in (
        ("duration=30s", "--meta duration '30s' is not a number"),
        ("control_rate=0", "--meta control_rate '0' must be > 0"),
        ("mode=Realtime", "--meta mode 'Realtime' is not one of lockstep, realtime"),
    ):
        with pytest.raises(BagFormatError, match=re.escape(message)):
            parse_meta([item])
        assert main(["--out", str(tmp_path / "bag"), "--meta", item]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "bag").exists()


def test_recorder_started_after_the_run_says_what_it_missed(ros_procs, tmp_path: Path) -> None:
    """record.sh attached to a lockstep run already stepping: it names the steps it missed, and the
    analysis of its bag is INCOMPLETE with the missing start listed (never PASS, never FAIL)."""
    from formation_core.spec import load_formation

    # record.sh runs setup.sh first: after an edit of src/ that compiles the kernels (~20 s), long
    # enough for the run to end before the recorder starts. Done here, it is a no-op there.
    subprocess.run([str(REPO / "ros2_ws" / "setup.sh")], check=True, timeout=900, capture_output=True)
    spec = load_formation(PAPER)
    for a in spec.agents:
        ros_procs.start(
            [*script("formation-agent"), "--ros-args", "-p", f"formation_file:={PAPER}", "-p", f"agent_id:='{a.id}'"]
        )
    out = tmp_path / "run"
    # long enough (~10-30 s of stepping) for record.sh to start and match on a busy machine: at 0.2 s the
    # run sometimes ended before the recorder had heard anything
    sim = ros_procs.start(
        [*script("formation-sim"), str(PAPER), "--out", str(out), "--no-plots", "--duration", "0.6",
         "--ground-truth-rate", "10000", "--progress-period", "0.1"]
    )  # fmt: skip
    ros_procs.wait_line(sim, "progress t=", 120)
    bag = tmp_path / "bag"
    rec = ros_procs.start(
        [str(REPO / "ros2_ws" / "record.sh"), "--out", str(bag), "--formation", str(PAPER), "--quiet",
         "--meta", "mode=lockstep", "control_rate=10000.0", "duration=0.6"]
    )  # fmt: skip
    ros_procs.wait_line(rec, "recording", 60)
    ros_procs.finish(sim, timeout=240)
    ros_procs.stop(rec)
    _, err = ros_procs.finish(rec, timeout=30)
    assert "started after the run: steps before t=" in err, err
    run = load_run(bag)
    _, summary, _ = analyze_run(run)
    assert summary["verdict"] == "INCOMPLETE" and summary["first_violation"] is None
    missing = summary["bag"]["missing"]
    assert missing[0].startswith("ground truth: ") and "steps missing (0.0000-" in missing[0], missing
    assert any(item.startswith("recorder: started after the run") for item in missing), missing
