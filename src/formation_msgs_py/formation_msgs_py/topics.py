"""Topic and frame names of docs/topics.md, defined once (no ROS import).

Names are relative (no leading slash) so that a run's namespace applies; with the default
empty namespace they resolve to the absolute names of docs/topics.md.
"""

from __future__ import annotations

CLOCK = "/clock"  # ROS fixes /clock at the root, whatever the namespace
GROUND_TRUTH = "formation/ground_truth"
MARKERS = "formation/markers"  # visualization_msgs/MarkerArray for viewers; no agent subscribes
FUNNELS = "formation/funnels"  # std_msgs/Float64MultiArray: e, ψ and their bounds per edge, for plots
LINKS = "formation/links"  # std_msgs/Float64MultiArray: each link's held sample's age [s], with a link model
TF = "/tf"  # tf2_msgs/TFMessage world -> agent_<id>, where tf2_msgs is installed
DIAGNOSTICS = "/diagnostics"  # the ROS convention: one global diagnostics topic
WORLD_FRAME = "world"


def agent_frame(agent_id: str) -> str:
    """Body frame (and namespace) of an agent: ``agent_<id>``."""
    return f"agent_{agent_id}"


def relative_pose(observer: str, target: str) -> str:
    """Relative pose of ``target`` measured by ``observer`` (PoseStamped in observer's body frame)."""
    return f"agent_{observer}/relative_pose/agent_{target}"


def velocity(agent_id: str) -> str:
    """Noisy body twist of an agent (TwistStamped)."""
    return f"agent_{agent_id}/velocity"


def wrench(agent_id: str) -> str:
    """Body wrench an agent commands (WrenchStamped)."""
    return f"agent_{agent_id}/wrench"


#: Agent i's node is /agent_<i>/formation_agent: the multi-robot convention of one namespace per robot.
AGENT_NODE_NAME = "formation_agent"
SIM_NODE_NAME = "formation_sim"
#: formation-replay: publishes a bag's measurements and /clock in the simulator's stead
REPLAY_NODE_NAME = "formation_replay"


def agent_node(agent_id: str) -> str:
    """Fully qualified name of agent i's node: ``/agent_<i>/formation_agent``."""
    return f"/{agent_frame(agent_id)}/{AGENT_NODE_NAME}"
