"""The shared, ROS-free core of the formation packages.

Formation files (schema, loading, validation, agent and simulator views), run options, outcome
(verdicts, exit codes), faults, SO(3) helpers, performance functions, the judge (one funnel rule),
topic names, the wire codec and the bag writer. The few helpers that import rclpy (QoS profiles,
message conversions, parameters, graph watch, stopping) are in :mod:`formation_msgs_py.ros`.
"""

from formation_msgs_py.errors import FormationError, FormationSpecError

__all__ = ["FormationError", "FormationSpecError"]
