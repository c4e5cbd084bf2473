#!/usr/bin/env bash
# The README's first command: set up the workspace (idempotent), render the sample sequence when
# it is absent, map it with the three nodes' core (pose -> depth -> fusion), and leave the map
# (PLY), a report and pictures under output/demo/.
#   ./run_demo.sh                              # ORB tracking on the office sample
#   ./run_demo.sh --pose-source groundtruth    # extra arguments go to `mdr demo`
set -eo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$ROOT"
./catkin_ws_setup.sh
set +u
source setup.bash
exec mdr demo --out "$ROOT/output" "$@"
