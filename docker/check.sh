#!/usr/bin/env bash
# Offline build check of docker/Dockerfile: no Docker engine and no container registry needed.
#
#   docker/check.sh [--base-image IMAGE] [--rebuild-base] [--duration S] [--keep] [--install-tools]
#                   [--ca-bundle FILE]
#
# 1. base: a Debian bookworm root file system with python3.11 made by mmdebstrap from Debian's
#    packages and imported into podman (cached in WORKDIR; --rebuild-base remakes it), unless
#    --base-image names an image podman already has (e.g. python:3.11-slim-bookworm).
# 2. build: podman build --isolation=chroot of docker/Dockerfile over that base, from a clean
#    context (the files git tracks or would track; no .venv), i.e. the install by ros2_ws/setup.sh.
# 3. smoke: podman cannot run containers here, so a container is created and mounted, and its
#    entrypoint runs under chroot as the image's user, with the image's environment, in private
#    mount, PID and network namespaces (loopback only): formation-check, formation-headless on
#    the paper preset shortened to --duration S (default 0.05 s), an rclpy publish/subscribe
#    round trip, and, once ros2_ws/sim.sh and agent.sh exist, the same scenario as one simulator
#    process and one process per agent, whose trajectory must equal the headless one.
# Options: --keep keeps the image (localhost/formation:check); --install-tools apt-installs podman
# and mmdebstrap if missing; --ca-bundle FILE (default $PIP_CERT, '' for none) is copied into the
# made base image with PIP_CERT set, for machines whose HTTPS goes through a TLS-inspecting proxy.
# WORKDIR is $FORMATION_DOCKER_WORKDIR (default /var/tmp/formation-docker).
# Needs root. Prints the time of every step; exit status 0 when every step passed.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
WORKDIR="${FORMATION_DOCKER_WORKDIR:-/var/tmp/formation-docker}"
BASE_IMAGE=""
REBUILD_BASE=0
DURATION=0.05
KEEP=0
INSTALL_TOOLS=0
CA_BUNDLE="${PIP_CERT:-}"
IMAGE=localhost/formation:check
BASE_TAG=localhost/formation-base:bookworm-py311

usage() { sed -n '2,25p' "$0" | sed 's/^# \{0,1\}//'; }
die() { echo "check: error: $*" >&2; exit 2; }
while [ $# -gt 0 ]; do
  case "$1" in
    -h|--help) usage; exit 0 ;;
    --base-image) [ $# -ge 2 ] || die "--base-image needs an IMAGE"; BASE_IMAGE="$2"; shift ;;
    --rebuild-base) REBUILD_BASE=1 ;;
    --duration) [ $# -ge 2 ] || die "--duration needs seconds"; DURATION="$2"; shift ;;
    --keep) KEEP=1 ;;
    --install-tools) INSTALL_TOOLS=1 ;;
    --ca-bundle) [ $# -ge 2 ] || die "--ca-bundle needs a FILE (or '')"; CA_BUNDLE="$2"; shift ;;
    *) die "unknown option '$1' (see --help)" ;;
  esac
  shift
done

if [ -n "$CA_BUNDLE" ]; then
  [ -f "$CA_BUNDLE" ] || die "CA bundle '$CA_BUNDLE' does not exist (--ca-bundle, or PIP_CERT)"
  BASE_TAG="$BASE_TAG-localca"
fi
[ "$(id -u)" = 0 ] || die "needs root (podman build --isolation=chroot, mmdebstrap, chroot)"
missing=()
for tool in podman mmdebstrap unshare chroot ip git; do
  command -v "$tool" >/dev/null 2>&1 || missing+=("$tool")
done
if [ "${#missing[@]}" -gt 0 ]; then
  if [ "$INSTALL_TOOLS" = 1 ]; then
    echo "check: installing podman mmdebstrap (apt-get)" >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q podman mmdebstrap iproute2 >/dev/null
  else
    die "missing ${missing[*]}: apt-get install podman mmdebstrap iproute2 (or pass --install-tools)"
  fi
