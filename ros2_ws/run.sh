#!/usr/bin/env bash
# Install (on first use) and run a formation; the default is the paper's scenario.
#
#   ros2_ws/run.sh [FILE] [--out DIR] [formation-headless options…]
#
# Writes OUT (default out/<formation>-headless): summary.json, trajectory.npz and the
# figures errors.png, orientation_errors.png, inputs.png; prints a pass/fail summary.
# Exit status: 0 every funnel held, 1 a funnel was violated, 2 invalid file or settings.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in -h|--help) sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;; esac
"$ROOT/ros2_ws/setup.sh"
FILE="$ROOT/config/paper_5agents.yaml"
if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then FILE="$1"; shift; fi
exec "$ROOT/.venv/bin/formation-headless" "$FILE" "$@"
