#!/usr/bin/env bash
# Install (on first use) and run the whole test suite: ruff (lint and format), mypy, then pytest.
#
#   ros2_ws/test.sh                 # everything (CI runs exactly this)
#   ros2_ws/test.sh -k controller   # extra arguments go to pytest
#
# ROS tests pick their own ROS_DOMAIN_ID and keep discovery on this host
# (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST); see tests/README.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
case "${1:-}" in -h|--help) awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"; exit 0 ;; esac
"$ROOT/ros2_ws/setup.sh"
cd "$ROOT"
echo "test: ruff check" >&2
.venv/bin/ruff check src tests
echo "test: ruff format --check" >&2
.venv/bin/ruff format --check src tests
echo "test: mypy (mypy.ini)" >&2
.venv/bin/mypy
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
exec .venv/bin/python -m pytest tests "$@"
