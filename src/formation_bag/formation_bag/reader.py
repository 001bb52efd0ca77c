"""Read rosbag2 bags with rosbags, also bags left by a killed recorder.

:class:`Bag` opens a bag directory (or a single ``.mcap``/``.db3`` file). With an intact
``metadata.yaml`` it uses rosbags' :class:`~rosbags.rosbag2.Reader` on the directory. When the
metadata is missing or lists files that are gone (a recorder killed with SIGKILL, a copy
interrupted), it *tolerates*: every segment file that rosbags can open is read on its own,
in segment order, and the files it cannot open (the segment that was open when the recorder
died) are listed in :attr:`Bag.lost`. :func:`repair` writes the rebuilt ``metadata.yaml``.
"""

from __future__ import annotations

import os
import re
import shutil
import sqlite3
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import yaml
from rosbags.interfaces import Connection, ConnectionExtRosbag2
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError

from formation_bag.contract import KEY_REPAIRED
from formation_bag.metadata import STORAGES, SegmentInfo, metadata_yaml
from formation_bag.writer import typestore
from formation_core.errors import BagExistsError, BagFormatError, BagNotFoundError

SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}
_SEG_RE = re.compile(r"_(\d+)$")


class BagMessage(NamedTuple):
    topic: str
    msgtype: str
    log_time: int  # ns
    data: bytes | memoryview


@dataclass
class TopicInfo:
    name: str
    msgtype: str
    count: int
    qos: list[Any] = field(default_factory=list)
    digest: str = ""


def _segment_key(path: Path) -> tuple[int, str]:
    m = _SEG_RE.search(path.stem)
    return (int(m.group(1)) if m else -1, path.name)


def segment_files(path: Path) -> list[Path]:
    """Storage files directly in a bag directory, in segment order (``NAME_0``, ``NAME_1``, …)."""
    return sorted((p for p in path.iterdir() if p.suffix in SUFFIXES and p.is_file()), key=_segment_key)


def partial_files(path: Path) -> list[Path]:
    """Files of segments that were open when a recorder died (hidden ``.NAME_k/`` directories)."""
    out: list[Path] = []
    for d in sorted(path.iterdir()):
        if d.is_dir() and d.name.startswith("."):
            out.extend(p for p in d.iterdir() if p.suffix in SUFFIXES)
    return out


