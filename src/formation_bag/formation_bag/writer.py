"""A rosbag2 writer that writes in segments, so a killed recorder loses at most the last one.

The bag is a standard multi-file rosbag2 directory as Jazzy's ``ros2 bag record`` leaves it
(metadata version 9)::

    BAG/metadata.yaml        relative_file_paths: [BAG_0.mcap, BAG_1.mcap, …], files: per-file info
    BAG/BAG_0.mcap           closed segments (complete MCAP files with summary and index)
    BAG/BAG_1.mcap
    BAG/.BAG_2/.BAG_2.mcap   the open segment (moved to BAG/BAG_2.mcap when it is closed)

Each segment is written by rosbags' :class:`rosbags.rosbag2.Writer` (typestore ``ROS2_JAZZY``)
into a hidden directory and moved next to the others when it is closed; ``metadata.yaml`` is
rewritten atomically after every closed segment. A recorder killed with SIGKILL therefore
leaves a readable bag of every closed segment (``ros2 bag info`` works as is) and loses only
the open one (rosbags keeps a segment in memory or in an uncommitted transaction until close).

Segments close after ``segment_seconds`` of log time or ``segment_bytes`` of file, whichever
comes first, checked at every write; a segment's size is its payload plus
:data:`MESSAGE_OVERHEAD` per message.

Within the open MCAP segment, a chunk is closed, written and flushed to the operating system as
soon as it holds :data:`CHUNK_BYTES` or ``chunk_seconds`` (default 1 s) of log time, and the
segment's custom_data is written at its start (a Metadata record named :data:`CUSTOM_DATA_RECORD`):
a writer killed with SIGKILL, or stopped by a full disk, leaves every chunk but the open one and
the run's settings on disk, and ``formation-bag repair`` makes a complete file of them. In
lockstep the log time is simulation time: a crash loses at most the last second of the run.

Over 500 lines: this is the one module that reaches into rosbags' internals (an MCAP writer
subclassed, its chunks and records written directly), so that an upgrade of rosbags breaks here
and nowhere else; tests/test_library_internals.py checks every internal it uses.
"""

from __future__ import annotations

import os
import shutil
import struct
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import version as package_version
from io import BytesIO
from pathlib import Path
from types import MappingProxyType, TracebackType
from typing import TYPE_CHECKING, Any

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    MessageDefinition,
    MessageDefinitionFormat,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk, write_record, write_string
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from formation_bag.metadata import METADATA_VERSION, STORAGES, SegmentInfo, metadata_yaml, qos_yaml
from formation_core.errors import BagExistsError, BagWriterError

if TYPE_CHECKING:
    from rosbags.rosbag2.writer import StorageWriter  # a Protocol rosbags declares for type checkers only

#: rmw's "infinite" duration, as Jazzy writes it in metadata.yaml
INFINITE = QosTime(sec=9223372036, nsec=854775807)
ZERO = QosTime(sec=0, nsec=0)

#: bytes of MCAP record and message index per message beyond its payload (the paper's default run:
#: a 142 890 890 B file for 97 358 996 B of payload in 965 765 messages, 47.1 B each)
MESSAGE_OVERHEAD = 48
#: rosbags' MCAP writer closes a chunk once it holds more than this
CHUNK_BYTES = 2**20
#: log time [s] after which a chunk is closed and flushed even if small (what a crash may lose)
CHUNK_SECONDS = 1.0
#: name of the MCAP Metadata record, written at a file's start, that holds the writer's custom_data
#: (rosbag2 stores it only in the "rosbag2" record written at close, which a killed writer never writes)
CUSTOM_DATA_RECORD = "formation_custom_data"


@cache
def typestore() -> Typestore:
    """The ROS 2 Jazzy typestore (shared, built once)."""
    return get_typestore(Stores.ROS2_JAZZY)


