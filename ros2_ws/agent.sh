#!/usr/bin/env bash
# Start one agent process alone (multi-host deployments: one agent per machine or container).
#
#   ros2_ws/agent.sh FILE AGENT_ID [--ros-args -p NAME:=VALUE ...]
#
# Runs formation-agent with formation_file:=FILE and agent_id:=AGENT_ID (node
# /agent_<ID>/formation_agent, use_sim_time:=true): it subscribes to /agent_<ID>/velocity and its
# tree neighbours' relative poses, publishes /agent_<ID>/wrench and /diagnostics, and runs until
# Ctrl-C or SIGTERM. Parameters (-p NAME:=VALUE or --params-file FILE; formation-agent --help):
# pose_wait, diagnostics_period, delta, gamma (live), measurement_qos, executor (read-only).
# Environment: ROS_DOMAIN_ID (default 0), ROS_AUTOMATIC_DISCOVERY_RANGE (unset here: the ROS default,
# SUBNET, to reach other hosts; set LOCALHOST to stay on this machine), ROS_STATIC_PEERS (hosts to
# reach by unicast, ';'-separated). See docs/ros2.md.
# Exit status: 0 stopped by a signal, 2 invalid file, agent id or parameter.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in -h|--help) sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;; esac
if [ $# -lt 2 ]; then echo "agent.sh: usage: agent.sh FILE AGENT_ID [--ros-args ...] (see --help)" >&2; exit 2; fi
FILE="$1"; ID="$2"; shift 2
[ -f "$FILE" ] || { echo "agent.sh: formation file '$FILE' does not exist" >&2; exit 2; }
FILE="$(cd "$(dirname "$FILE")" && pwd)/$(basename "$FILE")"
"$ROOT/ros2_ws/setup.sh"
extra=("$@")
if [ ${#extra[@]} -gt 0 ] && [ "${extra[0]}" = "--ros-args" ]; then extra=("${extra[@]:1}"); fi
exec "$ROOT/.venv/bin/formation-agent" --ros-args -p "formation_file:=$FILE" -p "agent_id:='$ID'" \
  -p use_sim_time:=true "${extra[@]+"${extra[@]}"}"
