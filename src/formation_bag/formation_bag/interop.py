"""Interoperability check of a bag: rosbags, and for MCAP the independent ``mcap``/``mcap_ros2`` readers.

:func:`check_bag` reads every message with rosbags (and deserializes it with the Jazzy
typestore); for MCAP files it also reads every file with ``mcap.reader`` and decodes every
message with ``mcap_ros2.decoder``, side by side in one pass, and compares per-topic counts and
the header stamps of both readers (as an order-free digest per topic: memory does not grow with
the bag); it checks that metadata.yaml has the keys, order and counts Jazzy's rosbag2 writes.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import zip_longest
from pathlib import Path
from typing import Any

import yaml

from formation_bag import messages as m
from formation_bag.progress import Progress
from formation_bag.reader import Bag
from formation_msgs_py.bag.writer import typestore

#: top-level keys of metadata.yaml version 9, in the order rosbag2 (Jazzy) writes them
JAZZY_KEYS = (
    "version",
    "storage_identifier",
    "duration",
    "starting_time",
    "message_count",
    "topics_with_message_count",
    "compression_format",
    "compression_mode",
    "relative_file_paths",
    "files",
    "custom_data",
    "ros_distro",
)


@dataclass
class InteropReport:
    path: Path
    problems: list[str] = field(default_factory=list)
    counts_rosbags: dict[str, int] = field(default_factory=dict)
    counts_mcap: dict[str, int] | None = None
    lost: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "ok": self.ok,
            "problems": self.problems,
            "counts_rosbags": self.counts_rosbags,
            "counts_mcap": self.counts_mcap,
            "lost": self.lost,
        }


def _stamp(obj: Any) -> int | None:
    if hasattr(obj, "header"):
        return obj.header.stamp.sec * m.NS_PER_S + obj.header.stamp.nanosec
    if hasattr(obj, "clock"):
        return obj.clock.sec * m.NS_PER_S + obj.clock.nanosec
    return None


def check_metadata(path: Path, report: InteropReport) -> None:
    meta = path / "metadata.yaml"
    if not meta.exists():
        report.problems.append(f"{meta}: missing (a killed recorder's bag: run 'formation-bag repair {path}')")
        return
    doc = yaml.safe_load(meta.read_text(encoding="utf-8"))
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        report.problems.append(f"{meta}: no rosbag2_bagfile_information mapping")
        return
    keys = tuple(info)
    if keys != JAZZY_KEYS:
        report.problems.append(f"{meta}: keys {keys} differ from Jazzy's {JAZZY_KEYS}")
    if info.get("version") != 9:
        report.problems.append(f"{meta}: version {info.get('version')!r}, expected 9")
    files = info.get("files") or []
    rel = info.get("relative_file_paths") or []
    if [f.get("path") for f in files] != rel:
        report.problems.append(f"{meta}: files[].path {[f.get('path') for f in files]} != relative_file_paths {rel}")
    for f in rel:
        if not (path / f).exists():
            report.problems.append(f"{meta}: relative_file_paths lists {f}, which does not exist")
    total = sum(t.get("message_count", 0) for t in info.get("topics_with_message_count") or [])
    if total != info.get("message_count"):
        report.problems.append(f"{meta}: topic counts sum to {total}, message_count is {info.get('message_count')}")
    if sum(f.get("message_count", 0) for f in files) != info.get("message_count"):
        report.problems.append(f"{meta}: files[].message_count do not sum to message_count")
    for t in info.get("topics_with_message_count") or []:
        tm = t.get("topic_metadata", {})
        if not isinstance(tm.get("offered_qos_profiles"), list):
            report.problems.append(f"{meta}: {tm.get('name')}: offered_qos_profiles is not a list (version 9)")
        if not str(tm.get("type_description_hash", "")).startswith("RIHS01_"):
            report.problems.append(f"{meta}: {tm.get('name')}: type_description_hash is not RIHS01")


class StampDigest:
    """Per topic: message count and an order-free digest of the header stamps (sums of the stamps and
    of a 64-bit mix of them, modulo 2⁶⁴): equal for two readers that read the same stamps in any
    order, in constant memory however long the bag."""

    MASK = (1 << 64) - 1

    def __init__(self) -> None:
        self.topics: dict[str, list[int]] = {}

    def add(self, topic: str, stamp: int | None) -> None:
        d = self.topics.get(topic)
        if d is None:
            d = self.topics[topic] = [0, 0, 0]
        d[0] += 1
        if stamp is not None:
            d[1] = (d[1] + stamp) & self.MASK
            d[2] = (d[2] + _mix64(stamp)) & self.MASK

    def counts(self) -> dict[str, int]:
        return {t: d[0] for t, d in self.topics.items()}


def _mix64(x: int) -> int:
    """splitmix64's finaliser: a 64-bit mix of x (one stamp's contribution to a digest)."""
    x = (x + 0x9E3779B97F4A7C15) & StampDigest.MASK
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & StampDigest.MASK
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & StampDigest.MASK
    return x ^ (x >> 31)


def _rosbags_stamps(bag: Bag, report: InteropReport) -> Iterator[tuple[str, int | None]]:
    """(topic, header stamp) of every message rosbags reads and deserializes (problems reported)."""
    ts = typestore()
    for msg in bag.messages():
        try:
            obj = ts.deserialize_cdr(msg.data, msg.msgtype)
        except Exception as exc:
            report.problems.append(f"rosbags: {msg.topic} at {msg.log_time}: cannot deserialize ({exc})")
            continue
        yield msg.topic, _stamp(obj)


def _mcap_stamps(segments: list[Path], report: InteropReport) -> Iterator[tuple[str, int | None]]:
    """(topic, header stamp) of every message of the MCAP files, read by mcap and decoded by mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    for seg in segments:
        with seg.open("rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            header = reader.get_header()
            if header.profile != "ros2":
                report.problems.append(f"mcap: {seg}: profile {header.profile!r}, expected 'ros2'")
            for schema, channel, _message, decoded in reader.iter_decoded_messages(log_time_order=True):
                if schema is None or schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                    report.problems.append(f"mcap: {seg}: {channel.topic}: not a ros2msg/cdr channel")
                yield channel.topic, _stamp(decoded)


def check_bag(path: str | Path, *, prog: str = "formation-bag") -> InteropReport:
    """Read a bag with rosbags and (MCAP) with mcap + mcap_ros2 side by side in one pass (constant
    memory, a progress line every few seconds); compare. See :class:`InteropReport`."""
    path = Path(path)
    report = InteropReport(path)
    if path.is_dir():
        check_metadata(path, report)
    with Bag(path) as bag:
        report.lost = list(bag.lost)
        mcaps = [s for s in bag.segments if s.suffix == ".mcap"]
        listed = bag.topics
        rb, mc = StampDigest(), StampDigest() if mcaps else None
        progress = Progress(prog, f"checking {path.name}", bag.message_count)
        n = 0
        readers = zip_longest(_rosbags_stamps(bag, report), _mcap_stamps(mcaps, report) if mcaps else ())
        for from_rb, from_mc in readers:
            if from_rb is not None:
                rb.add(*from_rb)
                n += 1
                progress.update(n)
            if from_mc is not None and mc is not None:
                mc.add(*from_mc)
        progress.finish(n)
    report.counts_rosbags = rb.counts()
    for name, info in listed.items():
        if info.count != report.counts_rosbags.get(name, 0):
            report.problems.append(
                f"rosbags: {name}: {report.counts_rosbags.get(name, 0)} messages read, {info.count} listed"
            )
    if mc is not None:
        report.counts_mcap = mc.counts()
        if report.counts_mcap != report.counts_rosbags:
            report.problems.append(
                f"mcap: per-topic counts {report.counts_mcap} differ from rosbags' {report.counts_rosbags}"
            )
        for topic, digest in rb.topics.items():
            if digest[1:] != mc.topics.get(topic, [0, 0, 0])[1:]:
                report.problems.append(f"mcap: {topic}: header stamps differ between rosbags and mcap_ros2")
    return report