def make_qos(*, depth: int = 10, reliable: bool = True, transient_local: bool = False, keep_all: bool = False) -> Qos:
    """A rosbags Qos record (offered QoS of a topic, stored in metadata.yaml)."""
    return Qos(
        history=QosHistory.KEEP_ALL if keep_all else QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
        deadline=INFINITE,
        lifespan=INFINITE,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=INFINITE,
        avoid_ros_namespace_conventions=False,
    )


def offered_qos(profile: Any) -> Qos:
    """The offered QoS of an rclpy ``QoSProfile`` as a bag stores it (metadata.yaml), read by its policies'
    names so that this module needs no rclpy."""
    return make_qos(
        depth=int(profile.depth),
        reliable=profile.reliability.name != "BEST_EFFORT",
        transient_local=profile.durability.name == "TRANSIENT_LOCAL",
        keep_all=profile.history.name == "KEEP_ALL",
    )


#: an MCAP Message record's head: opcode 0x05, record length, channel id, sequence 0, log and
#: publish time (both the log time, as rosbags writes them); the serialized message follows
_MCAP_MESSAGE = struct.Struct("<BQHIQQ")
_MCAP_MESSAGE_FIELDS = 2 + 4 + 8 + 8


class _McapWriter(McapWriter):
    """rosbags' MCAP writer with a message write of one ``struct`` pack instead of ~12 calls, and
    chunks closed by log time too (``chunk_ns``) and flushed when closed.

    Every message of a run passes here (~20 per lockstep step): a whole write took 7 µs, now 3.5 µs
    (BENCHMARKS.md, "Bags"). With ``chunk_ns`` None the bytes are rosbags' own
    (tests/formation_bag/test_bag_io.py compares the files).
    """

    #: close the open chunk once its messages span this much log time [ns] (None: by size only)
    chunk_ns: int | None = None

    def write_custom_data(self, custom_data: dict[str, str]) -> None:
        """A Metadata record (``name`` :data:`CUSTOM_DATA_RECORD`) in the data section, flushed:
        the settings a salvaged file needs. Readers of rosbag2 MCAP files ignore other names."""
        rec = BytesIO()
        write_string(rec, CUSTOM_DATA_RECORD)
        body = BytesIO()
        for key, value in custom_data.items():
            write_string(body, key)
            write_string(body, value)
        rec.write(struct.pack("<I", body.tell()))
        rec.write(body.getbuffer())
        write_record(self.bio, 0x0C, rec)
        self.bio.flush()

    def close_chunk(self) -> None:
        """Close the open chunk and hand it to the operating system (a killed process loses nothing of it)."""
        super().close_chunk()
        self.bio.flush()

    def write(self, connection: Connection, timestamp: int, data: bytes | memoryview) -> None:
        chunk = self.chunk
        if timestamp < self.message_start_time:
            self.message_start_time = timestamp
        if timestamp > self.message_end_time:
            self.message_end_time = timestamp
        if timestamp < chunk.message_start_time:
            chunk.message_start_time = timestamp
        if timestamp > chunk.message_end_time:
            chunk.message_end_time = timestamp
        self.channel_stats[connection.id] += 1
        bio = chunk.bio
        chunk.msgs[connection.id].append((timestamp, bio.tell()))
        bio.write(_MCAP_MESSAGE.pack(0x05, _MCAP_MESSAGE_FIELDS + len(data), connection.id, 0, timestamp, timestamp))
        bio.write(data)
        if bio.tell() > CHUNK_BYTES or (
            self.chunk_ns is not None and chunk.message_end_time - chunk.message_start_time >= self.chunk_ns
        ):
            self.close_chunk()


