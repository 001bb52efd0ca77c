"""metadata.yaml of a rosbag2 bag (version 9, as Jazzy writes it), without ROS: shared by the
writer and formation_bag's reader (which rebuilds it for a bag left without one).

Emitted with PyYAML's libyaml dumper: rosbags' own (ruamel.yaml) takes ~30 ms per topic, which
would stall a recorder at every segment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import yaml
from rosbags.interfaces import Qos
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2.metadata import dump_qos_v9

from formation_bag.contract import STORAGE_NAMES

#: storage name -> (rosbags plugin, file suffix)
STORAGES = dict(zip(STORAGE_NAMES, ((StoragePlugin.MCAP, ".mcap"), (StoragePlugin.SQLITE3, ".db3")), strict=True))
METADATA_VERSION: Final = 9  # a literal: rosbags takes version 8 or 9
ROS_DISTRO = "jazzy"
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


@dataclass
class SegmentInfo:
    """One closed storage file of a bag: its name, first and last log time [ns], message count."""

    path: str
    start: int
    end: int
    count: int


def _dump(node: Any) -> str:
    return yaml.dump(node, Dumper=_DUMPER, sort_keys=False, default_flow_style=False, allow_unicode=True, width=1 << 30)


def qos_yaml(qos: list[Qos] | tuple[Qos, ...]) -> str:
    """Offered QoS profiles as rosbag2 stores them per connection (version 9 YAML list)."""
    return _dump(dump_qos_v9(list(qos))).rstrip("\n")


def metadata_yaml(
    *,
    storage: str,
    segments: list[SegmentInfo],
    topics: list[tuple[str, str, tuple[Qos, ...], str, int]],
    custom_data: dict[str, str] | None,
) -> str:
    """metadata.yaml of a multi-file bag, version 9, with the keys and layout Jazzy writes."""
    if segments:
        start = min(s.start for s in segments)
        end = max(s.end for s in segments)
    else:
        start, end = 0, 0
    info: dict[str, Any] = {
        "version": METADATA_VERSION,
        "storage_identifier": storage,
        "duration": {"nanoseconds": max(0, end - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": sum(s.count for s in segments),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": name,
                    "type": msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": dump_qos_v9(list(qos)),
                    "type_description_hash": digest,
                },
                "message_count": count,
            }
            for name, msgtype, qos, digest, count in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [s.path for s in segments],
        "files": [
            {
                "path": s.path,
                "starting_time": {"nanoseconds_since_epoch": s.start},
                "duration": {"nanoseconds": max(0, s.end - s.start)},
                "message_count": s.count,
            }
            for s in segments
        ],
        "custom_data": dict(custom_data) if custom_data else None,
        "ros_distro": ROS_DISTRO,
    }
    return _dump({"rosbag2_bagfile_information": info})
