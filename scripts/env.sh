# Source me (bash): activates .venv, the built workspace and `ros2`.
#   source scripts/env.sh
# With ROS 2 Jazzy from apt, source /opt/ros/jazzy/setup.bash first (before `make` too).
_metampc_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [[ ! -x "$_metampc_root/.venv/bin/python" ]]; then
  echo "metampc: no .venv yet; run 'make setup' (or 'make build') first" >&2
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
source "$_metampc_root/.venv/bin/activate"
# The ROS wheels install their prefix into the venv; colcon and the ament index need to see it.
if [[ ":${AMENT_PREFIX_PATH:-}:" != *":$VIRTUAL_ENV:"* && ! -d /opt/ros/jazzy/share/rclpy ]]; then
  export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
  export CMAKE_PREFIX_PATH="$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
fi
if [[ -f "$_metampc_root/install/local_setup.bash" ]]; then
  # shellcheck disable=SC1091
  source "$_metampc_root/install/local_setup.bash"
fi
unset _metampc_root
