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
#              MDR_SKIP_APT=1 never calls apt (for machines where you manage packages yourself);
#              MDR_BUILD_NAVIGATION=1 builds move_base (ROS navigation) when none is installed,
#              from MDR_NAVIGATION_TARBALL (default ../shared/thirdparty/ros-navigation-*.tar.gz),
#              into ~/.cache/mdr_slam/navigation-<sha256 prefix> (MDR_CACHE_DIR), once per tarball.
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

# ---------------------------------------------------------------- 4. move_base (optional)
# An installed move_base (Noetic: ros-noetic-navigation) is used as is. Debian packages none, so
# on request the navigation stack is built from a source tarball into its own workspace outside
# the checkout (minutes of build: cached, shared by checkouts, keyed by the tarball's hash).
NAV_WS=""
nav_installed() {   # in a clean environment: our own cached workspace does not count
  env -i PATH=/usr/local/bin:/usr/bin:/bin HOME="$HOME" bash -c \
    '[ -z "$1" ] || source "$1"; rospack find move_base' _ "$ROS_SETUP" >/dev/null 2>&1
}
tarball="${MDR_NAVIGATION_TARBALL:-}"
if [ -z "$tarball" ]; then
  tarball=$(ls -1 "$ROOT"/../shared/thirdparty/ros-navigation-*.tar.gz 2>/dev/null | tail -1 || true)
fi
if [ -n "$tarball" ] && [ -f "$tarball" ]; then
  NAV_WS="${MDR_CACHE_DIR:-$HOME/.cache/mdr_slam}/navigation-$(sha256sum "$tarball" | cut -c1-16)"
fi
if nav_installed; then
  NAV_WS=""
  log "move_base: installed, used as is"
elif [ -n "$NAV_WS" ] && [ -f "$NAV_WS/.built" ]; then
  log "move_base: built earlier in $NAV_WS"
elif [ "${MDR_BUILD_NAVIGATION:-0}" != 1 ]; then
  NAV_WS=""
  log "move_base: not found (MDR_BUILD_NAVIGATION=1 builds it from the navigation tarball)"
elif [ -z "$NAV_WS" ]; then
  log "move_base: no navigation tarball (${tarball:-../shared/thirdparty/ros-navigation-*.tar.gz}): not built, its tests skip"
else
  if [ -n "$ROS_SETUP" ]; then
    NAV_APT=(ros-noetic-dynamic-reconfigure ros-noetic-map-msgs ros-noetic-move-base-msgs
             ros-noetic-laser-geometry ros-noetic-tf2-sensor-msgs ros-noetic-angles
             ros-noetic-tf2-eigen ros-noetic-pluginlib ros-noetic-actionlib
             ros-noetic-visualization-msgs libnetpbm10-dev)
  else
    NAV_APT=(libdynamic-reconfigure-config-init-mutex-dev python3-dynamic-reconfigure
             libmap-msgs-dev libmove-base-msgs-dev liblaser-geometry-dev
             libtf2-sensor-msgs-dev libangles-dev libnetpbm-dev libtf2-eigen-dev)
  fi
  missing=()
  for p in "${NAV_APT[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ "${#missing[@]}" -gt 0 ]; then
    if [ "${MDR_SKIP_APT:-0}" = 1 ]; then
      log "MDR_SKIP_APT=1 but move_base's build needs: ${missing[*]}"; exit 1
    fi
    log "installing move_base's build dependencies with apt: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
  mkdir -p "$(dirname "$NAV_WS")"
  exec 9> "$NAV_WS.lock"   # one build at a time: several checkouts may set up at once
  flock 9
  if [ ! -f "$NAV_WS/.built" ]; then
    log "move_base: building $(basename "$tarball") in $NAV_WS (minutes; log: $NAV_WS/build.log)"
    rm -rf "$NAV_WS"
    mkdir -p "$NAV_WS/src"
    tar -xzf "$tarball" -C "$NAV_WS/src"
    t0=$(date +%s)
    # a clean environment, so the workspace chains to ROS only, not to this checkout or its venv
    env -i PATH=/usr/local/bin:/usr/bin:/bin HOME="$HOME" LANG=C.UTF-8 bash -c \
      '[ -z "$1" ] || source "$1"; cd "$2" && catkin_make -j2 -DCATKIN_ENABLE_TESTING=OFF \
         -DCMAKE_BUILD_TYPE=Release -DPYTHON_EXECUTABLE=/usr/bin/python3' \
      _ "$ROS_SETUP" "$NAV_WS" > "$NAV_WS/build.log" 2>&1 \
      || { tail -40 "$NAV_WS/build.log"; log "move_base build failed (log: $NAV_WS/build.log)"; exit 1; }
    echo "$(basename "$tarball") built in $(( $(date +%s) - t0 )) s" > "$NAV_WS/.built"
    log "move_base: $(cat "$NAV_WS/.built")"
  else
    log "move_base: built meanwhile in $NAV_WS"
  fi
  flock -u 9
  exec 9>&-
fi

# ---------------------------------------------------------------- 5. root setup.bash
cat > "$ROOT/setup.bash" <<EOF
# Written by catkin_ws_setup.sh: activates the venv and the catkin devel space.
# Usage: source setup.bash
${ROS_SETUP:+source "$ROS_SETUP"}
source "$VENV/bin/activate"
source "$ROOT/devel/setup.bash"
EOF
if [ -n "$NAV_WS" ]; then
  cat >> "$ROOT/setup.bash" <<EOF
# move_base, built by catkin_ws_setup.sh (MDR_BUILD_NAVIGATION=1) in a workspace of its own
if [ -f "$NAV_WS/devel/setup.bash" ]; then source "$NAV_WS/devel/setup.bash" --extend; fi
EOF
fi
log "done. Now: source setup.bash"
