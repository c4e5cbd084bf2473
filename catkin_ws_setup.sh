#!/usr/bin/env bash
# One-command set-up of the MDR-SLAM catkin workspace (this repository's root).
#
#   ./catkin_ws_setup.sh            # install what is missing, (re)build, write ./setup.bash
#   source setup.bash               # venv + devel space: rosrun/roslaunch mdr_slam, `mdr` on PATH
#
# Idempotent: a second run skips apt when every package is present, skips pip when
# requirements.txt is unchanged, and catkin_make only rebuilds what changed.
#
# ROS 1 comes from an existing /opt/ros/noetic when there is one (Ubuntu 20.04), otherwise from
# Debian's own ROS packages (Debian 12: ros-core-dev, python3-rospy, ...).
#
# Environment: MDR_WITH_RVIZ=0 skips rviz (default 1: the demo takes an rviz screenshot);
#              MDR_SKIP_APT=1 never calls apt (for machines where you manage packages yourself).
set -eo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$ROOT"
log() { printf '[catkin_ws_setup] %s\n' "$*"; }

SUDO=""
if [ "$(id -u)" != 0 ]; then
  if command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
fi

# ---------------------------------------------------------------- 1. ROS 1 and system packages
if [ -f /opt/ros/noetic/setup.bash ]; then
  ROS_SETUP=/opt/ros/noetic/setup.bash
  log "using ROS Noetic from /opt/ros/noetic"
  APT_PKGS=(python3-venv python3-dev build-essential cmake xvfb
            ros-noetic-ros-base ros-noetic-cv-bridge ros-noetic-tf2-ros ros-noetic-tf2-geometry-msgs
            ros-noetic-message-filters ros-noetic-diagnostic-updater ros-noetic-std-srvs
            ros-noetic-nav-msgs ros-noetic-sensor-msgs ros-noetic-rosbag ros-noetic-tf2-tools)
  RVIZ_PKGS=(ros-noetic-rviz)
else
  ROS_SETUP=""
  log "using Debian's ROS 1 packages"
  APT_PKGS=(ros-core-dev catkin ros-message-generation ros-message-runtime
            python3-rospy python3-rosbag python3-message-filters python3-tf2-ros
            python3-tf2-geometry-msgs python3-sensor-msgs python3-geometry-msgs python3-nav-msgs
            python3-std-msgs python3-std-srvs python3-diagnostic-msgs python3-diagnostic-updater
            python3-cv-bridge ros-std-srvs ros-tf2-msgs tf2-tools rosbash
            python3-venv python3-dev build-essential cmake xvfb)
  RVIZ_PKGS=(rviz)
fi
if [ "${MDR_WITH_RVIZ:-1}" = 1 ]; then APT_PKGS+=("${RVIZ_PKGS[@]}"); fi

missing=()
for p in "${APT_PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  if [ "${MDR_SKIP_APT:-0}" = 1 ]; then
    log "MDR_SKIP_APT=1 but these packages are missing: ${missing[*]}"; exit 1
  fi
  log "installing ${#missing[@]} packages with apt: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  log "system packages: all present"
fi

# ---------------------------------------------------------------- 2. Python venv
VENV="$ROOT/.venv"
if [ ! -x "$VENV/bin/python" ]; then
  log "creating $VENV (system site packages visible, for rospy and friends)"
  /usr/bin/python3 -m venv --system-site-packages "$VENV"
fi
PY="$VENV/bin/python"
stamp="$VENV/.requirements.sha256"
want=$(cat requirements.txt constraints.txt | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  log "installing pinned Python dependencies (requirements.txt; numpy < 2)"
  "$PY" -m pip install -q --disable-pip-version-check -r requirements.txt -c constraints.txt 2>&1 \
    | grep -vE "^WARNING: Location '.*' is ignored" || true
  "$PY" -c "import numpy, sys; sys.exit(0 if int(numpy.__version__.split('.')[0]) < 2 else 1)" \
    || { log "numpy >= 2 ended up in the venv; Debian's cv_bridge would break"; exit 1; }
  echo "$want" > "$stamp"
else
  log "Python dependencies: up to date"
fi

# ---------------------------------------------------------------- 3. catkin build
set +u
if [ -n "$ROS_SETUP" ]; then source "$ROS_SETUP"; fi
source "$VENV/bin/activate"
log "building with catkin_make (PYTHON_EXECUTABLE=$PY)"
mkdir -p "$ROOT/build"
catkin_make -DPYTHON_EXECUTABLE="$PY" -DCMAKE_BUILD_TYPE=Release > "$ROOT/build/catkin_make.log" 2>&1 \
  || { tail -40 "$ROOT/build/catkin_make.log"; log "catkin_make failed (log: build/catkin_make.log)"; exit 1; }

# ---------------------------------------------------------------- 4. root setup.bash
cat > "$ROOT/setup.bash" <<EOF
# Written by catkin_ws_setup.sh: activates the venv and the catkin devel space.
# Usage: source setup.bash
${ROS_SETUP:+source "$ROS_SETUP"}
source "$VENV/bin/activate"
source "$ROOT/devel/setup.bash"
EOF
log "done. Now: source setup.bash"
