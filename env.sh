# Source me (bash): activates the project's venv and the colcon workspace overlay.
#   source env.sh
_mshoot_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")" && pwd)"
if [ ! -x "$_mshoot_root/.venv/bin/python" ] || [ ! -f "$_mshoot_root/ros2_ws/install/local_setup.bash" ]; then
  echo "mshoot: not set up yet, run 'make setup' in $_mshoot_root" >&2
  return 1 2>/dev/null || exit 1
fi
# shellcheck disable=SC1091
source "$_mshoot_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$_mshoot_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$_mshoot_root/.venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
# shellcheck disable=SC1091
COLCON_TRACE= source "$_mshoot_root/ros2_ws/install/local_setup.bash"
export MSHOOT_ROOT="$_mshoot_root"
# the BOPTEST test case of the benchmark (any folder in BOPTEST's layout; a value set wins)
export MSHOOT_BOPTEST_DIR="${MSHOOT_BOPTEST_DIR:-$(dirname "$_mshoot_root")/shared/boptest/bestest_hydronic_heat_pump}"
unset _mshoot_root
