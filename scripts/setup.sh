#!/usr/bin/env bash
# Create or update .venv with every pinned dependency, the CMake fix-ups and the ros2 shim.
# Idempotent: when the pins and this script are unchanged since the last success, it returns
# at once. With ROS 2 Jazzy from apt (/opt/ros/jazzy/setup.bash sourced before `make`), the
# venv sees the system's rclpy and ros2 (--system-site-packages) and no ROS wheels are installed.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
PYTHON=${PYTHON:-python3}
venv=$root/.venv

if [[ "${ROS_DISTRO:-}" == jazzy && "${AMENT_PREFIX_PATH:-}" == */opt/ros/jazzy* ]]; then
  mode=system
  reqs=(requirements/python.txt)
else
  mode=wheels
  reqs=(requirements/ros.txt requirements/python.txt)
fi
stamp=$venv/.metampc-setup
want=$(cat "${reqs[@]}" scripts/setup.sh scripts/fix_cmake_paths.py scripts/ros2_shim.py \
       | sha256sum | cut -c1-16)-$mode
if [[ -f $stamp && "$(cat "$stamp")" == "$want" ]]; then
  echo "setup: .venv is up to date ($mode ROS)"
  exit 0
fi

start=$(date +%s)
if [[ ! -x $venv/bin/python ]]; then
  if [[ $mode == system ]]; then
    "$PYTHON" -m venv --system-site-packages "$venv"
  else
    "$PYTHON" -m venv "$venv"
  fi
fi
pip=("$venv/bin/python" -m pip --disable-pip-version-check -q)
req_args=()
for r in "${reqs[@]}"; do req_args+=(-r "$r"); done
# pip's warnings about missing local index folders are noise on these machines.
"${pip[@]}" install "${req_args[@]}" 2> >(grep -v "is ignored: it is neither" >&2)
# colcon-core needs setuptools<80; torch pulls a newer one, so this pin goes last.
"${pip[@]}" install -r requirements/last.txt
if [[ $mode == wheels ]]; then
  "$venv/bin/python" scripts/fix_cmake_paths.py "$venv"
  install -m 755 /dev/null "$venv/bin/ros2"
  { echo "#!$venv/bin/python"; cat scripts/ros2_shim.py; } > "$venv/bin/ros2"
fi
echo "$want" > "$stamp"
echo "setup: done in $(( $(date +%s) - start )) s ($mode ROS)"