fi

T0=$(date +%s.%N)
STEP_T=$T0
step_done() {  # step_done NAME: print the time since the previous step
  local now
  now=$(date +%s.%N)
  awk -v a="$now" -v b="$STEP_T" -v n="$1" 'BEGIN { printf "check: %-44s %7.1f s\n", n, a - b }'
  STEP_T=$now
}

mkdir -p "$WORKDIR"
CTX="$(mktemp -d "$WORKDIR/context.XXXXXX")"
CTR=""
cleanup() {
  [ -n "$CTR" ] && { podman umount "$CTR" >/dev/null 2>&1 || true; podman rm -f "$CTR" >/dev/null 2>&1 || true; }
  [ "$KEEP" = 1 ] || podman rmi -f "$IMAGE" >/dev/null 2>&1 || true
  rm -rf "$CTX"
}
trap cleanup EXIT
trap 'exit 130' INT TERM   # so that the EXIT trap also runs when interrupted

# --- 1. base image ------------------------------------------------------------------------------
if [ -z "$BASE_IMAGE" ]; then
  BASE_IMAGE="$BASE_TAG"
  TARBALL="$WORKDIR/bookworm-py311.tar"
  TARBALL_PART="$WORKDIR/bookworm-py311.part.tar"  # mmdebstrap picks the format by the extension
  if [ "$REBUILD_BASE" = 1 ] || [ ! -s "$TARBALL" ]; then
    echo "check: mmdebstrap bookworm (python3.11, venv) -> $TARBALL" >&2
    mmdebstrap --quiet --variant=minbase --include=python3.11,python3.11-venv,ca-certificates \
      bookworm "$TARBALL_PART" >"$WORKDIR/mmdebstrap.log" 2>&1 \
      || { tail -n 20 "$WORKDIR/mmdebstrap.log" >&2; die "mmdebstrap failed (log: $WORKDIR/mmdebstrap.log)"; }
    mv "$TARBALL_PART" "$TARBALL"
    podman rmi -f "$BASE_TAG" >/dev/null 2>&1 || true
    step_done "base: mmdebstrap bookworm"
  fi
  if ! podman image exists "$BASE_TAG"; then
    if [ -z "$CA_BUNDLE" ]; then
      podman import --quiet --change 'CMD ["/bin/bash"]' "$TARBALL" "$BASE_TAG" >/dev/null
    else
      # This machine's TLS trust (pip's PIP_CERT) goes into the base image, not the Dockerfile.
      podman import --quiet --change 'CMD ["/bin/bash"]' "$TARBALL" "$BASE_TAG-raw" >/dev/null
      cp "$CA_BUNDLE" "$CTX/ca-bundle.crt"
      printf '%s\n' "FROM $BASE_TAG-raw" "COPY ca-bundle.crt /etc/ssl/certs/ca-certificates.crt" \
        "ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt" >"$CTX/Containerfile.base"
      podman build --quiet --isolation=chroot -f "$CTX/Containerfile.base" -t "$BASE_TAG" "$CTX" >/dev/null
      podman rmi "$BASE_TAG-raw" >/dev/null 2>&1 || true
      rm -f "$CTX/ca-bundle.crt" "$CTX/Containerfile.base"
    fi
    step_done "base: podman import"
  else
    step_done "base: cached $BASE_TAG"
  fi
else
  podman image exists "$BASE_IMAGE" || die "podman has no image '$BASE_IMAGE' (podman images)"
fi

# --- 2. build -----------------------------------------------------------------------------------
# Clean context: what git tracks plus new files it does not ignore (the working tree's versions).
git -C "$ROOT" ls-files -z --cached --others --exclude-standard \
  | (cd "$ROOT" && xargs -0 -r sh -c 'for f; do [ -e "$f" ] && printf "%s\0" "$f"; done' _) \
  | tar -C "$ROOT" --null -T - -cf - | tar -C "$CTX" -xf -