class _SegmentFileWriter(Writer):
    """rosbags' Writer for one segment, with its slow (ruamel) YAML dumps replaced.

    rosbags dumps the QoS of every connection and the file metadata with ruamel.yaml, ~30 ms per
    topic: a recorder would stall for a second at every segment. Connections and the embedded
    metadata are the same records, emitted by :mod:`formation_bag.metadata` (libyaml).
    MCAP messages are written by :class:`_McapWriter`.
    """

    # declared as rosbags declares it (an attribute each writer reads), with MCAP written by ours
    STORAGE_PLUGINS: Mapping[StoragePlugin, type[StorageWriter]] = MappingProxyType(
        {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _McapWriter}
    )

    def add_topic_fast(self, topic: str, msgtype: str, msgdef: str, rihs01: str, qos: list[Qos]) -> Connection:
        if not self.storage:
            raise BagWriterError(f"segment {self.path} is not open")
        fmt = MessageDefinitionFormat.IDL if msgdef.startswith("=" * 80 + "\nIDL: ") else MessageDefinitionFormat.MSG
        connection = Connection(
            id=len(self.connections) + 1,
            topic=topic,
            msgtype=msgtype,
            msgdef=MessageDefinition(fmt, msgdef),
            digest=rihs01,
            msgcount=0,
            ext=ConnectionExtRosbag2(serialization_format="cdr", offered_qos_profiles=list(qos)),
            owner=self,
        )
        if msgtype not in self.added_types:
            self.storage.add_msgtype(connection)
            self.added_types.add(msgtype)
        self.storage.add_connection(connection, qos_yaml(qos))
        self.connections.append(connection)
        self.counts[connection.id] = 0
        return connection

    def close_fast(self, embedded_metadata: str) -> None:
        """Finish the storage file (index, summary, embedded metadata); no metadata.yaml."""
        if not self.storage:
            raise BagWriterError(f"segment {self.path} is not open")
        self.storage.close(self.version, embedded_metadata)
        self.storage = None


@dataclass
class TopicRecord:
    name: str
    msgtype: str
    qos: tuple[Qos, ...]
    count: int = 0


@dataclass
class _Open:
    writer: _SegmentFileWriter
    tmpdir: Path
    final: Path
    connections: dict[str, Connection] = field(default_factory=dict)
    start: int = 2**63 - 1
    end: int = 0
    count: int = 0
    size: int = 0
    opened_at: int = 0  # log time of its first message (set by the write that opens it)
    storage: Any = None  # the rosbags storage plugin writer of this segment
    counts: dict[int, int] = field(default_factory=dict)  # the segment writer's per-connection counts


