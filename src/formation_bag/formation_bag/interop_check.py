"""Interoperability check of a bag: rosbags, and for MCAP the independent ``mcap``/``mcap_ros2`` readers.

:func:`check_bag` reads every message with rosbags and deserializes it with the Jazzy typestore;
for MCAP files it also reads every message with ``mcap.reader``, side by side in one streaming
pass, and compares per-topic counts and the messages' bytes (an order-free digest per topic:
memory does not grow with the bag). ``mcap_ros2`` decodes the first :data:`DECODE_SAMPLE`
messages of every channel of every file (every message on request), each compared field by field
with rosbags' decoding: the messages of a channel share one schema, and the bytes of every other
message are already shown equal, so the sample tests the decoders' agreement at a fraction of
the cost (decoding every message with ``mcap_ros2``, in log-time order, was three quarters of the
check's profiled time).
It checks that metadata.yaml has the keys, order and counts Jazzy's rosbag2 writes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import zip_longest
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from formation_bag.progress import Progress
from formation_bag.reader import Bag
from formation_bag.writer import typestore

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

#: messages of every channel of every MCAP file that ``mcap_ros2`` decodes by default
DECODE_SAMPLE = 100


@dataclass
class InteropReport:
    path: Path
    problems: list[str] = field(default_factory=list)
    counts_rosbags: dict[str, int] = field(default_factory=dict)
    counts_mcap: dict[str, int] | None = None
    decoded_mcap_ros2: int = 0
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
            "decoded_mcap_ros2": self.decoded_mcap_ros2,
            "lost": self.lost,
        }


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


class BytesDigest:
    """Per topic: message count and an order-free digest of the messages' bytes (the sum of their
    hashes modulo 2⁶⁴): equal for two readers that read the same messages in any order, in constant
    memory however long the bag. The hashes are Python's, stable within one process only."""

    MASK = (1 << 64) - 1

    def __init__(self) -> None:
        self.topics: dict[str, list[int]] = {}

    def add(self, topic: str, data: bytes) -> None:
        d = self.topics.get(topic)
        if d is None:
            d = self.topics[topic] = [0, 0]
        d[0] += 1
        d[1] = (d[1] + hash(data)) & self.MASK

    def counts(self) -> dict[str, int]:
        return {t: d[0] for t, d in self.topics.items()}


