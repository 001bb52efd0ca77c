#!/usr/bin/env bash
# Create (once) and update the project's virtual environment at <repo root>/.venv.
#
#   ros2_ws/setup.sh            # idempotent; fast (< 2 s) when nothing changed
#   ros2_ws/setup.sh --force    # reinstall requirements and the src/ packages
#
# It also compiles the closed-loop kernels into numba's cache whenever a file under src/ changed
# (~15-25 s once), so that a first run does not compile them.
#
# Other scripts call "$(dirname "$0")/setup.sh" and then use .venv/bin/python or .venv/bin/NAME.
# Environment: PYTHON=/path/to/python3.11 picks the interpreter (default: python3.11 on PATH).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
REQ="$ROOT/ros2_ws/requirements.txt"
LOG="$VENV/setup-pip.log"
FORCE=0
INSTALLED=0

case "${1:-}" in
  -h|--help)
    awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"
    exit 0 ;;
  --force) FORCE=1 ;;
  "") ;;
  *) echo "setup: unknown option '$1' (see --help)" >&2; exit 2 ;;
esac

say() { echo "setup: $*" >&2; }
die() { echo "setup: error: $*" >&2; exit 1; }

is_py311() { "$1" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' >/dev/null 2>&1; }

hash_files() {  # sha256 over the names and contents of the given files (missing ones are skipped)
  local f
  for f in "$@"; do
    [ -f "$f" ] || continue
    printf '%s\n' "${f#"$ROOT"/}"
    sha256sum <"$f"
  done | sha256sum | cut -d' ' -f1
}

run_pip() {  # one line per package pip collects or installs; the full output goes to $LOG
  if ! PIP_PROGRESS_BAR=off "$VENV/bin/python" -m pip --disable-pip-version-check --no-input "$@" 2>&1 \
    | tee -a "$LOG" \
    | awk '/^(Collecting|Obtaining) / { sub(/ \(from .*/, ""); print "setup:   " $0; fflush() }
           /^Successfully installed / { print "setup:   installed " NF - 2 " packages"; fflush() }' >&2; then
    echo "setup: pip failed; last lines of $LOG:" >&2
    grep -v "is ignored: it is neither a file nor a directory" "$LOG" | tail -n 30 >&2
    exit 1
  fi
}

# --- 1. the virtual environment ------------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ] || ! is_py311 "$VENV/bin/python"; then
  PY="${PYTHON:-}"
  if [ -z "$PY" ]; then
    PY="$(command -v python3.11 || true)"
  fi
  [ -n "$PY" ] || die "python3.11 not found on PATH (install Python 3.11, or set PYTHON=/path/to/python3.11)"
  is_py311 "$PY" || die "'$PY' is not a working Python 3.11 (set PYTHON=/path/to/python3.11)"
  [ -e "$VENV" ] && { say "removing broken $VENV"; rm -rf "$VENV"; }
  say "creating virtual environment $VENV with $PY"
  "$PY" -m venv "$VENV" || die "could not create $VENV"
fi

# One setup at a time (tests may start several scripts at once).
exec 9>"$VENV/.setup.lock"
flock 9

# --- 2. pinned requirements ----------------------------------------------------------------------
[ -f "$REQ" ] || die "missing $REQ"
REQ_STAMP="$VENV/.stamp-requirements"
req_hash="$(hash_files "$REQ")"
if [ "$FORCE" = 1 ] || [ "$(cat "$REQ_STAMP" 2>/dev/null || true)" != "$req_hash" ]; then
  say "installing requirements (ros2_ws/requirements.txt; the first time takes one to four minutes)…"
  : >"$LOG"
  run_pip install -r "$REQ"
  INSTALLED=1
  echo "$req_hash" >"$REQ_STAMP"
  rm -f "$VENV/.stamp-src"   # packages are re-checked against the new requirements
fi

# --- 3. the project's packages under src/ (editable) ---------------------------------------------
SRC_STAMP="$VENV/.stamp-src"
pkgs=()
meta=()
if [ -d "$ROOT/src" ]; then
  while IFS= read -r setup_py; do
    d="$(dirname "$setup_py")"
    pkgs+=("$d")
    meta+=("$d/setup.py" "$d/setup.cfg" "$d/package.xml" "$d/pyproject.toml")
  done < <(find "$ROOT/src" -mindepth 2 -maxdepth 2 -name setup.py -not -path '*/.*' | LC_ALL=C sort)
fi
src_hash="$(hash_files "${meta[@]+"${meta[@]}"}")"
if [ "${#pkgs[@]}" -gt 0 ] && { [ "$FORCE" = 1 ] || [ "$(cat "$SRC_STAMP" 2>/dev/null || true)" != "$src_hash" ]; }; then
  names=()
  edit_args=()
  for d in "${pkgs[@]}"; do names+=("$(basename "$d")"); edit_args+=(-e "$d"); done
  say "installing src packages (editable): ${names[*]}…"
  : >"$LOG"
  run_pip install --no-build-isolation --use-pep517 "${edit_args[@]}"
  INSTALLED=1
  echo "$src_hash" >"$SRC_STAMP"
fi

# --- 4. numba's cache of the compiled core, and Python's bytecode of src/ ---------------------------
# A first run would compile the closed loop (~15 s on two cores); here it is done once per change of
# the sources. Every kernel's cache entry is keyed on all the sources compiled into it
# (formation_core/numba_kernels.py), so an entry of older sources is never loaded; they are deleted
# here only so that they do not pile up. A short headless run of the paper
# scenario compiles the headless loop and, as its parts, the kernels the simulator and the agents
# load (team_step, agent_step, rkmk4_step, relative_poses, measured_velocity_into). The editable
# sources are byte-compiled too: under PYTHONDONTWRITEBYTECODE every process would otherwise compile
# them again (~0.2 s of each start); a stale .pyc is ignored (Python checks the source's mtime).
# Without src/ (the container image's dependency layer copies ros2_ws/ only) there is nothing to compile.
NUMBA_STAMP="$VENV/.stamp-numba"
numba_hash=""
if [ "${#pkgs[@]}" -gt 0 ]; then
  numba_hash="$(find "$ROOT/src" -name '*.py' -not -path '*/.*' | LC_ALL=C sort | { mapfile -t f; hash_files "${f[@]}"; })"
fi
if [ -n "$numba_hash" ] && { [ "$FORCE" = 1 ] || [ "$(cat "$NUMBA_STAMP" 2>/dev/null || true)" != "$numba_hash" ]; }; then
  say "compiling the closed-loop kernels into numba's cache (once per change of src/, ~15-25 s)…"
  find "$ROOT/src" -path '*/__pycache__/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete
  "$VENV/bin/python" -m compileall -q "$ROOT/src" >/dev/null || say "warning: byte-compiling src/ failed"
  warm_out="$(mktemp -d)"
  if "$VENV/bin/formation-headless" "$ROOT/config/paper_5agents.yaml" --duration 0.001 --no-plots --quiet \
      --force --out "$warm_out" >"$warm_out.log" 2>&1; then
    echo "$numba_hash" >"$NUMBA_STAMP"
    INSTALLED=1
  else
    say "warning: compiling the kernels failed (the first run will compile them); last lines:"
    tail -n 5 "$warm_out.log" >&2
  fi
  rm -rf "$warm_out" "$warm_out.log"
fi

[ "$INSTALLED" = 1 ] && say "done in ${SECONDS} s"
exit 0