class Bag:
    """A bag opened for reading. Use as a context manager."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagNotFoundError(f"bag {self.path} does not exist")
        self.readers: list[Reader] = []
        self.segments: list[Path] = []
        self.lost: list[str] = []
        self.recovered = False
        self.metadata: dict[str, Any] | None = None
        self.custom_data: dict[str, str] = {}
        self.storage = ""
        self._open()

    # -- opening --------------------------------------------------------------------------------

    def _open(self) -> None:
        if self.path.is_file():
            if self.path.suffix not in SUFFIXES:
                raise BagFormatError(f"{self.path}: not a bag directory, .mcap or .db3 file")
            self.storage = SUFFIXES[self.path.suffix]
            self._open_files([self.path])
            if not self.readers:
                raise BagFormatError(f"{self.path}: not readable ({'; '.join(self.lost)})")
            self.custom_data = embedded_custom_data(self.path)
            return
        meta_path = self.path / "metadata.yaml"
        if meta_path.exists():
            try:
                doc = yaml.safe_load(meta_path.read_text(encoding="utf-8"))
                self.metadata = doc["rosbag2_bagfile_information"]
                self.custom_data = dict(self.metadata.get("custom_data") or {})
                self.storage = str(self.metadata.get("storage_identifier", ""))
            except (yaml.YAMLError, KeyError, TypeError) as exc:
                raise BagFormatError(f"{meta_path}: not a rosbag2 metadata file ({exc})") from None
            try:
                reader = Reader(self.path)
                reader.open()
            except (ReaderError, FileNotFoundError, KeyError, ValueError) as exc:
                self.lost.append(f"{meta_path}: {exc}")
            else:
                self.readers = [reader]
                self.segments = [self.path / Path(p).name for p in self.metadata.get("relative_file_paths", [])]
                self.lost.extend(f"{p}: segment open when the recorder stopped" for p in partial_files(self.path))
                return
        # recovery: read every segment file that opens
        self.recovered = True
        files = segment_files(self.path)
        if not files and not partial_files(self.path):
            raise BagNotFoundError(f"bag {self.path} holds no .mcap or .db3 file and no metadata.yaml")
        self._open_files(files)
        self.lost.extend(f"{p}: segment open when the recorder stopped" for p in partial_files(self.path))
        if not self.readers:
            raise BagFormatError(f"bag {self.path}: no readable segment ({'; '.join(self.lost)})")
        if not self.storage:
            self.storage = SUFFIXES[self.segments[0].suffix]
        if not self.custom_data:
            self.custom_data = embedded_custom_data(self.segments[0])

    def _open_files(self, files: Iterable[Path]) -> None:
        for f in files:
            try:
                r = Reader(f)
                r.open()
            except (ReaderError, OSError, KeyError, ValueError, IndexError, sqlite3.DatabaseError) as exc:
                self.lost.append(f"{f}: {exc}")
                continue
            if f.suffix == ".db3" and r.message_count == 0 and not r.connections:
                r.close()
                self.lost.append(f"{f}: empty database (uncommitted when the recorder stopped)")
                continue
            self.readers.append(r)
            self.segments.append(f)

    def close(self) -> None:
        for r in self.readers:
            r.close()
        self.readers = []

    def __enter__(self) -> Bag:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- contents -------------------------------------------------------------------------------

    @property
    def topics(self) -> dict[str, TopicInfo]:
        """Every topic: type, message count (over the readable segments), offered QoS."""
        out: dict[str, TopicInfo] = {}
        for r in self.readers:
            for c in r.connections:
                info = out.get(c.topic)
                qos = c.ext.offered_qos_profiles if isinstance(c.ext, ConnectionExtRosbag2) else []
                if info is None:
                    out[c.topic] = TopicInfo(c.topic, c.msgtype, c.msgcount, list(qos), c.digest)
                else:
                    info.count += c.msgcount
        return out

    @property
    def message_count(self) -> int:
        return sum(r.message_count for r in self.readers)

    @property
    def start_time(self) -> int:
        return min((r.start_time for r in self.readers if r.message_count), default=0)

    @property
    def end_time(self) -> int:
        """Log time of the last message (ns)."""
        return max((r.end_time - 1 for r in self.readers if r.message_count), default=0)

    def messages(
        self, topics: Iterable[str] | None = None, *, start: int | None = None, stop: int | None = None
    ) -> Iterator[BagMessage]:
        """Messages in log-time order; ``topics`` selects, ``start``/``stop`` bound the log time (ns)."""
        wanted = None if topics is None else set(topics)
        for r in self.readers:
            conns: list[Connection] = [c for c in r.connections if wanted is None or c.topic in wanted]
            if not conns:
                continue
            for conn, ts, data in r.messages(connections=conns, start=start, stop=stop):
                yield BagMessage(conn.topic, conn.msgtype, ts, data)


def embedded_custom_data(path: Path) -> dict[str, str]:
    """custom_data from the metadata a storage file carries itself (rosbag2 writes it there too)."""
    try:
        if path.suffix == ".db3":
            con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
            try:
                row = con.execute("SELECT metadata FROM metadata ORDER BY id DESC LIMIT 1").fetchone()
            finally:
                con.close()
            text = row[0] if row else None
        else:
            from mcap.reader import make_reader

            text = None
            with path.open("rb") as f:
                for rec in make_reader(f).iter_metadata():
                    if rec.name == "rosbag2":
                        text = rec.metadata.get("serialized_metadata")
        if not text:
            return {}
        doc = yaml.safe_load(text)
        info = doc.get("rosbag2_bagfile_information", doc) if isinstance(doc, dict) else {}
        return dict(info.get("custom_data") or {})
    except Exception:
        return {}


def recovered_note(name: str, count: int, first_ns: int, last_ns: int) -> str:
    """``custom_data.repaired`` of a salvaged file: what was recovered (log time from its first message)."""
    return f"{name}: {count} messages up to {(last_ns - first_ns) / 1e9:.4f} s of log time recovered, the rest lost"


def salvage(partial: Path, final: Path, name: str | None = None) -> int:
    """Write the messages of the closed chunks of ``partial`` (an MCAP file whose writer was killed:
    no summary, a torn last chunk) as the complete MCAP file ``final``; returns how many.

    The writer (formation_bag.writer) puts each chunk in the file when it closes (at ~1 MiB
    or 1 s of log time), so a killed writer's file holds all but its last chunk, and its custom_data
    (the run's settings) at its start: the complete file carries them again. Nothing is written if
    no message can be read. The complete file's custom_data also says what was recovered
    (:data:`KEY_REPAIRED`, :func:`recovered_note`, naming the file ``name``, default ``final``'s).
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2.metadata import parse_qos

    from formation_bag.writer import CUSTOM_DATA_RECORD, SegmentedBagWriter

    tmp = final.parent / f".salvage_{final.stem}"
    schemas: dict[int, str] = {}
    topics: dict[int, tuple[str, str, list[Any]]] = {}
    writer: SegmentedBagWriter | None = None
    custom_data: dict[str, str] = {}
    count, first, last = 0, 2**63 - 1, 0
    with partial.open("rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False, emit_chunks=False).records:
                if isinstance(rec, Metadata) and rec.name == CUSTOM_DATA_RECORD:
                    custom_data = dict(rec.metadata)  # the run's settings, written when the file opened
                elif isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    qos = parse_qos(rec.metadata.get("offered_qos_profiles", "") or [])
                    topics[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""), qos)
                elif isinstance(rec, Message) and rec.channel_id in topics:
                    topic, msgtype, qos = topics[rec.channel_id]
                    if writer is None:
                        writer = SegmentedBagWriter(
                            tmp, segment_seconds=None, segment_bytes=None, custom_data=custom_data
                        )
                    writer.add_topic(topic, msgtype, qos)
                    writer.write(topic, rec.log_time, rec.data)
                    count += 1
                    first, last = min(first, rec.log_time), max(last, rec.log_time)
        except (McapError, EOFError, ValueError, struct.error):
            pass  # the torn end of the file
    if writer is None:
        return 0
    writer.custom_data[KEY_REPAIRED] = recovered_note(name or final.name, count, first, last)
    writer.close()
    written = writer.path / f"{writer.path.name}_0.mcap"
    os.replace(written, final)
    shutil.rmtree(tmp)
    return count


def _is_complete_mcap(path: Path) -> bool:
    """True if the MCAP file ends with its closing magic (a writer that was not killed wrote it)."""
    with path.open("rb") as f:
        if f.seek(0, os.SEEK_END) < 16:
            return False
        f.seek(-8, os.SEEK_END)
        return f.read(8) == b"\x89MCAP0\r\n"


def repair_file(path: str | Path) -> str:
    """Make the MCAP file a killed writer left (``OUT/view.mcap``, or a bag's file) complete in place:
    its closed chunks, with its custom_data and ``custom_data.repaired`` saying what was recovered.
    Returns that note; BagFormatError if the file is complete already or holds no readable message."""
    path = Path(path)
    if not path.is_file() or path.suffix != ".mcap":
        raise BagFormatError(f"{path}: not an MCAP file")
    if _is_complete_mcap(path):
        raise BagFormatError(f"{path}: complete already (it has its summary), nothing to repair")
    tmp = path.parent / f".repaired_{path.name}"
    if not salvage(path, tmp, path.name):
        raise BagFormatError(f"{path}: no readable message (nothing was flushed before the writer stopped)")
    note = embedded_custom_data(tmp)[KEY_REPAIRED]
    os.replace(tmp, path)
    return note


def repair(path: str | Path, *, force: bool = False) -> tuple[Path, list[str]]:
    """Write ``metadata.yaml`` for the readable segments of a bag; returns (path, lost files).

    The file a killed writer left open (MCAP) is salvaged first: its closed chunks become a complete
    file in its place. Refuses to replace an existing metadata.yaml unless ``force``.
    """
    path = Path(path)
    meta = path / "metadata.yaml"
    if meta.exists() and not force:
        raise BagExistsError(meta, "metadata file")
    if meta.exists():
        meta.unlink()
    salvaged: list[str] = []
    repaired: list[str] = []  # custom_data.repaired: what the bag's readers should know of it
    for part in partial_files(path):
        final = path / f"{part.name.lstrip('.')}"
        if part.suffix != ".mcap" or final.exists():
            continue
        n = salvage(part, final)
        if n:
            shutil.rmtree(part.parent)
            salvaged.append(
                f"{part}: open when the writer stopped: {n} messages recovered into {final.name}, its tail lost"
            )
            repaired.append(embedded_custom_data(final)[KEY_REPAIRED])
    bag = Bag(path)
    try:
        infos: list[SegmentInfo] = []
        topic_rows: dict[str, list[Any]] = {}
        for f, r in zip(bag.segments, bag.readers):
            n = r.message_count
            infos.append(SegmentInfo(f.name, r.start_time if n else 0, r.end_time - 1 if n else 0, n))
            for c in r.connections:
                qos = tuple(c.ext.offered_qos_profiles) if isinstance(c.ext, ConnectionExtRosbag2) else ()
                digest = c.digest
                if not str(digest).startswith("RIHS01_") and c.msgtype in typestore().types:
                    digest = typestore().hash_rihs01(c.msgtype)  # MCAP channels do not carry the hash
                row = topic_rows.setdefault(c.topic, [c.topic, c.msgtype, qos, digest, 0])
                row[4] += c.msgcount
        storage = bag.storage if bag.storage in STORAGES else SUFFIXES[bag.segments[0].suffix]
        text = metadata_yaml(
            storage=storage,
            segments=infos,
            topics=[(topic, msgtype, qos, digest, count) for topic, msgtype, qos, digest, count in topic_rows.values()],
            custom_data={**bag.custom_data, **({KEY_REPAIRED: "; ".join(repaired)} if repaired else {})},
        )
        lost = salvaged + list(bag.lost)
    finally:
        bag.close()
    meta.write_text(text, encoding="utf-8")
    return meta, lost
