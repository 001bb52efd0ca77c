"""``formation-agent``: one agent process. ``--help`` is answered here, before rclpy is imported;
whether the controller runs compiled is :mod:`formation_agent.kernel_cache`'s choice.
"""

from __future__ import annotations

import os
import sys

USAGE = """usage: formation-agent --ros-args -p formation_file:=FILE -p agent_id:=ID [-p NAME:=VALUE ...]
       formation-agent --ros-args --params-file PARAMS.yaml [-p agent_id:=ID | -r __ns:=/agent_ID]

One agent of a formation: node /agent_<ID>/formation_agent; subscribes to /agent_<ID>/velocity and
the relative poses of its tree neighbours, publishes /agent_<ID>/wrench and /diagnostics.

parameters (ros2 param describe /agent_<ID>/formation_agent NAME):
  formation_file       formation file (YAML); only the agent's own view of it is used   read-only
  agent_id             the agent's id in the file                                      read-only
  measurement_qos      reliable (default) or best-effort, as the simulator's --measurement-qos  read-only
  intruder_policy      report (default) or refuse: a publisher other than the simulator on the
                       agent's measurements (or other than itself on its wrench) is logged; refuse
                       also ignores that topic's messages while it is there  read-only
  use_sim_time         default true (the simulator publishes /clock)
  pose_wait            wall s to wait for the neighbours' poses after the velocity (default 0.005);
                       a neighbour still missing then is out of range: zero wrench + ERROR     live
  faults_file          where to write the agent's fault counts when it stops (default: none)   read-only
  diagnostics_period   wall s between /diagnostics messages (default 0.5, minimum 0.1)         live
  delta, gamma         the controller's gains (default: the formation file's); checked like the
                       file (> 0); applied from the next step                                  live
Change a live one while it runs: formation-param set /agent_<ID>/formation_agent gamma 12 (the agent logs it).
A parameters file may hold every agent: a /** section for what they share and one
/agent_<ID>/formation_agent section per agent (docs/ros2.md, "Parameters").
environment: ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS: see docs/ros2.md
"""


def main(args: list[str] | None = None) -> int:
    """Entry point of ``formation-agent`` (``args``: the whole sys.argv form, ROS arguments included)."""
    if any(a in ("-h", "--help") for a in (sys.argv if args is None else args)[1:]):
        print(USAGE)
        return 0
    os.environ.setdefault("NUMBA_DISABLE_JIT", "1")
    from formation_agent.agent_node import main as node_main

    return node_main(args)
