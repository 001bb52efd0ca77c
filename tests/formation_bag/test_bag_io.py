"""Segmented writing, reading (also of killed recordings), repair and the interop check (no ROS)."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from formation_bag import messages as m
from formation_bag.interop_check import JAZZY_KEYS, check_bag
from formation_bag.reader import Bag, repair, repair_file
from formation_bag.writer import SegmentedBagWriter
from formation_core.errors import BagExistsError, BagFormatError, BagNotFoundError, BagWriterError

START = 1_700_000_000 * m.NS_PER_S


def _write(path: Path, storage: str, n: int, *, segment_seconds: float | None = 0.1, **kw) -> list[bytes]:
    enc = m.Encoder()
    rng = np.random.default_rng(7)
    payloads = []
    with SegmentedBagWriter(path, storage=storage, segment_seconds=segment_seconds, **kw) as w:
        w.add_topic("/clock", m.CLOCK)
        w.add_topic("/agent_1/velocity", m.TWIST_STAMPED)
        for k in range(n):
            ns = k * 10_000_000
            w.write("/clock", START + ns, enc.clock(ns))
            data = enc.twist(ns, "1", rng.standard_normal(6).tolist())
            payloads.append(data)
            w.write("/agent_1/velocity", START + ns + 1000, data)
    return payloads


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip(tmp_path: Path, storage: str) -> None:
    """Every message comes back byte for byte, in order, from a multi-segment bag."""
    bag = tmp_path / "bag"
    payloads = _write(bag, storage, 50)
    suffix = ".mcap" if storage == "mcap" else ".db3"
    files = sorted(p.name for p in bag.iterdir())
    assert files == sorted([f"bag_{i}{suffix}" for i in range(5)] + ["metadata.yaml"])
    with Bag(bag) as b:
        assert not b.recovered and not b.lost
        got = [msg.data for msg in b.messages(["/agent_1/velocity"])]
        assert [bytes(x) for x in got] == payloads
        assert b.topics["/clock"].count == 50 and b.message_count == 100
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert tuple(info) == JAZZY_KEYS
    assert info["version"] == 9 and info["storage_identifier"] == storage and info["ros_distro"] == "jazzy"
    assert info["relative_file_paths"] == [f"bag_{i}{suffix}" for i in range(5)]
    assert sum(f["message_count"] for f in info["files"]) == 100
    report = check_bag(bag)
    assert report.ok, report.problems
    if storage == "mcap":
        assert report.counts_mcap == {"/clock": 50, "/agent_1/velocity": 50}


def test_mcap_files_are_byte_for_byte_those_of_rosbags_own_writer(tmp_path: Path, monkeypatch) -> None:
    """Our MCAP message write (one struct pack) leaves the file rosbags' McapWriter.write leaves:
    the same bytes for a segment of several chunks (messages of different topics and sizes)."""
    from rosbags.rosbag2.storage_mcap import McapWriter

    from formation_bag import writer as bag_writer

    def segment(path: Path) -> bytes:
        enc = m.Encoder()
        rng = np.random.default_rng(3)
        with SegmentedBagWriter(path, segment_seconds=None, chunk_seconds=None) as w:
            w.add_topic("/clock", m.CLOCK)
            w.add_topic("/agent_1/velocity", m.TWIST_STAMPED)
            for k in range(30_000):  # ~3.3 MB: four chunks
                ns = k * 100_000
                w.write("/clock", START + ns, enc.clock(ns))
                w.write("/agent_1/velocity", START + ns + 7, enc.twist(ns, "1", rng.standard_normal(6).tolist()))
        return (path / "bag_0.mcap").read_bytes()

    ours = segment(tmp_path / "ours" / "bag")  # the same name: the embedded metadata names the file
    plugins = {**bag_writer._SegmentFileWriter.STORAGE_PLUGINS, bag_writer.StoragePlugin.MCAP: McapWriter}
    monkeypatch.setattr(bag_writer._SegmentFileWriter, "STORAGE_PLUGINS", plugins)
    theirs = segment(tmp_path / "theirs" / "bag")
    assert len(ours) > 3 * bag_writer.CHUNK_BYTES  # a chunk closes past CHUNK_BYTES: four at least
    assert ours == theirs


def test_segments_by_size(tmp_path: Path) -> None:
    """A size limit closes segments too."""
    _write(tmp_path / "bag", "mcap", 40, segment_seconds=None, segment_bytes=1000)
    with Bag(tmp_path / "bag") as b:
        assert len(b.segments) > 3 and b.message_count == 80


def test_mutant_bag_end_time_off_by_one__the_last_log_time_exactly(tmp_path: Path) -> None:
    """Bag.end_time is the log time of the last message itself [ns] (rosbags' end_time is one past it), in
    a bag with metadata and in one recovered without it."""
    _write(tmp_path / "bag", "mcap", 30)
    last = START + 29 * 10_000_000 + 1000  # the last velocity message, 1 µs after its clock
    with Bag(tmp_path / "bag") as b:
        assert (b.start_time, b.end_time) == (START, last)
    (tmp_path / "bag" / "metadata.yaml").unlink()
    with Bag(tmp_path / "bag") as b:
        assert b.recovered and (b.start_time, b.end_time) == (START, last)


def test_mutant_segments_sorted_by_name__eleven_and_more_segments_in_time_order(tmp_path: Path) -> None:
    """A recording of 12 segments read without its metadata.yaml (a killed recorder's): the segments in
    number order (bag_2 before bag_10, not by name), every message in log-time order, and repair writes
    them in that order."""
    bag = tmp_path / "bag"
    payloads = _write(bag, "mcap", 120)  # 10 ms apart, a segment every 0.1 s: 12 segments
    (bag / "metadata.yaml").unlink()
    names = [f"bag_{i}.mcap" for i in range(12)]
    with Bag(bag) as b:
        assert b.recovered and [f.name for f in b.segments] == names
        got = list(b.messages(["/agent_1/velocity"]))
        assert [bytes(x.data) for x in got] == payloads
        times = [x.log_time for x in b.messages()]
        assert times == sorted(times) and len(times) == 240
    repair(bag)
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == names


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    """An existing path is never overwritten, and the error names it."""
    (tmp_path / "bag").mkdir()
    with pytest.raises(BagExistsError, match=re.escape(str(tmp_path / "bag"))):
        SegmentedBagWriter(tmp_path / "bag")
    with pytest.raises(BagWriterError, match="zip"):
        SegmentedBagWriter(tmp_path / "other", storage="zip")


def test_missing_bag_is_named(tmp_path: Path) -> None:
    """Opening a bag that does not exist names the path."""
    with pytest.raises(BagNotFoundError, match="nope"):
        Bag(tmp_path / "nope")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_sigkill_loses_at_most_the_open_segment(tmp_path: Path, storage: str) -> None:
    """A writer process killed with SIGKILL leaves every closed segment readable, with metadata."""
    bag = tmp_path / "bag"
    code = textwrap.dedent(
        f"""
        import sys, time
        from formation_bag import messages as m
        from formation_bag.writer import SegmentedBagWriter
        enc = m.Encoder()
        w = SegmentedBagWriter({str(bag)!r}, storage={storage!r}, segment_seconds=0.2)
        w.add_topic("/clock", m.CLOCK)
        k = 0
        while True:
            w.write("/clock", time.time_ns(), enc.clock(k * 1000000))
            if k == 20:
                print("writing", flush=True)
            k += 1
            time.sleep(0.002)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        time.sleep(1.1)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    with Bag(bag) as b:
        assert not b.recovered  # metadata.yaml lists the closed segments
        assert len(b.segments) >= 3
        assert len(b.lost) == 1 and "open when the recorder stopped" in b.lost[0]
        stamps = [m.stamp_ns(m.deserialize(x.data, x.msgtype).clock) for x in b.messages()]
    # contiguous from the first message: nothing but the open segment's tail is missing
    assert stamps == [k * 1_000_000 for k in range(len(stamps))]
    assert check_bag(bag).ok
    # without metadata.yaml the segments are still read, and repair rebuilds it
    (bag / "metadata.yaml").unlink()
    with Bag(bag) as b:
        assert b.recovered and b.message_count == len(stamps)
    meta, lost = repair(bag)
    assert meta.exists() and len(lost) == 1
    assert check_bag(bag).ok
    with pytest.raises(BagExistsError, match=r"metadata\.yaml"):
        repair(bag)


def test_sigkill_of_a_one_file_writer_is_salvaged_by_repair(tmp_path: Path) -> None:
    """A one-file bag (the default) whose writer got SIGKILL: repair recovers every closed ~1 MiB chunk."""
    bag = tmp_path / "bag"
    code = textwrap.dedent(
        f"""
        import time
        from formation_bag import messages as m
        from formation_bag.writer import SegmentedBagWriter
        enc = m.Encoder()
        w = SegmentedBagWriter({str(bag)!r}, segment_seconds=None, segment_bytes=None)
        w.add_topic("/clock", m.CLOCK)
        for k in range(100_000):
            w.write("/clock", k * 1000, enc.clock(k * 1000))
        print("written", flush=True)
        time.sleep(600)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "written"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    with pytest.raises(BagFormatError, match="no readable segment"):
        Bag(bag)  # only the open file, without its summary
    meta, lost = repair(bag)
    assert meta.exists() and len(lost) == 1 and "messages recovered into bag_0.mcap" in lost[0]
    with Bag(bag) as b:
        stamps = [m.stamp_ns(m.deserialize(x.data, x.msgtype).clock) for x in b.messages()]
    # a Clock message takes 43 B in a chunk: a 1 MiB chunk holds ~24 000; all but the torn last one are back
    assert stamps == [k * 1000 for k in range(len(stamps))] and len(stamps) >= 100_000 - 25_000
    assert check_bag(bag).ok


def test_a_killed_writer_loses_at_most_the_last_second_of_log_time(tmp_path: Path) -> None:
    """Small messages (a 1 MiB chunk would take ~17 s here): chunks close and reach the disk every
    second of log time, so after SIGKILL repair recovers every message up to within 1 s of the last
    one written, with the writer's custom_data, and notes what it recovered."""
    bag = tmp_path / "bag"
    code = textwrap.dedent(
        f"""
        import time
        from formation_bag import messages as m
        from formation_bag.writer import SegmentedBagWriter
        enc = m.Encoder()
        w = SegmentedBagWriter({str(bag)!r}, segment_seconds=None, segment_bytes=None,
                               custom_data={{"duration": "10", "formation_file": "f.yaml"}})
        w.add_topic("/clock", m.CLOCK)
        for k in range(3500):  # 3.5 s of log time at 1 kHz
            w.write("/clock", k * 1_000_000, enc.clock(k * 1_000_000))
        print("written", flush=True)
        time.sleep(600)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "written"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    _, lost = repair(bag)
    assert len(lost) == 1 and "messages recovered into bag_0.mcap" in lost[0]
    with Bag(bag) as b:
        stamps = [m.stamp_ns(m.deserialize(x.data, x.msgtype).clock) for x in b.messages()]
        custom = b.custom_data
    # chunks close once they span 1 s: [0, 1.000], [1.001, 2.001], [2.002, 3.002]; the rest was open
    assert stamps == [k * 1_000_000 for k in range(len(stamps))]
    assert 3499 - len(stamps) < 1000  # lost: less than 1 s of log time
    assert custom["duration"] == "10" and custom["formation_file"] == "f.yaml"
    recovered = f"bag_0.mcap: {len(stamps)} messages up to 3.0020 s of log time recovered, the rest lost"
    assert custom["repaired"] == recovered
    assert check_bag(bag).ok


def test_a_killed_view_file_is_completed_in_place_by_repair(tmp_path: Path) -> None:
    """A one-file MCAP writer (OUT/view.mcap's) killed after 3.5 s of log time: its chunks are on disk
    up to within 1 s; ``formation-bag repair FILE`` completes the file in place, saying what it
    recovered; a complete file is refused."""
    from mcap.reader import make_reader

    view = tmp_path / "view.mcap"
    code = textwrap.dedent(
        f"""
        import time
        from formation_bag import messages as m
        from formation_bag.writer import McapFileWriter
        enc = m.Encoder()
        w = McapFileWriter({str(view)!r}, custom_data={{"mode": "lockstep"}})
        w.add_topic("/clock", m.CLOCK)
        for k in range(106):  # 3.5 s at 30 Hz
            w.write("/clock", round(k * 1e9 / 30), enc.clock(round(k * 1e9 / 30)))
        print("written", flush=True)
        time.sleep(600)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "written"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    r = subprocess.run(
        [sys.executable, "-m", "formation_bag.cli", "repair", str(view)], capture_output=True, text=True, check=False
    )
    assert r.returncode == 0, r.stdout + r.stderr
    with view.open("rb") as f:
        reader = make_reader(f)
        times = [msg.log_time for _, _, msg in reader.iter_messages()]
        assert reader.get_summary() is not None
    # chunks close once they span 1 s: at 1.0, 2.033, 3.067 s; what came after was open
    assert times == [round(k * 1e9 / 30) for k in range(len(times))] and len(times) == 93
    note = f"view.mcap: 93 messages up to {times[-1] / 1e9:.4f} s of log time recovered, the rest lost"
    assert r.stdout.strip() == f"repaired {view}: {note}"
    with Bag(view) as b:
        assert b.custom_data == {"mode": "lockstep", "repaired": note}
    with pytest.raises(BagFormatError, match="complete already"):
        repair_file(view)


def test_interop_flags_a_broken_metadata(tmp_path: Path) -> None:
    """check_bag reports a metadata.yaml whose counts do not match the files."""
    bag = tmp_path / "bag"
    _write(bag, "mcap", 10)
    meta = bag / "metadata.yaml"
    meta.write_text(meta.read_text().replace("message_count: 20", "message_count: 21", 1))
    report = check_bag(bag)
    assert not report.ok and any("message_count" in p for p in report.problems)


def test_interop_decodes_a_sample_with_mcap_ros2_or_every_message(tmp_path: Path) -> None:
    """mcap_ros2 decodes the first DECODE_SAMPLE messages of every channel of every file (all on
    request), each equal to rosbags' decoding; mcap reads every message either way."""
    bag = tmp_path / "bag"
    _write(bag, "mcap", 150, segment_seconds=None)
    sampled = check_bag(bag, sample=100)
    assert sampled.ok, sampled.problems
    assert sampled.counts_mcap == {"/clock": 150, "/agent_1/velocity": 150}
    assert sampled.decoded_mcap_ros2 == 2 * 100
    full = check_bag(bag, sample=None)
    assert full.ok, full.problems
    assert full.decoded_mcap_ros2 == 2 * 150


def test_interop_reports_bytes_that_differ_between_the_readers(tmp_path: Path, monkeypatch) -> None:
    """One message whose bytes differ between rosbags and mcap is a problem naming its topic."""
    import formation_bag.interop_check as interop_check

    bag = tmp_path / "bag"
    _write(bag, "mcap", 20, segment_seconds=None)
    honest = interop_check._rosbags_bytes

    def one_byte_off(b: Bag, report: interop_check.InteropReport):
        for k, (topic, data) in enumerate(honest(b, report)):
            yield topic, (data[:-1] + bytes([data[-1] ^ 1]) if k == 7 else data)

    monkeypatch.setattr(interop_check, "_rosbags_bytes", one_byte_off)
    report = check_bag(bag)
    assert not report.ok
    assert len(report.problems) == 1 and "bytes differ between rosbags and mcap" in report.problems[0]


def test_interop_compares_decoded_fields_with_nan_equal_to_nan() -> None:
    """The field-by-field comparison of the two decoders: NaN equals NaN, -0.0 equals 0.0 as floats
    do, a changed number or a missing key does not."""
    from formation_bag.interop_check import _same, plain
    from formation_bag.writer import typestore

    enc = m.Encoder()
    data = enc.twist(5, "1", [float("nan"), -0.0, 1.0, 2.0, 3.0, 4.0])
    msg = typestore().deserialize_cdr(data, m.TWIST_STAMPED)
    as_plain = plain(msg)
    assert as_plain["header"]["frame_id"] == "agent_1" and as_plain["header"]["stamp"]["nanosec"] == 5
    assert _same(as_plain, plain(typestore().deserialize_cdr(data, m.TWIST_STAMPED)))
    changed = plain(msg)
    changed["twist"]["linear"]["z"] = 1.5
    assert not _same(as_plain, changed)
    del changed["twist"]
    assert not _same(as_plain, changed)


def test_classify_topics() -> None:
    """Topic names map to their meaning (docs/topics.md), also in a namespace."""
    assert m.classify("/agent_3/relative_pose/agent_5") == m.TopicKind("relative_pose", m.POSE_STAMPED, "3", "5")
    assert m.classify("/agent_2/wrench").agent == "2"
    assert m.classify("/formation/ground_truth").kind == "ground_truth"
    assert m.classify("/run1/agent_2/velocity", "run1").kind == "velocity"
    assert m.classify("/run1/agent_2/velocity") is None
    assert m.classify("/rosout") is None


def test_fast_decoding_equals_rosbags(short_bags) -> None:
    """The struct decoders give exactly rosbags' numbers for every message (docs/topics.md) of a run."""
    decoders = {
        "relative_pose": m.decode_relative_pose,
        "velocity": m.decode_twist,
        "wrench": m.decode_wrench,
        "ground_truth": m.decode_poses,
    }
    with Bag(short_bags["mcap"][0]) as b:
        for msg in b.messages():
            kind = m.classify(msg.topic).kind
            stamp, value = m.fast_decode(kind, msg.data, msg.msgtype)
            obj = m.deserialize(msg.data, msg.msgtype)
            if kind == "clock":
                assert (stamp, value) == (m.stamp_ns(obj.clock), None)
            else:
                assert (stamp, value) == (m.stamp_ns(obj.header.stamp), decoders[kind](obj))


def test_fast_ground_truth_decode_equals_rosbags() -> None:
    """The wire codec's PoseArray decoder gives rosbags' numbers exactly, for 1..7 poses (any frame name)."""
    from scipy.spatial.transform import Rotation

    from formation_msgs_py import codec

    rng = np.random.default_rng(11)
    for n in (1, 2, 7):
        p = rng.normal(size=(n, 3)).tolist()
        R = Rotation.random(n, random_state=n).as_matrix().tolist()
        data = codec.ground_truth_bytes(12_345_678_901, p, R)
        stamp, (p_fast, R_fast) = m.fast_decode("ground_truth", data, m.POSE_ARRAY)
        p_ref, R_ref = m.decode_poses(m.deserialize(data, m.POSE_ARRAY))
        assert stamp == 12_345_678_901
        # both decode the same doubles and convert the quaternion with the same function: bit-identical
        assert p_fast == p_ref and R_fast == R_ref


def test_info_into_a_closed_pipe_ends_quietly(short_bags) -> None:
    """`formation-bag info BAG | head -1`: the reader closes the pipe; exit 0, nothing on stderr."""
    bag, _ = short_bags["mcap"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "formation_bag.cli", "info", str(bag)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # closed before the first line is written: every write meets a closed pipe
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 0
    assert err == b""


def test_older_transform_stamped_relative_poses_read_and_replay_as_pose_stamped() -> None:
    """A relative pose of an older bag (TransformStamped) decodes to the same numbers as the PoseStamped
    it replays as (frame agent_<observer>, same stamp), which rosbags reads back alike."""
    ts = m.Encoder().ts
    t = ts.types
    q = (0.1, -0.2, 0.3, math.sqrt(1 - 0.14))
    old = t[m.TRANSFORM_STAMPED](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=3, nanosec=500), frame_id="agent_2"),
        child_frame_id="agent_1",
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=1.0, y=2.0, z=-3.0),
            rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        ),
    )
    data = bytes(ts.serialize_cdr(old, m.TRANSFORM_STAMPED))
    stamp, (p, R) = m.fast_decode("relative_pose", data, m.TRANSFORM_STAMPED)
    assert stamp == 3_000_000_500 and p == [1.0, 2.0, -3.0]
    new = m.pose_stamped_from_transform(data, "2")
    pose = m.deserialize(new, m.POSE_STAMPED)
    assert pose.header.frame_id == "agent_2" and m.stamp_ns(pose.header.stamp) == stamp
    assert m.fast_decode("relative_pose", new, m.POSE_STAMPED) == (stamp, (p, R))
    assert m.decode_relative_pose(pose) == m.decode_relative_pose(old) == (p, R)
