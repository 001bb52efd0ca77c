#!/usr/bin/env bash
# Installs what the opt-in real-viewer test (tests/viewer/test_foxglove_viewer.py) needs:
#   - Foxglove Studio 1.48's prebuilt web app (npm package @foxglove/studio-base) and the React 17
#     builds it renders with, into a cache directory outside the repository;
#   - Debian's chromium (apt; run as root or with sudo);
#   - Playwright for Python into the project's .venv (its own browser download is not used: the
#     test launches Debian's chromium).
# Usage: tests/viewer/install.sh [--help]
# Environment: FORMATION_VIEWER_CACHE (default ~/.cache/formation-viewer): where the npm packages go.
set -euo pipefail

if [[ "${1:-}" == "--help" || "${1:-}" == "-h" ]]; then
    sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'
    exit 0
fi

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "${here}/../.." && pwd)"
cache="${FORMATION_VIEWER_CACHE:-${HOME}/.cache/formation-viewer}"

echo "npm packages into ${cache}"
mkdir -p "${cache}"
# The packages are fetched, not built: studio-base ships its web app prebuilt under assets/.
npm install --prefix "${cache}" --no-save --no-audit --no-fund --ignore-scripts \
    @foxglove/studio-base@1.48.0 react@17.0.2 react-dom@17.0.2

if ! command -v chromium > /dev/null; then
    echo "chromium (apt)"
    sudo_cmd=()
    if [[ "$(id -u)" != "0" ]]; then sudo_cmd=(sudo); fi
    "${sudo_cmd[@]}" apt-get update
    "${sudo_cmd[@]}" apt-get install -y chromium
fi

echo "playwright into ${repo}/.venv"
"${repo}/.venv/bin/python" -m pip install --quiet "playwright==1.65.2"
echo "done: FORMATION_VIEWER_CHECK=1 .venv/bin/python -m pytest tests/viewer -q"
