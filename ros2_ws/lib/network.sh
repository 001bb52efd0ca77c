# Network options shared by sim.sh, agent.sh and record.sh (sourced, not run).
#
#   --network host   discovery on this machine only (default): ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
#                    unless the environment sets it (docker/compose.yaml and the image set SUBNET),
#                    carried out as UDP on 127.0.0.1 only (formation_msgs_py/fastdds_loopback.xml);
#                    every non-secure process uses UDP only, never Fast DDS's shared memory
#   --network lan    the ROS default: multicast discovery on the local network (SUBNET)
#   --secure KEYS    TLS over TCP only, with this process's key from KEYS (formation-keys init KEYS):
#                    no UDP, no shared memory; every process of the run needs --secure (docs/security.md)
#   --hosts FILE     with --secure: YAML mapping process name -> host (default: all on 127.0.0.1)
#   --host NAME=ADDR with --secure: one process's host (repeat; wins over --hosts)
#   --port-base N    with --secure: first port, the same on every host (default 7700)
#   --discovery simple|server[:HOST:PORT]
#                    simple (default): the DDS announcements --network chooses; server: this process is
#                    a client of the Fast DDS discovery server at HOST:PORT (default 127.0.0.1:11811):
#                    unicast only, no multicast; sim.sh starts that server (docs/ros2.md). Not with --secure
#
# formation_network_options NAME FILE ARGS...: sets REST (the other arguments) and exports the
# environment; NAME is the process's key name (simulator, agent_<id>, recorder, replay). It sets
# DISCOVERY to the --discovery value (the recorder is a super client: it sees the whole graph).
formation_network_options() {
  local name="$1" file="$2"; shift 2
  local network="" keys="" hosts="" port_base="" duration="" host_args=()
  REST=()
  DISCOVERY=simple
  while [ $# -gt 0 ]; do
    case "$1" in
      --network) network="${2:?--network needs host or lan}"; shift 2 ;;
      --network=*) network="${1#*=}"; shift ;;
      --secure) keys="${2:?--secure needs the key directory}"; shift 2 ;;
      --secure=*) keys="${1#*=}"; shift ;;
      --hosts) hosts="${2:?--hosts needs a file}"; shift 2 ;;
      --port-base) port_base="${2:?--port-base needs a number}"; shift 2 ;;
      --host) host_args+=(--host "${2:?--host needs NAME=ADDR}"); shift 2 ;;
      --discovery) DISCOVERY="${2:?--discovery needs simple or server[:HOST:PORT]}"; shift 2 ;;
      --discovery=*) DISCOVERY="${1#*=}"; shift ;;
      --duration) duration="${2:-}"; REST+=("$1" "${2:-}"); shift; [ $# -gt 0 ] && shift ;;  # the certificates' check
      --duration=*) duration="${1#*=}"; REST+=("$1"); shift ;;
      --ros-args) REST+=("$@"); break ;;
      *) REST+=("$1"); shift ;;
    esac
  done
  case "$network" in
    "") export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}" ;;
    host) export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ;;
    lan) export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET ;;
    *) echo "--network: expected host or lan, got '$network'" >&2; return 2 ;;
  esac
  if [ "$DISCOVERY" != simple ]; then
    if [ -n "$keys" ]; then
      echo "--discovery server cannot be combined with --secure: the secure transport is TLS over TCP only," \
        "the discovery server listens on UDP (docs/security.md)" >&2
      return 2
    fi
    local super=() ds_env
    [ "$name" = recorder ] && super=(--super-client)
    ds_env="$("$ROOT/.venv/bin/python" -m formation_sim.launch.discovery_server env "$DISCOVERY" "${super[@]+"${super[@]}"}")" \
      || return 2
    eval "$ds_env"
  fi
  if [ "$DISCOVERY" = simple ] && [ -z "$keys" ]; then
    # UDP only, never Fast DDS's shared memory: LOCALHOST becomes the loopback profile
    # (formation_sim.launch.dds_env.transport_environment; docs/ros2.md, "Transports")
    local transports
    transports="$("$ROOT/.venv/bin/python" -m formation_sim.launch.dds_env transports)" || return 2
    eval "$transports"
  fi
  if [ -n "$keys" ] && [ -z "$file" ]; then
    echo "--secure needs the formation file (the ports follow its agents)" >&2; return 2
  fi
  if [ -n "$keys" ]; then
    local args=(profile "$keys" "$name" --formation "$file" --out "${FORMATION_PROFILE_DIR:-$keys/profiles}")
    [ -n "$hosts" ] && args+=(--hosts "$hosts")
    [ -n "$port_base" ] && args+=(--port-base "$port_base")
    [ -n "$duration" ] && args+=(--duration "$duration")
    args+=("${host_args[@]+"${host_args[@]}"}")
    local lines
    lines="$("$ROOT/.venv/bin/formation-keys" "${args[@]}")" || return 2
    eval "$lines"
  elif [ -n "$hosts$port_base${host_args[*]+x}" ]; then
    echo "--hosts, --host and --port-base need --secure KEYS" >&2; return 2
  fi
}
