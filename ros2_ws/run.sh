#!/usr/bin/env bash
# Install (on first use) and run a formation through ROS 2: the simulator node and one process per
# agent, recorded into OUT/bag by the simulator; the default is the paper's scenario (config/paper_5agents.yaml).
#
#   ros2_ws/run.sh [FILE] [--mode lockstep|realtime] [--out DIR] [--duration S] [--control-rate HZ]
#                  [--no-record] [--animate] [--netns auto|on|off] [--headless] [options below]
#
# Validates FILE first (exit 2, nothing started, if invalid); starts every process in its own process
# group with a log in OUT/logs/; shows progress (sim time, real-time factor, worst funnel margin);
# stops everything on completion, Ctrl-C, SIGTERM or the death of a process; prints the summary and
# writes OUT (default out/<formation>-ros2-<mode>-<time>): summary.json, trajectory.npz, errors.png,
# orientation_errors.png, inputs.png, velocity_errors.png, clearance.png, foxglove_layout.json, logs/, bag/ and
# view.mcap (unless --no-record; view.mcap is what to open in Foxglove with foxglove_layout.json) and,
# with --animate, animation.gif (docs/outputs.md).
# Discovery stays on this host: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless set; a free
# ROS_DOMAIN_ID is picked unless set; runs above 30 processes use a private network namespace, unless
# --discovery server: every process a client of a Fast DDS discovery server the launcher starts.
# --headless runs the same formation in one process without ROS: formation-headless FILE with the
# other options (see formation-headless --help).
# Verdict PASS / FAIL / INCOMPLETE (with the reason) in the last lines and OUT/summary.json. Exit status:
# 0 PASS, 1 FAIL (a funnel was violated), 2 invalid input (nothing started), 3 a process died or an
# agent stopped answering, 4 incomplete (I/O error, disk full, lag budget, data missing), 5 wrong
# answer (lockstep: an agent answered a step, again when re-sent, with a wrench the simulator's witness
# refuses), 130 interrupted. --params-file FILE hands one ROS 2 parameters file to every agent (their
# gains). Details: docs/ros2.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in
  -h|--help)
    awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"
    echo
    # shellcheck source=lib/help.sh
    . "$ROOT/ros2_ws/lib/help.sh"
    echo "Options (formation-launch):"
    formation_command_help formation-launch | sed -n '/^options:/,$p;/^The options/,$p' | sed '/^options:/d'
    exit 0 ;;
esac
"$ROOT/ros2_ws/setup.sh"
FILE="$ROOT/config/paper_5agents.yaml"
if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then FILE="$1"; shift; fi
args=()
headless=0
for a in "$@"; do
  if [ "$a" = "--headless" ]; then headless=1; else args+=("$a"); fi
done
if [ "$headless" = 1 ]; then
  exec "$ROOT/.venv/bin/formation-headless" "$FILE" "${args[@]+"${args[@]}"}"
fi
exec "$ROOT/.venv/bin/formation-launch" "$FILE" "${args[@]+"${args[@]}"}"
