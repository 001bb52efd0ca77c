#!/usr/bin/env bash
# Start the simulator process alone (multi-host deployments: the agents run elsewhere, agent.sh).
#
#   ros2_ws/sim.sh FILE [--network host|lan] [--secure KEYS [--hosts FILE] [--port-base N]]
#                  [--mode lockstep|realtime] [--out DIR] [--duration S] [--control-rate HZ] ...
#
# Runs formation-sim: waits for every agent of FILE to be discovered, then publishes /clock, relative
# poses, velocities and ground truth, collects the wrenches, checks the funnels at every control step
# and writes OUT (default out/<formation>-ros2-<mode>). All options: formation-sim --help (below).
# Network: --network host (default: this machine only), --network lan, --secure KEYS (key
# 'simulator'), --hosts, --port-base as for agent.sh (agent.sh --help, docs/security.md).
# --discovery server[:HOST:PORT]: starts a Fast DDS discovery server listening on HOST:PORT (default
# 127.0.0.1:11811; across machines an address the agents reach), runs the simulator as its client and
# stops the server when the simulator exits; every agent.sh/record.sh takes the same --discovery.
# Environment: ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS as for agent.sh.
# Exit status: 0 PASS, 1 FAIL, 2 invalid, 3 a process died or an agent stopped answering, 4 incomplete,
# 5 wrong answer (an agent's wrench refused by the witness, again when the step was re-sent), 130 interrupted.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in
  -h|--help)
    awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"
    echo
    # shellcheck source=lib/help.sh
    . "$ROOT/ros2_ws/lib/help.sh"
    formation_command_help formation-sim
    exit 0 ;;
esac
"$ROOT/ros2_ws/setup.sh"
# shellcheck source=lib/network.sh
. "$ROOT/ros2_ws/lib/network.sh"
formation_network_options simulator "${1:-}" "$@" || exit 2  # FILE comes first
if [ "$DISCOVERY" != simple ]; then
  exec "$ROOT/.venv/bin/python" -m formation_sim.launch.discovery_server serve "$DISCOVERY" -- \
    "$ROOT/.venv/bin/formation-sim" "${REST[@]+"${REST[@]}"}"
fi
exec "$ROOT/.venv/bin/formation-sim" "${REST[@]+"${REST[@]}"}"
