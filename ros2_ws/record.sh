#!/usr/bin/env bash
# Record a running formation into a ROS 2 bag (installs the environment on first use).
#
#   ros2_ws/record.sh --out DIR [--formation FILE] [--storage mcap|sqlite3] [--topics T …]
#                     [--segment-seconds S] [--max-bag-size BYTES] [--decimate TOPIC=N …] [--meta K=V …]
#
# Default: every topic of docs/topics.md (discovered on the graph, or all of FILE's with
# --formation, which also stores FILE in the bag for formation-analyze). Stop with Ctrl-C or
# SIGTERM: the bag is closed cleanly. One file unless --max-bag-size or --segment-seconds splits it;
# after a SIGKILL, formation-bag repair BAG salvages all but the open file's last ~1 MiB.
# Start it first, then sim.sh FILE --wait-recorder: the simulator waits for it and the bag starts at
# the first step; started later, it says which steps it missed. It is an observer: nothing waits
# for it while stepping (for a lockstep bag that cannot lose a message: sim.sh FILE --bag DIR).
# Started before replay.sh BAG, it records every replayed message (the replay waits for it).
# A run whose command line overrides the file's mode, rate or duration: add --meta mode=M
# control_rate=HZ duration=S, so that the bag says what was run (formation-analyze uses it).
# Log times are simulation time in lockstep.
# Network: --network host (default: LOCALHOST unless ROS_AUTOMATIC_DISCOVERY_RANGE is set) or lan;
# --secure KEYS [--hosts FILE] joins a secure run with the key 'recorder' (needs --formation FILE:
# the ports follow its agents; docs/security.md); --discovery server[:HOST:PORT] joins a run whose
# simulator started a discovery server there (as a super client: it sees the whole graph).
# All options: formation-record --help; user guide: docs/bags.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in
  -h|--help)
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"
    # shellcheck source=lib/help.sh
    . "$ROOT/ros2_ws/lib/help.sh"
    formation_command_help formation-record
    exit 0 ;;
esac
"$ROOT/ros2_ws/setup.sh"
# shellcheck source=lib/network.sh
. "$ROOT/ros2_ws/lib/network.sh"
formation=""; prev=""
for a in "$@"; do [ "$prev" = "--formation" ] && formation="$a"; prev="$a"; done
formation_network_options recorder "$formation" "$@" || exit 2
exec "$ROOT/.venv/bin/formation-record" "${REST[@]+"${REST[@]}"}"
