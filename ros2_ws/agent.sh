#!/usr/bin/env bash
# Start one agent process alone (multi-host deployments: one agent per machine or container).
#
#   ros2_ws/agent.sh FILE AGENT_ID [--network host|lan] [--secure KEYS [--hosts FILE] [--port-base N]]
#                    [--discovery simple|server[:HOST:PORT]] [--ros-args -p NAME:=VALUE ...]
#
# Runs formation-agent with formation_file:=FILE and agent_id:=AGENT_ID (node
# /agent_<ID>/formation_agent, use_sim_time:=true): it subscribes to /agent_<ID>/velocity and its
# tree neighbours' relative poses, publishes /agent_<ID>/wrench and /diagnostics, and runs until
# Ctrl-C or SIGTERM. Parameters (-p NAME:=VALUE or --params-file FILE; formation-agent --help):
# pose_wait, diagnostics_period, delta, gamma (live), measurement_qos, intruder_policy, faults_file.
# Network: discovery stays on this machine unless asked: --network host (default; LOCALHOST unless
# ROS_AUTOMATIC_DISCOVERY_RANGE is set) or --network lan (SUBNET, the ROS default: multicast on
# the LAN); ROS_STATIC_PEERS adds unicast hosts. --secure KEYS: TLS over TCP only, with the key
# agent_<ID> of formation-keys init KEYS (--hosts: where each process runs). docs/security.md.
# --discovery server[:HOST:PORT]: a client of the discovery server that sim.sh started on HOST:PORT
# (default 127.0.0.1:11811): no multicast. Environment: ROS_DOMAIN_ID (default 0). See docs/ros2.md.
# Exit status: 0 stopped by a signal, 2 invalid file, agent id, option or parameter.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in -h|--help) awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"; exit 0 ;; esac
if [ $# -lt 2 ]; then echo "agent.sh: usage: agent.sh FILE AGENT_ID [options] [--ros-args ...] (see --help)" >&2; exit 2; fi
FILE="$1"; ID="$2"; shift 2
[ -f "$FILE" ] || { echo "agent.sh: formation file '$FILE' does not exist" >&2; exit 2; }
FILE="$(cd "$(dirname "$FILE")" && pwd)/$(basename "$FILE")"
"$ROOT/ros2_ws/setup.sh"
# shellcheck source=lib/network.sh
. "$ROOT/ros2_ws/lib/network.sh"
formation_network_options "agent_$ID" "$FILE" "$@" || exit 2
extra=("${REST[@]+"${REST[@]}"}")
if [ ${#extra[@]} -gt 0 ] && [ "${extra[0]}" = "--ros-args" ]; then extra=("${extra[@]:1}"); fi
exec "$ROOT/.venv/bin/formation-agent" --ros-args -p "formation_file:=$FILE" -p "agent_id:='$ID'" \
  -p use_sim_time:=true "${extra[@]+"${extra[@]}"}"
