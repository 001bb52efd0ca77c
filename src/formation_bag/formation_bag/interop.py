"""Interoperability check of a bag: rosbags, and for MCAP the independent ``mcap``/``mcap_ros2`` readers.

:func:`check_bag` reads every message with rosbags (and deserializes it with the Jazzy
typestore); for MCAP segments it also reads every file with ``mcap.reader`` and decodes every
message with ``mcap_ros2.decoder``, and compares per-topic counts and the header stamps of both
readers; it checks that metadata.yaml has the keys, order and counts Jazzy's rosbag2 writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from formation_bag import messages as m
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


def check_bag(path: str | Path) -> InteropReport:
    """Read a bag with rosbags and (MCAP) with mcap + mcap_ros2; compare. See :class:`InteropReport`."""
    path = Path(path)
    report = InteropReport(path)
    if path.is_dir():
        check_metadata(path, report)
    ts = typestore()
    stamps_rb: dict[str, list[int | None]] = {}
    with Bag(path) as bag:
        report.lost = list(bag.lost)
        segments = list(bag.segments)
        listed = bag.topics
        for msg in bag.messages():
            try:
                obj = ts.deserialize_cdr(msg.data, msg.msgtype)
            except Exception as exc:
                report.problems.append(f"rosbags: {msg.topic} at {msg.log_time}: cannot deserialize ({exc})")
                continue
            report.counts_rosbags[msg.topic] = report.counts_rosbags.get(msg.topic, 0) + 1
            stamps_rb.setdefault(msg.topic, []).append(_stamp(obj))
        for name, info in listed.items():
            if info.count != report.counts_rosbags.get(name, 0):
                report.problems.append(
                    f"rosbags: {name}: {report.counts_rosbags.get(name, 0)} messages read, {info.count} listed"
                )
    mcaps = [s for s in segments if s.suffix == ".mcap"]
    if mcaps:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        counts: dict[str, int] = {}
        stamps_mc: dict[str, list[int | None]] = {}
        for seg in mcaps:
            with seg.open("rb") as f:
                reader = make_reader(f, decoder_factories=[DecoderFactory()])
                header = reader.get_header()
                if header.profile != "ros2":
                    report.problems.append(f"mcap: {seg}: profile {header.profile!r}, expected 'ros2'")
                for schema, channel, _message, decoded in reader.iter_decoded_messages(log_time_order=True):
                    if schema is None or schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                        report.problems.append(f"mcap: {seg}: {channel.topic}: not a ros2msg/cdr channel")
                    counts[channel.topic] = counts.get(channel.topic, 0) + 1
                    stamps_mc.setdefault(channel.topic, []).append(_stamp(decoded))
        report.counts_mcap = counts
        if counts != report.counts_rosbags:
            report.problems.append(f"mcap: per-topic counts {counts} differ from rosbags' {report.counts_rosbags}")
        for topic, st in stamps_rb.items():
            if sorted(x for x in st if x is not None) != sorted(x for x in stamps_mc.get(topic, []) if x is not None):
                report.problems.append(f"mcap: {topic}: header stamps differ between rosbags and mcap_ros2")
    return report
