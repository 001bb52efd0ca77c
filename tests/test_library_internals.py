"""The libraries' internals the code reaches past their public API, checked against the installed
versions (pinned in ros2_ws/requirements.txt): an upgrade that moves one fails here, naming it and the
module that uses it, not somewhere in a run. Each library's internals live in one module, its adapter:
formation_ros/rclpy_internals.py (checked here), formation_bag/writer.py (rosbags', here) and
formation_core/numba_kernels.py (numba's, in tests/formation_core/test_numba_kernels.py: they need a
fresh compiled process)."""

from __future__ import annotations

import importlib
import inspect
from collections import defaultdict
from importlib.metadata import version
from io import BytesIO
from pathlib import Path

import pytest


def _resolve(owner: str) -> object:
    """``a.b.C.d`` -> the object, importing the longest module prefix."""
    parts = owner.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(owner)


def test_rclpy_internals_are_where_the_adapter_reaches_them() -> None:
    """Every (owner, attribute) formation_ros.rclpy_internals uses exists in the installed rclpy."""
    from formation_ros import rclpy_internals

    missing = []
    for owner, attribute in rclpy_internals.INTERNALS:
        try:
            present = hasattr(_resolve(owner), attribute)
        except (ImportError, AttributeError):
            present = False
        if not present:
            missing.append(f"{owner}.{attribute}")
    assert not missing, (
        f"rclpy {version('ros-rclpy')} (written for 7.1.6) lacks {missing}: formation_ros/rclpy_internals.py uses them"
    )
    assert issubclass(rclpy_internals.RCLError, Exception)


def test_rosbags_mcap_writer_sets_what_our_file_storage_sets(tmp_path: Path) -> None:
    """formation_bag.writer's one-file MCAP storage repeats rosbags' McapWriter.__init__ with its
    own path: both set the same attributes (a new one in rosbags would be missing from ours), and the
    names the writer imports and overrides are rosbags' still."""
    from rosbags.rosbag2.enums import CompressionMode
    from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk, write_record, write_string

    from formation_bag.writer import _McapFileStorage, _McapWriter

    (tmp_path / "theirs").mkdir()
    theirs = McapWriter(tmp_path / "theirs", CompressionMode.NONE)
    ours = _McapFileStorage(tmp_path / "ours.mcap")
    try:
        assert set(vars(ours)) == set(vars(theirs)), (
            f"rosbags {version('rosbags')} (written for 0.11.9): McapWriter sets {sorted(set(vars(theirs)))}, "
            f"formation_bag/writer.py's _McapFileStorage {sorted(set(vars(ours)))}"
        )
    finally:
        ours.bio.close()
        theirs.bio.close()
    assert list(inspect.signature(PendingChunk).parameters) == ["message_start_time", "message_end_time", "bio", "msgs"]
    assert isinstance(PendingChunk(0, 0, BytesIO(), defaultdict(list)).msgs, defaultdict)
    assert callable(write_record) and callable(write_string)
    overridden = [name for name in ("close_chunk", "write") if not hasattr(McapWriter, name)]
    assert not overridden, f"rosbags' McapWriter has no {overridden}: _McapWriter overrides them"
    assert issubclass(_McapWriter, McapWriter)


@pytest.mark.parametrize("attribute", ["storage", "connections", "added_types", "counts", "version"])
def test_rosbags_writer_has_what_the_segment_writer_reads(tmp_path: Path, attribute: str) -> None:
    """_SegmentFileWriter adds topics and closes files through rosbags' Writer's own state."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    writer = Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        assert hasattr(writer, attribute), (
            f"rosbags {version('rosbags')}: Writer has no {attribute!r} (formation_bag/writer.py reads it)"
        )
        assert StoragePlugin.MCAP in Writer.STORAGE_PLUGINS
    finally:
        writer.close()
