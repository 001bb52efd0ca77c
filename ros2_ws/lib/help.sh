# --help of the scripts that install on first use (sourced, not run): help never installs.
#
# formation_command_help NAME: NAME --help from .venv when the project is installed there (NAME's
# own parser: every option); else how to see it. ROOT must be set.
formation_command_help() {
  local exe="$ROOT/.venv/bin/$1"
  if [ -x "$exe" ]; then
    "$exe" --help
  else
    echo "The options of $1 are listed here once the project is installed: ros2_ws/setup.sh (one to"
    echo "three minutes the first time; any script of ros2_ws/ runs it), then this --help again."
  fi
}
