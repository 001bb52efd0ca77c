"""Writing standard ROS 2 bags without ROS (rosbags), shared by the simulator and formation_bag.

:mod:`writer` (the segmented rosbag2 writer and the ROS 2 Jazzy typestore), :mod:`metadata`
(metadata.yaml, version 9), :mod:`errors`. The simulator writes a lockstep run's bag itself with
it (formation_sim.node.run_bag); formation_bag records, reads and analyses bags with it. This module
imports nothing heavy: the command-line parsers read the names below.
"""

#: storage plugins, by the name the command lines take (metadata.STORAGES maps them to rosbags')
STORAGE_NAMES = ("mcap", "sqlite3")
#: custom_data keys of a run's bag: the formation file's text and name (analysis needs no other input)
KEY_FORMATION_YAML = "formation_yaml"
KEY_FORMATION_FILE = "formation_file"
#: custom_data key that ``formation-bag repair`` sets when it salvaged a file a killed writer left open
#: (what was recovered); formation-analyze reports the run INCOMPLETE with it
KEY_REPAIRED = "repaired"
#: custom_data key the simulator sets when its run stopped before its end: JSON {"exit_status", "reason"}
#: (a process died, a wrong answer, an interruption); formation-analyze reports the same reason and status
KEY_RUN_STOPPED = "run_stopped"
#: custom_data key the simulator sets in a run with a link model: summary.json's ``links`` as JSON (its
#: counts and ages are the simulator's, of every control step); formation-analyze reports them
KEY_LINKS = "links"
#: message types whose CDR starts with a stamp (std_msgs/Header or builtin_interfaces/Time): their log
#: time in simulation time is that stamp; other types (markers, funnel values, /tf) take the latest one
STAMPED_TYPES = frozenset(
    f"{pkg}/msg/{name}"
    for pkg, name in (
        ("geometry_msgs", "TwistStamped"),
        ("geometry_msgs", "WrenchStamped"),
        ("geometry_msgs", "PoseStamped"),
        ("geometry_msgs", "PoseArray"),
        ("rosgraph_msgs", "Clock"),
        ("diagnostic_msgs", "DiagnosticArray"),
    )
)


def ros_type_name(msg_class: type) -> str:
    """``pkg/msg/Name`` of a generated ROS 2 message class (``geometry_msgs.msg.TwistStamped``)."""
    return f"{msg_class.__module__.split('.')[0]}/msg/{msg_class.__name__}"
