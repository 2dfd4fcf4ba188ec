#!/usr/bin/env bash
# Run pytest (any arguments) the way `make test` does: inside a private network namespace,
# with the ROS environment set. Example: scripts/pytest.sh tests/sim -q -x
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export AMENT_PREFIX_PATH="$ROOT/.venv" ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST RMW_IMPLEMENTATION=rmw_fastrtps_cpp
cd "$ROOT"
exec "$ROOT/.venv/bin/python" -m bac_bringup.netns -- "$ROOT/.venv/bin/python" -m pytest "$@"
