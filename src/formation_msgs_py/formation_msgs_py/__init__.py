"""The shared contract of the formation packages.

Formation files (schema, loading, validation, agent and simulator views), SO(3) helpers,
performance functions, topic names, QoS profiles and message conversions. Only
:mod:`formation_msgs_py.qos` and :mod:`formation_msgs_py.conversions` import ROS.
"""

from formation_msgs_py.errors import FormationError, FormationSpecError

__all__ = ["FormationError", "FormationSpecError"]