BUILD_LOG="$WORKDIR/build.log"
if ! podman build --isolation=chroot --network=host \
      --build-arg "BASE_IMAGE=$BASE_IMAGE" -f "$CTX/docker/Dockerfile" -t "$IMAGE" "$CTX" >"$BUILD_LOG" 2>&1; then
  tail -n 30 "$BUILD_LOG" >&2
  die "podman build failed (log: $BUILD_LOG)"
fi
SIZE=$(podman image inspect -f '{{.Size}}' "$IMAGE")
step_done "build: podman build (image $((SIZE / 1000000)) MB)"

# --- 3. smoke test in a chroot of the image -----------------------------------------------------
CTR=$(podman create "$IMAGE")
MNT=$(podman mount "$CTR")
mapfile -t ENVS < <(podman image inspect -f '{{range .Config.Env}}{{println .}}{{end}}' "$IMAGE" | sed '/^$/d')
USERSPEC=$(podman image inspect -f '{{.Config.User}}' "$IMAGE")
ENTRY=$(podman image inspect -f '{{range .Config.Entrypoint}}{{.}} {{end}}' "$IMAGE")
DOMAIN=$((200 + $$ % 30))

in_image() {  # in_image CMD...: the entrypoint with CMD, as the image would run it, offline
  unshare --mount --net --pid --fork --kill-child bash -euo pipefail -c '
    mnt="$1"; userspec="$2"; shift 2
    ip link set lo up
    mount -t proc proc "$mnt/proc"
    mount --bind /dev "$mnt/dev"
    mount -t tmpfs -o mode=1777 tmpfs "$mnt/dev/shm"
    mount -t tmpfs -o mode=1777 tmpfs "$mnt/tmp"
    exec chroot --userspec="$userspec" "$mnt" "$@"
  ' _ "$MNT" "${USERSPEC:-0:0}" /usr/bin/env -i "${ENVS[@]}" HOME=/home/formation \
    "ROS_DOMAIN_ID=$DOMAIN" ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $ENTRY "$@"
}

in_image --help >/dev/null
step_done "smoke: entrypoint --help"
in_image formation-check config/paper_5agents.yaml >/dev/null
step_done "smoke: formation-check paper preset"
in_image formation-headless config/paper_5agents.yaml --duration "$DURATION" --no-plots --quiet \
  --out /opt/formation/out/smoke-headless >/dev/null
python3 - "$MNT/opt/formation/out/smoke-headless/summary.json" <<'EOF'
import json, sys
s = json.load(open(sys.argv[1]))
print(f"check: headless summary: funnels_held={s.get('funnels_held')} duration={s.get('duration')}")
EOF
step_done "smoke: formation-headless ${DURATION} s"
in_image python -c '
import sys, rclpy
from rclpy.node import Node
from std_msgs.msg import String
rclpy.init()
a, b = Node("smoke_talker"), Node("smoke_listener")
got = []
b.create_subscription(String, "smoke", lambda m: got.append(m.data), 10)
pub = a.create_publisher(String, "smoke", 10)
from rclpy.executors import SingleThreadedExecutor
ex = SingleThreadedExecutor(); ex.add_node(a); ex.add_node(b)
for _ in range(200):
    pub.publish(String(data="ping"))
    ex.spin_once(timeout_sec=0.05)
    if got: break
rclpy.try_shutdown()
print("check: rclpy round trip:", "ok" if got else "NO MESSAGE")
sys.exit(0 if got else 1)
'
step_done "smoke: rclpy publish/subscribe"

if [ -x "$MNT/opt/formation/ros2_ws/sim.sh" ] && [ -x "$MNT/opt/formation/ros2_ws/agent.sh" ]; then
  in_image python /opt/formation/docker/smoke_ros.py --duration "$DURATION" \
    --out /opt/formation/out/smoke-ros --headless /opt/formation/out/smoke-headless
  step_done "smoke: sim.sh + 5 x agent.sh ${DURATION} s"
else
  echo "check: ros2_ws/sim.sh or agent.sh not in the image yet: multi-process scenario skipped" >&2
fi
STEP_T=$T0
step_done "total"
echo "check: OK"