class SegmentedBagWriter:
    """Write a rosbag2 bag in segments. Use as a context manager; ``close()`` finishes the bag.

    MCAP chunks close at :data:`CHUNK_BYTES` or ``chunk_seconds`` of log time (None: by size
    only, rosbags' own files) and are flushed when they close.

    ``write(topic, timestamp_ns, data)`` takes CDR-serialized messages (what a raw ROS
    subscription delivers). Register topics first with :meth:`add_topic`; topics may be added
    at any time (they appear from the segment that is open then).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        storage: str = "mcap",
        segment_seconds: float | None = 2.0,
        segment_bytes: int | None = 64 * 1024 * 1024,
        custom_data: dict[str, str] | None = None,
        store: Typestore | None = None,
        chunk_seconds: float | None = CHUNK_SECONDS,
    ) -> None:
        self.path = Path(path)
        if storage not in STORAGES:
            raise BagWriterError(f"storage {storage!r} is not one of {', '.join(STORAGES)}")
        if self.path.exists():
            raise BagExistsError(self.path, "bag")
        if segment_seconds is not None and segment_seconds <= 0:
            raise BagWriterError(f"segment_seconds must be positive, got {segment_seconds!r}")
        if segment_bytes is not None and segment_bytes <= 0:
            raise BagWriterError(f"segment_bytes must be positive, got {segment_bytes!r}")
        if chunk_seconds is not None and chunk_seconds <= 0:
            raise BagWriterError(f"chunk_seconds must be positive, got {chunk_seconds!r}")
        self.chunk_ns = None if chunk_seconds is None else round(chunk_seconds * 1e9)
        self.storage = storage
        self.plugin, self.suffix = STORAGES[storage]
        self.segment_ns = None if segment_seconds is None else round(segment_seconds * 1e9)
        self.segment_bytes = segment_bytes
        self.custom_data = dict(custom_data or {})
        self.store = store or typestore()
        self.topics: dict[str, TopicRecord] = {}
        self.segments: list[SegmentInfo] = []
        self._open: _Open | None = None
        self._index = 0
        self._closed = False
        self._msgdefs: dict[str, tuple[str, str]] = {}
        self._closed_counts: dict[str, int] = {}
        self.path.mkdir(parents=True)

    # -- context manager ----------------------------------------------------------------------

    def __enter__(self) -> SegmentedBagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- topics and messages ------------------------------------------------------------------

    def add_topic(self, name: str, msgtype: str, qos: tuple[Qos, ...] | list[Qos] = ()) -> None:
        """Register a topic (absolute name, ROS 2 type such as ``geometry_msgs/msg/TwistStamped``)."""
        if self._closed:
            raise BagWriterError(f"bag {self.path} is closed")
        if name in self.topics:
            if self.topics[name].msgtype != msgtype:
                raise BagWriterError(f"topic {name} is {self.topics[name].msgtype}, cannot add it as {msgtype}")
            return
        if msgtype not in self.store.types:
            raise BagWriterError(f"topic {name}: type {msgtype} is not in the ROS2_JAZZY typestore")
        self.topics[name] = TopicRecord(name, msgtype, tuple(qos) or (make_qos(),))
        if self._open is not None:
            self._connect(self._open, self.topics[name])

    def write(self, topic: str, timestamp: int, data: bytes | memoryview) -> None:
        """Write one serialized message with log time ``timestamp`` (ns since the epoch)."""
        seg = self._open
        if seg is None or (
            (self.segment_ns is not None and timestamp - seg.opened_at >= self.segment_ns)
            or (self.segment_bytes is not None and seg.size >= self.segment_bytes)
        ):
            if self._closed:
                raise BagWriterError(f"bag {self.path} is closed")
            if topic not in self.topics:
                raise BagWriterError(f"topic {topic} was not added to bag {self.path}")
            if seg is not None:
                self._close_segment()
            seg = self._open_segment()
            seg.opened_at = timestamp
        conn = seg.connections.get(topic)
        if conn is None:  # every added topic has a connection in the open segment (add_topic)
            raise BagWriterError(f"topic {topic} was not added to bag {self.path}")
        # rosbags' Writer.write minus its per-message checks (the connection is ours, no compression)
        seg.storage.write(conn, timestamp, data)
        seg.counts[conn.id] += 1
        seg.count += 1
        seg.size += len(data) + MESSAGE_OVERHEAD
        if timestamp < seg.start:
            seg.start = timestamp
        if timestamp > seg.end:
            seg.end = timestamp
        self.topics[topic].count += 1

    def split(self) -> None:
        """Close the open segment now (the next write opens a new one)."""
        if self._open is not None:
            self._close_segment()

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def close(self) -> None:
        """Close the open segment and write the final metadata.yaml (idempotent)."""
        if self._closed:
            return
        if self._open is not None:
            self._close_segment()
        self._write_metadata()
        self._closed = True

    # -- segments -----------------------------------------------------------------------------

    def _seg_name(self, index: int) -> str:
        return f"{self.path.name}_{index}"

    def _open_segment(self) -> _Open:
        name = self._seg_name(self._index)
        tmpdir = self.path / f".{name}"
        final = self.path / f"{name}{self.suffix}"
        if tmpdir.exists() or final.exists():
            raise BagExistsError(final, "segment")
        writer = _SegmentFileWriter(tmpdir, version=METADATA_VERSION, storage_plugin=self.plugin)
        try:
            writer.open()
        except (WriterError, OSError) as exc:
            raise BagWriterError(f"cannot open segment {tmpdir}: {exc}") from exc
        seg = _Open(writer, tmpdir, final)
        seg.storage = writer.storage
        if isinstance(seg.storage, _McapWriter):
            seg.storage.chunk_ns = self.chunk_ns
            if self.custom_data:
                try:
                    seg.storage.write_custom_data(self.custom_data)
                except OSError as exc:
                    raise BagWriterError(f"cannot write segment {tmpdir}: {exc}") from exc
        seg.counts = writer.counts
        for rec in self.topics.values():
            self._connect(seg, rec)
        self._open = seg
        self._index += 1
        return seg

    def _connect(self, seg: _Open, rec: TopicRecord) -> None:
        msgdef, digest = self._msgdef(rec.msgtype)
        seg.connections[rec.name] = seg.writer.add_topic_fast(rec.name, rec.msgtype, msgdef, digest, list(rec.qos))

    def _msgdef(self, msgtype: str) -> tuple[str, str]:
        if msgtype not in self._msgdefs:
            self._msgdefs[msgtype] = (
                self.store.generate_msgdef(msgtype, ros_version=2)[0],
                self.store.hash_rihs01(msgtype),
            )
        return self._msgdefs[msgtype]

    def _close_segment(self) -> None:
        seg, self._open = self._open, None
        assert seg is not None
        info = SegmentInfo(seg.final.name, seg.start, seg.end, seg.count)
        counts = {name: seg.writer.counts[c.id] for name, c in seg.connections.items()}
        seg.writer.close_fast(
            metadata_yaml(
                storage=self.storage,
                segments=[info],
                topics=[
                    (t.name, t.msgtype, t.qos, self._msgdef(t.msgtype)[1], counts.get(t.name, 0))
                    for t in self.topics.values()
                    if t.name in seg.connections
                ],
                custom_data=self.custom_data,
            )
        )
        written = seg.tmpdir / f"{seg.tmpdir.name}{self.suffix}"
        os.replace(written, seg.final)
        shutil.rmtree(seg.tmpdir)
        self.segments.append(info)
        self._closed_counts = {name: self._closed_counts.get(name, 0) + n for name, n in counts.items()}
        self._write_metadata()

    def _write_metadata(self) -> None:
        text = metadata_yaml(
            storage=self.storage,
            segments=self.segments,
            topics=[
                (t.name, t.msgtype, t.qos, self._msgdef(t.msgtype)[1], self._closed_counts.get(t.name, 0))
                for t in self.topics.values()
            ],
            custom_data=self.custom_data,
        )
        tmp = self.path / ".metadata.yaml.tmp"
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, self.path / "metadata.yaml")


class _McapFileStorage(_McapWriter):
    """:class:`_McapWriter` on a file of the caller's name (rosbags' names it ``DIR/DIR.mcap``).

    The file's head is rosbags' (magic, Header record with profile ``ros2``); the rest is inherited.
    """

    def __init__(self, path: Path) -> None:  # rosbags' McapWriter.__init__ with the path as given
        self.path = path
        self.bio = path.open("xb")
        self.bio.write(b"\x89MCAP\x30\r\n")
        rec = BytesIO()
        write_string(rec, "ros2")
        write_string(rec, f"rosbags-{package_version('rosbags')}")
        write_record(self.bio, 0x01, rec)
        self.schemas = []
        self.channels = []
        self.chunks = []
        self.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        self.compression = ""
        self.compressor = bytes
        self.message_start_time = 2**63 - 1
        self.message_end_time = 0
        self.channel_stats = {}


class McapFileWriter:
    """One standalone MCAP file at ``path`` (rosbag2's profile and embedded metadata: Foxglove,
    ``ros2 bag info FILE`` and the ``mcap`` readers open it), with chunks closed and flushed at
    :data:`CHUNK_BYTES` or ``chunk_seconds`` of log time as a segment's: a killed writer leaves
    every closed chunk readable (without the index: Foxglove reads such a file by streaming it).

    ``write(topic, timestamp_ns, data)`` takes CDR bytes; :meth:`add_topic` first. ``close()`` writes
    the index and summary (idempotent).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_seconds: float | None = CHUNK_SECONDS,
        custom_data: dict[str, str] | None = None,
        store: Typestore | None = None,
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagExistsError(self.path, "file")
        self.store = store or typestore()
        self.custom_data = dict(custom_data or {})
        try:
            self.storage: _McapFileStorage | None = _McapFileStorage(self.path)
            self.storage.chunk_ns = None if chunk_seconds is None else round(chunk_seconds * 1e9)
            if self.custom_data:
                self.storage.write_custom_data(self.custom_data)
        except OSError as exc:
            raise BagWriterError(f"cannot write {self.path}: {exc}") from exc
        self.topics: dict[str, TopicRecord] = {}
        self.connections: dict[str, Connection] = {}
        self._types: set[str] = set()
        self._msgdefs: dict[str, tuple[str, str]] = {}
        self.start = 2**63 - 1
        self.end = 0

    def add_topic(self, name: str, msgtype: str, qos: tuple[Qos, ...] | list[Qos] = ()) -> None:
        """Register a topic (absolute name, ``pkg/msg/Name``); adding it again is a no-op."""
        if self.storage is None:
            raise BagWriterError(f"{self.path} is closed")
        if name in self.topics:
            return
        if msgtype not in self.store.types:
            raise BagWriterError(f"topic {name}: type {msgtype} is not in the ROS2_JAZZY typestore")
        rec = TopicRecord(name, msgtype, tuple(qos) or (make_qos(),))
        if msgtype not in self._msgdefs:
            self._msgdefs[msgtype] = (
                self.store.generate_msgdef(msgtype, ros_version=2)[0],
                self.store.hash_rihs01(msgtype),
            )
        msgdef, digest = self._msgdefs[msgtype]
        fmt = MessageDefinitionFormat.IDL if msgdef.startswith("=" * 80 + "\nIDL: ") else MessageDefinitionFormat.MSG
        conn = Connection(
            id=len(self.connections) + 1,
            topic=name,
            msgtype=msgtype,
            msgdef=MessageDefinition(fmt, msgdef),
            digest=digest,
            msgcount=0,
            ext=ConnectionExtRosbag2(serialization_format="cdr", offered_qos_profiles=list(rec.qos)),
            owner=self,
        )
        if msgtype not in self._types:
            self.storage.add_msgtype(conn)
            self._types.add(msgtype)
        self.storage.add_connection(conn, qos_yaml(list(rec.qos)))
        self.topics[name] = rec
        self.connections[name] = conn

    def write(self, topic: str, timestamp: int, data: bytes | memoryview) -> None:
        """One serialized message with log time ``timestamp`` [ns]; OSError on an I/O error."""
        if self.storage is None:
            raise BagWriterError(f"{self.path} is closed")
        self.storage.write(self.connections[topic], timestamp, data)
        self.topics[topic].count += 1
        if timestamp < self.start:
            self.start = timestamp
        if timestamp > self.end:
            self.end = timestamp

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics.values())

    def close(self) -> None:
        """Write the last chunk, the index, the summary and the embedded metadata (idempotent)."""
        storage, self.storage = self.storage, None
        if storage is None:
            return
        n = self.message_count
        info = SegmentInfo(self.path.name, self.start if n else 0, self.end if n else 0, n)
        storage.close(
            METADATA_VERSION,
            metadata_yaml(
                storage="mcap",
                segments=[info],
                topics=[(t.name, t.msgtype, t.qos, self._msgdefs[t.msgtype][1], t.count) for t in self.topics.values()],
                custom_data=self.custom_data,
            ),
        )