def plain(obj: Any) -> Any:
    """A decoded message as nested dicts, lists and numbers, whichever decoder made it (rosbags'
    dataclasses and numpy arrays, mcap_ros2's slotted classes and byte strings)."""
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, (bytes, bytearray)):
        return list(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if dataclasses.is_dataclass(obj):
        # rosbags' message constants (DiagnosticStatus.OK) are fields typed "ClassVar[...]" as text
        fields = [f for f in dataclasses.fields(obj) if not str(f.type).startswith("ClassVar")]
        return {f.name: plain(getattr(obj, f.name)) for f in fields}
    slots = getattr(type(obj), "__slots__", None)
    if slots is not None:
        return {s: plain(getattr(obj, s)) for s in slots}
    raise TypeError(f"cannot compare a decoded {type(obj).__name__}")


def _same(a: Any, b: Any) -> bool:
    """Equal decoded values; NaN equals NaN (both decoders read the same bytes)."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return bool(a == b)


def _rosbags_bytes(bag: Bag, report: InteropReport) -> Iterator[tuple[str, bytes]]:
    """(topic, bytes) of every message rosbags reads, each deserialized with the Jazzy typestore."""
    ts = typestore()
    for msg in bag.messages():
        data = bytes(msg.data)
        try:
            ts.deserialize_cdr(data, msg.msgtype)
        except Exception as exc:
            report.problems.append(f"rosbags: {msg.topic} at {msg.log_time}: cannot deserialize ({exc})")
        yield msg.topic, data


class _McapSide:
    """The independent side: ``mcap.reader`` reads every message of the MCAP files in file order (the
    digests need no log-time order), checking the chunks' CRCs; ``mcap_ros2`` decodes the first
    ``sample`` messages of every channel of every file (all with ``sample=None``), each compared
    field by field with rosbags' decoding of the same bytes."""

    def __init__(self, segments: list[Path], report: InteropReport, sample: int | None) -> None:
        self.segments, self.report, self.sample = segments, report, sample
        self.decoded = 0
        self._ts = typestore()
        self._mismatches: dict[str, int] = {}

    def messages(self) -> Iterator[tuple[str, bytes]]:
        from mcap.reader import NonSeekingReader, make_reader
        from mcap_ros2.decoder import DecoderFactory

        factory = DecoderFactory()
        for seg in self.segments:
            with seg.open("rb") as f:
                header = make_reader(f).get_header()
            if header.profile != "ros2":
                self.report.problems.append(f"mcap: {seg}: profile {header.profile!r}, expected 'ros2'")
            # the streaming reader, in file order: the seeking one, unordered, decompresses every
            # chunk before its first message (the whole file in memory)
            with seg.open("rb") as f:
                reader = NonSeekingReader(f, validate_crcs=True)
                try:
                    yield from self._segment(seg, reader.iter_messages(log_time_order=False), factory)
                except Exception as exc:  # a damaged file: whatever mcap raises, the check reports it
                    self.report.problems.append(f"mcap: {seg}: unreadable ({type(exc).__name__}: {exc})")

    def _segment(self, seg: Path, messages: Iterator[Any], factory: Any) -> Iterator[tuple[str, bytes]]:
        decoded_here: dict[int, int] = {}
        decoders: dict[int, Any] = {}
        for schema, channel, message in messages:
            if channel.id not in decoders:
                if schema is None or schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                    self.report.problems.append(f"mcap: {seg}: {channel.topic}: not a ros2msg/cdr channel")
                    decoders[channel.id] = None
                else:
                    decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            k = decoded_here.get(channel.id, 0)
            decoder = decoders[channel.id]
            if decoder is not None and (self.sample is None or k < self.sample):
                decoded_here[channel.id] = k + 1
                self._compare(seg, channel.topic, schema.name if schema else "", decoder, message.data)
            yield channel.topic, message.data

    def _compare(self, seg: Path, topic: str, msgtype: str, decoder: Any, data: bytes) -> None:
        self.decoded += 1
        try:
            theirs = plain(decoder(data))
        except Exception as exc:
            self.report.problems.append(f"mcap_ros2: {seg}: {topic}: cannot decode ({exc})")
            return
        try:
            ours = plain(self._ts.deserialize_cdr(data, msgtype))
        except Exception:
            return  # rosbags' own failure is reported by its side
        if not _same(ours, theirs):
            n = self._mismatches[topic] = self._mismatches.get(topic, 0) + 1
            if n == 1:
                self.report.problems.append(f"mcap_ros2: {seg}: {topic}: decodes a message unlike rosbags")


def check_bag(path: str | Path, *, prog: str = "formation-bag", sample: int | None = DECODE_SAMPLE) -> InteropReport:
    """Read a bag with rosbags and (MCAP) with ``mcap`` side by side in one streaming pass (constant
    memory, a progress line every few seconds); compare. See the module docstring and
    :class:`InteropReport`; ``sample=None`` has ``mcap_ros2`` decode every message."""
    path = Path(path)
    report = InteropReport(path)
    if path.is_dir():
        check_metadata(path, report)
    with Bag(path) as bag:
        report.lost = list(bag.lost)
        mcaps = [s for s in bag.segments if s.suffix == ".mcap"]
        listed = bag.topics
        rb = BytesDigest()
        mc = BytesDigest() if mcaps else None
        side = _McapSide(mcaps, report, sample) if mcaps else None
        progress = Progress(prog, f"checking {path.name}", bag.message_count)
        n = 0
        for from_rb, from_mc in zip_longest(_rosbags_bytes(bag, report), side.messages() if side else ()):
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
    if mc is not None and side is not None:
        report.counts_mcap = mc.counts()
        report.decoded_mcap_ros2 = side.decoded
        if report.counts_mcap != report.counts_rosbags:
            report.problems.append(
                f"mcap: per-topic counts {report.counts_mcap} differ from rosbags' {report.counts_rosbags}"
            )
        for topic, digest in rb.topics.items():
            if digest[1] != mc.topics.get(topic, [0, 0])[1]:
                report.problems.append(f"mcap: {topic}: the messages' bytes differ between rosbags and mcap")
    return report
