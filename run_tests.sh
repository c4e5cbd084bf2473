#!/usr/bin/env bash
# The README's test command: set up the workspace (idempotent) and run the whole test suite.
#   ./run_tests.sh                 # everything
#   ./run_tests.sh -k conversions  # extra arguments go to pytest
set -eo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$ROOT"
./catkin_ws_setup.sh
set +u
source setup.bash
set +e
python -m pytest tests "$@"
rc=$?
if [ "$rc" = 5 ]; then
  echo "run_tests.sh: pytest collected no tests; that is a failure here" >&2
  exit 1
fi
exit "$rc"
