"""The simulator's own bag (formation_sim.node.run_bag), without ROS: log times, counts, an I/O error."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader

from formation_bag.writer import make_qos
from formation_msgs_py import codec
from formation_sim.node.run_bag import RunBag

CLOCK, WRENCH, FUNNELS = "/clock", "/agent_1/wrench", "/formation/funnels"
GT, MARKERS = "/formation/ground_truth", "/formation/markers"
STEP_NS = 100_000  # 10 kHz


def _bag(path: Path, max_bytes: int | None = None) -> RunBag:
    bag = RunBag(path, {"mode": "lockstep", "formation_file": "f.yaml"}, max_bytes=max_bytes)
    bag.add_topic(CLOCK, "rosgraph_msgs/msg/Clock", make_qos(depth=1), published=True)
    bag.add_topic(WRENCH, "geometry_msgs/msg/WrenchStamped", make_qos(), published=False)
    bag.add_topic(FUNNELS, "std_msgs/msg/Float64MultiArray", make_qos(), published=True)
    return bag


def _log_times(path: Path) -> dict[str, list[int]]:
    """Log times per topic, in the order the reader returns them (by log time)."""
    out: dict[str, list[int]] = {}
    with Reader(path) as reader:
        for conn, t, _ in reader.messages():
            out.setdefault(conn.topic, []).append(t)
    return out


def test_log_time_is_simulation_time(tmp_path: Path) -> None:
    """Stamped messages are logged at their stamp; unstamped ones (funnels) and malformed ones at the
    latest stamp the simulator itself published, never at a stamp an agent claimed."""
    bag = _bag(tmp_path / "bag")
    wrench = codec.wrench_codec("1")
    for k in range(3):
        bag.write(CLOCK, codec.clock_bytes(k * STEP_NS))
        bag.write(FUNNELS, b"\x00\x01\x00\x00" + bytes(12))  # contents are not read
        bag.write(WRENCH, wrench.encode(k * STEP_NS, [float(k)] * 6))
    bag.write(WRENCH, wrench.encode(10**12, [0.0] * 6))  # from the future: refused by the node, kept here
    bag.write(WRENCH, b"\x00\x01")  # malformed
    bag.write(FUNNELS, b"\x00\x01\x00\x00" + bytes(12))
    counts = bag.close()
    assert bag.failed is None
    assert counts == {
        "received": 12,
        "written": 12,
        "not_recorded": 0,
        "not_recorded_by_topic": {},
        "missed_start": None,
        "writer": "simulator",
    }
    times = _log_times(tmp_path / "bag")
    assert times[CLOCK] == [0, STEP_NS, 2 * STEP_NS]
    assert times[FUNNELS] == [0, STEP_NS, 2 * STEP_NS, 2 * STEP_NS]
    assert times[WRENCH] == [0, STEP_NS, 2 * STEP_NS, 2 * STEP_NS, 10**12]  # read back in log-time order
    custom = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    custom = custom["custom_data"]
    assert custom["mode"] == "lockstep" and custom["formation_file"] == "f.yaml"
    stored = json.loads(custom["recorder_counts"])
    assert stored["written"] == {CLOCK: 3, WRENCH: 5, FUNNELS: 4}
    # the simulator's own topics: every publication written; received ones: publisher unknown here
    assert stored["published_total"] == {CLOCK: 3, WRENCH: None, FUNNELS: 4}
    assert stored["log_time"] == "sim"


@pytest.mark.parametrize(("max_bytes", "files"), [(None, 1), (20_000, 3)])
def test_one_file_unless_a_size_is_given_and_the_wall_time_noted(tmp_path: Path, max_bytes, files) -> None:
    """The run's bag is one file by default; --max-bag-size splits it (each file closed once it holds about
    that many bytes); custom_data.wall_time is the wall span from the first to the last message written."""
    bag = _bag(tmp_path / "bag", max_bytes)
    for k in range(1000):  # 1000 × (12 B + 48 B of MCAP record and index) ≈ 60 kB
        bag.write(CLOCK, codec.clock_bytes(k * STEP_NS))
    bag.close()
    info = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert len(info["relative_file_paths"]) == files
    assert sum(f["message_count"] for f in info["files"]) == 1000
    assert 0.0 <= float(info["custom_data"]["wall_time"]) < 600.0  # a duration in s: not a log-time span


def test_a_failed_write_stops_the_bag_and_counts_what_is_lost(tmp_path: Path) -> None:
    """A write that fails (here: to a closed writer) names the bag; later messages are counted, not written."""
    bag = _bag(tmp_path / "bag")
    bag.write(CLOCK, codec.clock_bytes(0))
    bag.writer.close()
    bag.write(CLOCK, codec.clock_bytes(STEP_NS))
    bag.write(WRENCH, codec.wrench_codec("1").encode(STEP_NS, [0.0] * 6))
    assert bag.failed is not None and str(tmp_path / "bag") in bag.failed and "closed" in bag.failed
    counts = bag.close()
    assert counts["written"] == 1 and counts["not_recorded"] == 2
    assert counts["not_recorded_by_topic"] == {CLOCK: 1, WRENCH: 1}


def test_an_existing_bag_is_not_overwritten(tmp_path: Path) -> None:
    (tmp_path / "bag").mkdir()
    with pytest.raises(FileExistsError, match="exists already"):
        RunBag(tmp_path / "bag", {})


def test_display_messages_are_stored_with_zeroed_padding(tmp_path: Path) -> None:
    """rclpy's serialize_message leaves CDR alignment padding uninitialised: the bag gets the same
    values with zeros there (deterministic bytes); publications are stored padded to 4 bytes, as
    Fast DDS delivers them."""
    bag = _bag(tmp_path / "bag")
    store = bag.writer.store
    t = store.types
    msg = t["std_msgs/msg/Float64MultiArray"](
        layout=t["std_msgs/msg/MultiArrayLayout"](
            dim=[t["std_msgs/msg/MultiArrayDimension"](label="ab", size=2, stride=2)], data_offset=0
        ),
        data=np.array([1.5, -2.0]),
    )
    clean = bytes(store.serialize_cdr(msg, "std_msgs/msg/Float64MultiArray"))
    pad = clean.index(b"ab\x00") + 3  # one byte of padding before the uint32 size
    dirty = clean[:pad] + b"\x7f" + clean[pad + 1 :]
    assert clean[pad] == 0 and len(clean) % 4 == 0
    assert bag.zero_padded(FUNNELS, dirty) == clean
    # a publication that ends unaligned (a string) is stored padded to 4 bytes, as DDS delivers it
    bag.add_topic("/text", "std_msgs/msg/String", make_qos(), published=True)
    text = bytes(store.serialize_cdr(t["std_msgs/msg/String"](data="ab"), "std_msgs/msg/String"))
    bag.write_sent("/text", text)
    bag.write_sent(FUNNELS, clean)
    bag.close()
    with Reader(tmp_path / "bag") as reader:
        stored = {conn.topic: data for conn, _, data in reader.messages()}
    assert len(text) == 11 and stored["/text"] == text + b"\x00"
    assert stored[FUNNELS] == clean


def test_publications_held_are_written_in_order_when_the_hold_ends(tmp_path: Path) -> None:
    """RunBag.held: nothing is written inside, everything in order after (also when it raises)."""
    bag = _bag(tmp_path / "bag")
    with bag.held():
        for k in range(3):
            bag.write_sent(CLOCK, codec.clock_bytes(k * STEP_NS))
        assert bag.written[CLOCK] == 0
    assert bag.written[CLOCK] == 3
    with pytest.raises(RuntimeError), bag.held():
        bag.write_sent(CLOCK, codec.clock_bytes(3 * STEP_NS))
        raise RuntimeError("a publish failed")
    assert bag.written[CLOCK] == 4
    bag.write_sent(CLOCK, codec.clock_bytes(4 * STEP_NS))  # not held: at once
    assert bag.written[CLOCK] == 5
    bag.close()
    assert _log_times(tmp_path / "bag")[CLOCK] == [k * STEP_NS for k in range(5)]


def test_view_file_holds_the_display_topics_and_the_rest_at_the_display_rate(tmp_path: Path) -> None:
    """OUT/view.mcap: markers, funnels and /diagnostics whole, /clock and the ground truth on the
    30 Hz display grid (the first message at or after each k/30 s), read with the mcap reader; the
    bag keeps every message; a view file that exists is refused before the bag is made."""
    from mcap.reader import make_reader

    bag = RunBag(tmp_path / "bag", {"mode": "lockstep"}, view=tmp_path / "view.mcap", view_rate=30.0)
    bag.add_topic(CLOCK, "rosgraph_msgs/msg/Clock", make_qos(depth=1), published=True)
    bag.add_topic(GT, "geometry_msgs/msg/PoseArray", make_qos(), published=True)
    bag.add_topic(MARKERS, "visualization_msgs/msg/MarkerArray", make_qos(), published=True)
    bag.add_topic(WRENCH, "geometry_msgs/msg/WrenchStamped", make_qos(), published=False)
    wrench = codec.wrench_codec("1")
    for k in range(2001):  # 0.2 s at 10 kHz
        bag.write(CLOCK, codec.clock_bytes(k * STEP_NS))
        bag.write(GT, codec.clock_bytes(k * STEP_NS))  # a stamp first: all the log time needs
        bag.write(WRENCH, wrench.encode(k * STEP_NS, [0.0] * 6))
        if k % 333 == 0:
            bag.write(MARKERS, b"\x00\x01\x00\x00" + bytes(4))
    counts = bag.close()
    assert counts["view"] == {"path": str(tmp_path / "view.mcap"), "written": 2 * 7 + 7, "failed": None}
    times: dict[str, list[int]] = {}
    with (tmp_path / "view.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            times.setdefault(channel.topic, []).append(message.log_time)
    # 0, then the first 100 µs step at or after k/30 s: 33.4, 66.7, 100, 133.4, 166.7, 200 ms
    grid = [0, 33_400_000, 66_700_000, 100_000_000, 133_400_000, 166_700_000, 200_000_000]
    assert times[CLOCK] == grid and times[GT] == grid
    assert times[MARKERS] == [k * STEP_NS for k in range(0, 2001, 333)]
    assert WRENCH not in times  # not a display topic
    assert _log_times(tmp_path / "bag")[CLOCK] == [k * STEP_NS for k in range(2001)]
    with pytest.raises(FileExistsError, match="view file"):
        RunBag(tmp_path / "bag2", {}, view=tmp_path / "view.mcap")
    assert not (tmp_path / "bag2").exists()


class _DiskFull:
    """A file that takes ``room`` more bytes, then writes what fits and fails as a full disk does."""

    def __init__(self, f, room: int) -> None:
        self.f, self.room = f, room

    def write(self, data) -> int:
        data = bytes(data)
        if len(data) > self.room:
            self.f.write(data[: self.room])
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.f.write(data)

    def __getattr__(self, name: str):
        return getattr(self.f, name)


def test_a_full_disk_keeps_every_flushed_second_for_repair(tmp_path: Path) -> None:
    """The disk fills during the third second of log time: the run's bag fails (named), and repair
    recovers every message of the first two seconds, the chunks flushed before the disk was full."""
    from formation_bag.reader import Bag, repair

    bag = _bag(tmp_path / "bag")
    bag.write(CLOCK, codec.clock_bytes(0))
    storage = bag.writer._open.storage
    # a Clock message takes ~60 B with its index: a 1 s chunk (10 000 of them) ~0.6 MB; room for two
    storage.bio = _DiskFull(storage.bio, 1_400_000)
    for k in range(1, 35_000):
        bag.write(CLOCK, codec.clock_bytes(k * STEP_NS))
    counts = bag.close()
    assert bag.failed is not None and "No space left on device" in bag.failed
    assert counts["not_recorded"] > 0
    _, lost = repair(tmp_path / "bag")
    assert len(lost) == 1 and "recovered into bag_0.mcap" in lost[0]
    with Bag(tmp_path / "bag") as b:
        times = [msg.log_time for msg in b.messages()]
        assert "20002 messages up to 2.0001 s" in b.custom_data["repaired"]
    # chunks close once they span 1 s: [0, 1.0000] and [1.0001, 2.0001] reached the disk whole
    assert times == [k * STEP_NS for k in range(20_002)]
