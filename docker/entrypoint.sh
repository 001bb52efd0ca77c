#!/usr/bin/env bash
# Container entrypoint: run one of the project's commands.
#
#   entrypoint.sh COMMAND [ARGS…]
#
# COMMAND is a ros2_ws script (run.sh, sim.sh FILE, agent.sh FILE AGENT_ID, test.sh, …, with or
# without ".sh"), a console script of the project's virtual environment (formation-headless,
# formation-check, formation-compose, …) or any other program on PATH. Relative FILE arguments
# are relative to the repository (/opt/formation in the image), so config/paper_5agents.yaml works as is.
# Environment: ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_STATIC_PEERS (docs/docker.md).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"   # /opt/formation in the image
usage() { sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; }
if [ $# -eq 0 ] || [ "$1" = "-h" ] || [ "$1" = "--help" ]; then
  usage
  echo
  echo "ros2_ws scripts:"
  find "$ROOT/ros2_ws" -maxdepth 1 -name '*.sh' -printf '  %f\n' | LC_ALL=C sort
  echo "console scripts:"
  find "$ROOT/.venv/bin" -maxdepth 1 -name 'formation-*' -printf '  %f\n' | LC_ALL=C sort
  exit 0
fi
cmd="$1"
shift
cd "$ROOT"
if [ -x "$ROOT/ros2_ws/$cmd" ] && [ "${cmd%.sh}" != "$cmd" ]; then
  exec "$ROOT/ros2_ws/$cmd" "$@"
elif [ -x "$ROOT/ros2_ws/$cmd.sh" ]; then
  exec "$ROOT/ros2_ws/$cmd.sh" "$@"
elif [ -x "$ROOT/.venv/bin/$cmd" ]; then
  exec "$ROOT/.venv/bin/$cmd" "$@"
fi
command -v "$cmd" >/dev/null 2>&1 || { echo "entrypoint: unknown command '$cmd' (see --help)" >&2; exit 127; }
exec "$cmd" "$@"
