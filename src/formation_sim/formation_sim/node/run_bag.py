"""A run's bag, written by the simulator itself (no ROS import).

The simulator is the run's recorder (docs/bags.md): every message it publishes is written as the
CDR bytes it sent, and every wrench and /diagnostics message it receives as the bytes it received
(accepted or refused). Log time: in lockstep simulation time (the message's stamp), in realtime
the wall clock (system time) when the simulator sent or received it, i.e. the order in which
wrenches reached the simulator between its ticks. No second copy of any message crosses DDS and
nothing needs acknowledging; a message cannot be lost between publication and bag. The bag is what ``formation-record
--formation FILE`` leaves (one file unless ``--max-bag-size`` splits it, metadata.yaml version 9,
the formation file and the run's settings in custom_data, ``recorder_counts`` and the wall time
from its first to its last message, ``wall_time``), so every bag tool reads both alike.

A write or close that fails (disk full, I/O error) stops the writing: :attr:`RunBag.failed` says
why and the simulator ends the run INCOMPLETE; the messages it could not write are counted. The
writer closes and flushes a chunk at least every second of log time, so a killed simulator leaves
all but the last second of the run for ``formation-bag repair`` (docs/bags.md).

``view``: beside the bag, one small MCAP file (``OUT/view.mcap``) of what a viewer shows, written
as the run goes with the same bytes and log times: every message of the display topics (markers,
funnels, /tf) and /diagnostics, and /clock and the ground truth decimated to ``view_rate`` (the
display rate). It costs a step only its own writes (a dictionary look-up per bag message, a write
per display instant); its chunks are flushed every :data:`VIEW_CHUNK_SECONDS` of log time, so a
crash keeps all but its last half second (``formation-bag repair OUT/view.mcap`` completes it).
An I/O error on it stops only it (:attr:`RunBag.view_failed`): the bag is the run's record.
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from formation_bag.contract import KEY_LINKS, KEY_RUN_STOPPED, STAMPED_TYPES
from formation_bag.writer import McapFileWriter, SegmentedBagWriter
from formation_core.errors import BagError, BagExistsError
from formation_msgs_py.codec import stamp_of
from formation_sim.core.summary import LinkReport

#: the view file's name in OUT
VIEW_FILE = "view.mcap"
#: log time [s] after which the view file's chunk is closed and flushed (it is small: a chunk of
#: 1 MiB would take seconds to fill; a crash loses at most this much of it)
VIEW_CHUNK_SECONDS = 0.5
#: message types of the view file written whole (they come at the display rate or slower)
VIEW_ALL_TYPES = frozenset(
    (
        "visualization_msgs/msg/MarkerArray",
        "std_msgs/msg/Float64MultiArray",
        "tf2_msgs/msg/TFMessage",
        "diagnostic_msgs/msg/DiagnosticArray",
    )
)
#: message types of the view file decimated to the display rate (/clock, ground truth)
VIEW_DECIMATED_TYPES = frozenset(("rosgraph_msgs/msg/Clock", "geometry_msgs/msg/PoseArray"))


class RunBag:
    """The bag at ``path`` (must not exist); topics are added before their first message.

    One file, or files of about ``max_bytes`` each (``--max-bag-size``, as ``ros2 bag record -b``).
    ``view``: the view file to write beside it (must not exist), ``view_rate`` its rate [Hz of log
    time] for /clock and the ground truth.
    """

    def __init__(
        self,
        path: Path,
        custom_data: dict[str, str],
        *,
        wall_log_time: bool = False,
        max_bytes: int | None = None,
        view: Path | None = None,
        view_rate: float = 30.0,
    ) -> None:
        self.path = path
        self.wall_log_time = wall_log_time
        if view is not None and view.exists():  # before the bag: refused, nothing is left behind
            raise BagExistsError(view, "view file")
        self.writer = SegmentedBagWriter(path, segment_seconds=None, segment_bytes=max_bytes, custom_data=custom_data)
        self.view = (
            None if view is None else McapFileWriter(view, chunk_seconds=VIEW_CHUNK_SECONDS, custom_data=custom_data)
        )
        self.view_rate = float(view_rate)
        #: per view topic, the log time [ns] its next message is due at (0: every message)
        self.view_due: dict[str, int] = {}
        self.view_failed: str | None = None
        #: monotonic wall clock [s] of the first and the latest message written: the run's wall time
        self.first_wall: float | None = None
        self.last_wall = 0.0
        #: log time [ns] of messages without a stamp of their own (markers, funnels, /tf) and of
        #: malformed ones: the latest stamp the simulator published (the step being published)
        self.now_ns = 0
        self.written: dict[str, int] = {}
        self.own: set[str] = set()  # topics the simulator publishes (the others it receives)
        self.types: dict[str, str] = {}
        self.stamped: dict[str, bool] = {}
        self.not_written: dict[str, int] = {}
        self.failed: str | None = None
        self._held: list[tuple[str, bytes]] | None = None  # publications to write when held() ends

    def add_topic(self, name: str, msgtype: str, qos: Any, *, published: bool) -> None:
        """Register a topic (absolute name, ``pkg/msg/Name``, rosbags Qos); ``published``: by the simulator."""
        self.writer.add_topic(name, msgtype, (qos,))
        self.written[name] = 0
        self.types[name] = msgtype
        self.stamped[name] = msgtype in STAMPED_TYPES
        if published:
            self.own.add(name)
        if self.view is not None and msgtype in VIEW_ALL_TYPES | VIEW_DECIMATED_TYPES:
            self.view.add_topic(name, msgtype, (qos,))
            self.view_due[name] = -1 if msgtype in VIEW_DECIMATED_TYPES else 0

    def write(self, topic: str, data: bytes | memoryview) -> None:
        """One message as sent or received; log time: the wall clock, or its stamp, else :attr:`now_ns`."""
        ns = self.now_ns
        if self.wall_log_time:
            ns = time.time_ns()
        elif self.stamped[topic]:
            try:
                ns = stamp_of(data)
            except struct.error:
                pass  # a malformed message (refused by the node) is kept as received
            else:
                if topic in self.own and ns > self.now_ns:
                    self.now_ns = ns  # not a received stamp: a bad wrench may claim any time
        self.last_wall = time.monotonic()
        if self.first_wall is None:
            self.first_wall = self.last_wall
        if self.failed is None:
            try:
                self.writer.write(topic, ns, data)
            except (OSError, BagError) as exc:
                self.failed = f"I/O error writing the bag {self.path}: {exc}"
            else:
                self.written[topic] += 1
                if topic in self.view_due:
                    self._write_view(topic, ns, data)
                return
        self.not_written[topic] = self.not_written.get(topic, 0) + 1

    def _write_view(self, topic: str, ns: int, data: bytes | memoryview) -> None:
        """The view file's copy of a bag message: display topics whole, the others on the display grid."""
        due = self.view_due[topic]
        if due:
            if ns < due or self.view_failed is not None:
                return
            # the next instant k/rate after ns (on the grid: no drift; the first message opens it)
            self.view_due[topic] = round((math.floor(ns * self.view_rate / 1e9 + 1e-6) + 1) * 1e9 / self.view_rate)
        if self.view_failed is None:
            try:
                self.view.write(topic, ns, data)  # type: ignore[union-attr]  # view_due is empty without it
            except (OSError, BagError) as exc:
                self.view_failed = f"I/O error writing the view file {self.view.path}: {exc}"  # type: ignore[union-attr]

    def write_sent(self, topic: str, data: bytes) -> None:
        """A publication of the simulator as its subscribers receive it: Fast DDS pads the CDR to a
        multiple of 4 bytes with zeros (what formation-record stores)."""
        if self._held is not None:
            self._held.append((topic, data))
            return
        self.write(topic, data + bytes(-len(data) % 4) if len(data) % 4 else data)

    @contextmanager
    def held(self) -> Iterator[None]:
        """Publications made inside are written, in order, when it ends: the simulator sends every
        agent its measurements of a step before it spends time on the bag (lockstep's critical path)."""
        self._held = []
        try:
            yield
        finally:
            held, self._held = self._held, None
            for topic, data in held:
                self.write_sent(topic, data)

    def zero_padded(self, topic: str, data: bytes) -> bytes:
        """The same message with its CDR alignment padding zeroed.

        rclpy's ``serialize_message`` leaves the padding uninitialised (the simulator publishes its
        display messages as objects), so a bag would differ from run to run and carry stray memory;
        rosbags re-serialises with zeros. ~2 ms for a MarkerArray of the paper's scene.
        """
        store, msgtype = self.writer.store, self.types[topic]
        return bytes(store.serialize_cdr(store.deserialize_cdr(data, msgtype), msgtype))

    def counts(self) -> dict[str, Any]:
        """What formation-record stores as ``recorder_counts``: per topic received, written and, for the
        simulator's own topics, published (every publication is written: lossless by construction)."""
        published = {t: (n + self.not_written.get(t, 0) if t in self.own else None) for t, n in self.written.items()}
        return {
            "received": {t: n + self.not_written.get(t, 0) for t, n in self.written.items()},
            "written": dict(self.written),
            "published_seen": published,
            "published_total": published,
            "decimate": {},
            "log_time": "receive" if self.wall_log_time else "sim",
            "missed_start": None,
            "writer": "simulator",
        }

    def close(self, stopped: tuple[int, str] | None = None, links: LinkReport | None = None) -> dict[str, Any]:
        """Close the bag with its counts in custom_data, why the run stopped before its end if it did
        (``stopped``: exit status, reason; :data:`formation_bag.contract.KEY_RUN_STOPPED`) and its
        link model's statistics (:data:`formation_bag.contract.KEY_LINKS`); the run summary's
        ``recorder`` entry."""
        counts = self.counts()
        self.writer.custom_data["recorder_counts"] = json.dumps(counts, sort_keys=True)
        if links is not None:
            self.writer.custom_data[KEY_LINKS] = json.dumps(links, sort_keys=True)
        if stopped is not None:
            self.writer.custom_data[KEY_RUN_STOPPED] = json.dumps({"exit_status": stopped[0], "reason": stopped[1]})
        if self.first_wall is not None:
            # formation-analyze reports the run's real-time factor from it (lockstep log times are sim time)
            self.writer.custom_data["wall_time"] = repr(self.last_wall - self.first_wall)
        try:
            self.writer.close()
        except (OSError, BagError) as exc:
            self.failed = self.failed or f"I/O error closing the bag {self.path}: {exc}"
        view: dict[str, Any] = {}
        if self.view is not None:
            self.view.custom_data.update(self.writer.custom_data)
            try:
                self.view.close()
            except (OSError, BagError) as exc:
                self.view_failed = self.view_failed or f"I/O error closing the view file {self.view.path}: {exc}"
            view["view"] = {"path": str(self.view.path), "written": self.view.message_count, "failed": self.view_failed}
        return {
            "received": sum(counts["received"].values()),
            "written": sum(self.written.values()),
            "not_recorded": sum(self.not_written.values()),
            "not_recorded_by_topic": dict(self.not_written),
            "missed_start": None,
            "writer": "simulator",
            **view,
        }
