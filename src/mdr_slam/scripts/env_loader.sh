#!/usr/bin/env bash
# roslaunch env-loader for MDR-SLAM on another computer (the <machine env-loader="..."> of
# launch/mdr.launch). roslaunch logs in over ssh and runs `env_loader.sh COMMAND ARGS...`; this
# sources the workspace (the venv and the catkin devel space, through the setup.bash that
# catkin_ws_setup.sh writes) and then runs COMMAND. The workspace must be at the same path on
# every machine (the launch file names this script by its path on the launching computer),
# or set MDR_WS on the remote side.
#
# Per-machine settings (ROS_IP or ROS_HOSTNAME of that computer, so the others can reach its
# nodes): put `export ROS_IP=192.168.1.12` in WORKSPACE/machine.bash; it is sourced when present.
# From an install space (catkin_make install), whose setup.bash is catkin's own, MDR_VENV names
# the Python virtual environment that holds the pip dependencies (activated after setup.bash).
if [ $# -eq 0 ]; then
    echo "usage: env_loader.sh COMMAND [ARGS...]  (sources the MDR-SLAM workspace, then runs COMMAND)" >&2
    exit 1
fi
ws="${MDR_WS:-}"
if [ -z "$ws" ]; then
    # walk up from this script (src/mdr_slam/scripts in the source tree, share/mdr_slam/scripts
    # when installed) to the first directory with a setup.bash
    d="$(dirname "$(readlink -f "${BASH_SOURCE[0]}")")"
    while [ "$d" != "/" ]; do
        if [ -f "$d/setup.bash" ]; then ws="$d"; break; fi
        d="$(dirname "$d")"
    done
fi
if [ -z "$ws" ] || [ ! -f "$ws/setup.bash" ]; then
    echo "env_loader.sh: no MDR-SLAM workspace found (no setup.bash above $0; set MDR_WS)" >&2
    exit 1
fi
# shellcheck disable=SC1091
source "$ws/setup.bash"
if [ -n "${MDR_VENV:-}" ]; then
    if [ ! -f "$MDR_VENV/bin/activate" ]; then
        echo "env_loader.sh: MDR_VENV=$MDR_VENV has no bin/activate" >&2
        exit 1
    fi
    # shellcheck disable=SC1091
    source "$MDR_VENV/bin/activate"
fi
if [ -f "$ws/machine.bash" ]; then
    # shellcheck disable=SC1091
    source "$ws/machine.bash"
fi
exec "$@"
