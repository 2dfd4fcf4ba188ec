# Source this file to use bac by hand:  source scripts/env.sh
_bac_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
if [ ! -x "$_bac_root/.venv/bin/python" ]; then
  echo "bac: run scripts/setup.sh (or make test / make demo) first" >&2
else
  . "$_bac_root/.venv/bin/activate"
  export AMENT_PREFIX_PATH="$_bac_root/.venv"
  export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
  export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
  export BAC_WS="$_bac_root/ros_ws"
fi
unset _bac_root
