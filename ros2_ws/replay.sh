#!/usr/bin/env bash
# Replay a bag with its recorded timing and /clock (installs the environment on first use).
#
#   ros2_ws/replay.sh BAG [--rate R] [--topics T …] [--loop] [--start S] [--end S]
#                     [--clock-hz HZ] [--wait any|all|none] [--wait-timeout S] [--wait-settle S]
#                     [--foxglove [HOST:]PORT] [--quiet]
#
# Waits for a subscriber, then until every subscription it sees has matched and none has appeared
# for --wait-settle S (2), so that a recorder started first (record.sh) records every message;
# shows progress once a second. Replaying a run's relative poses and velocities into an agent
# (agent.sh FILE ID) re-runs that agent live.
# Network: --network host (default: LOCALHOST unless ROS_AUTOMATIC_DISCOVERY_RANGE is set) or lan;
# --discovery server[:HOST:PORT]: a client of the discovery server at HOST:PORT (default 127.0.0.1:11811),
# e.g. one that sim.sh --discovery server started.
# All options: formation-replay --help; user guide: docs/bags.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in
  -h|--help)
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"
    # shellcheck source=lib/help.sh
    . "$ROOT/ros2_ws/lib/help.sh"
    formation_command_help formation-replay
    exit 0 ;;
esac
"$ROOT/ros2_ws/setup.sh"
# shellcheck source=lib/network.sh
. "$ROOT/ros2_ws/lib/network.sh"
formation_network_options replay "" "$@" || exit 2
exec "$ROOT/.venv/bin/formation-replay" "${REST[@]+"${REST[@]}"}"
