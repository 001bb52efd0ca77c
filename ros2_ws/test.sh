#!/usr/bin/env bash
# Install (on first use) and run the whole test suite: ruff (lint and format), mypy, then pytest.
#
#   ros2_ws/test.sh                 # everything (CI runs exactly this)
#   ros2_ws/test.sh -k controller   # extra arguments go to pytest (both runs below)
#
# After the whole suite, the tests marked `numeric` (controller, judge, witness, golden runs) run
# again under a second numeric configuration that stands for another CPU (tests/numeric_config.py:
# numpy without its SIMD dispatch, numba for a generic CPU). Without arguments, the mutation check
# follows (tests/mutants.py: each mutant must fail a test of its folder). About 20 minutes on two cores.
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
echo "test: pytest" >&2
status=0
.venv/bin/python -m pytest tests "$@" || status=$?
mapfile -t SECOND < <(.venv/bin/python tests/numeric_config.py)
echo "test: pytest -m numeric again under ${SECOND[*]}" >&2
second=0
env "${SECOND[@]}" .venv/bin/python -m pytest tests -m numeric -p no:cacheprovider "$@" || second=$?
# pytest's 5: no test selected (e.g. -k names only non-numeric tests)
if [ "$second" -ne 0 ] && [ "$second" -ne 5 ] && [ "$status" -eq 0 ]; then status=$second; fi
if [ "$#" -eq 0 ]; then  # the whole suite: the mutation check too (tests/mutants.py, seconds)
    echo "test: mutation check (tests/mutants.py)" >&2
    .venv/bin/python tests/mutants.py || { [ "$status" -ne 0 ] || status=1; }
fi
exit "$status"
