#!/usr/bin/env bash
# One setup path for mshoot: venv + pinned wheels + CMake path fix + FMU build + colcon build.
# Idempotent: every stage is skipped when its inputs have not changed (stamps in .venv/).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
venv="$root/.venv"
py="${PYTHON:-python3.11}"
log() { printf '[setup] %s\n' "$*"; }
hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -c1-16; }

command -v "$py" >/dev/null || { echo "[setup] error: $py not found (Python 3.11 is required by the ROS 2 Jazzy wheels)" >&2; exit 1; }

# 1. The venv and the pinned packages.
if [ ! -x "$venv/bin/python" ]; then
  log "creating $venv with $($py --version)"
  "$py" -m venv "$venv"
fi
req_hash=$(hash_of requirements.txt tools/fix_wheel_cmake_paths.py)
if [ "$(cat "$venv/.stamp-requirements" 2>/dev/null)" != "$req_hash" ]; then
  log "installing pinned requirements (uv)"
  "$venv/bin/python" -m pip install -q --disable-pip-version-check uv==0.13.8
  VIRTUAL_ENV="$venv" "$venv/bin/uv" pip install -q -r requirements.txt
  "$venv/bin/python" tools/fix_wheel_cmake_paths.py "$venv"
  # byte-compile once: with PYTHONDONTWRITEBYTECODE set, every process would otherwise
  # compile numpy/scipy/pandas/matplotlib from source at import (seconds per node)
  "$venv/bin/python" -m compileall -q -j 0 "$venv/lib" > /dev/null || true
  echo "$req_hash" > "$venv/.stamp-requirements"
else
  log "requirements unchanged, skipping install"
fi

# 2. The FMUs and the batch drivers: compile the R1C1 FMU and the batched Co-Simulation and
#    Model Exchange drivers (gcc) into the cache, $MSHOOT_FMU_DIR or ~/.cache/mshoot/fmu, each
#    under a hash of its sources; a quick no-op when those builds are already there. The
#    runtime only finds them there (mshoot_core.fmu_cache): it never compiles.
fmu=$(PYTHONPATH="$root/ros2_ws/src/mshoot_core${PYTHONPATH:+:$PYTHONPATH}" \
  "$venv/bin/python" -m mshoot_core.fmu_build --cache r1c1 setpoint_zone) \
  || { echo "[setup] error: building the R1C1 FMU and the batch drivers failed (gcc is required; see above)" >&2; exit 1; }
log "R1C1 FMU and batch drivers: $(echo $fmu)"

# 3. The workspace (colcon, symlink install: Python edits are live without a rebuild).
src_files=$(find ros2_ws/src -type f \( -name package.xml -o -name setup.py -o -name setup.cfg \
  -o -name CMakeLists.txt -o -name '*.msg' -o -path '*/resource/*' -o -path '*/config/*' \
  -o -path '*/launch/*' -o -path '*/fmu_src/*' \) | LC_ALL=C sort)
ws_hash=$(hash_of $src_files)
if [ "$(cat "$venv/.stamp-workspace" 2>/dev/null)" != "$ws_hash" ] || [ ! -d ros2_ws/install ]; then
  log "building the workspace (colcon)"
  (
    export VIRTUAL_ENV="$venv" PATH="$venv/bin:$PATH"
    export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
    cd ros2_ws
    # the mshoot command was a generated console-script launcher; it is now a plain script
    # (a symlink to ros2_ws/src/mshoot_studies/scripts/mshoot) that cannot replace the old file
    launcher=install/mshoot_studies/bin/mshoot
    if [ -f "$launcher" ] && [ ! -L "$launcher" ]; then rm -f "$launcher"; fi
    colcon --log-base log build --symlink-install --event-handlers console_cohesion- \
      --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$venv/bin/python" \
      > build.log 2>&1 || { tail -40 build.log >&2; echo "[setup] error: colcon build failed, see ros2_ws/build.log" >&2; exit 1; }
  )
  echo "$ws_hash" > "$venv/.stamp-workspace"
else
  log "workspace unchanged, skipping colcon build"
fi

# 4. Byte-compile the workspace's own modules (the symlink install imports them from
#    ros2_ws/src): with PYTHONDONTWRITEBYTECODE set, as on these machines, every command would
#    otherwise compile them at import (~0.1 s a run). Only new or edited files are compiled;
#    a file edited after this is compiled in memory at import, as before.
"$venv/bin/python" -m compileall -q -j 0 ros2_ws/src > /dev/null || true

# 5. The plot worker's imports compiled at its optimisation level (-OO, see
#    mshoot_core.plotting.worker_command), which step 1 does not compile: once, else the first
#    run's worker would (a second or more of CPU).
if ! compgen -G "$venv/lib/python*/site-packages/matplotlib/__pycache__/__init__.*.opt-2.pyc" > /dev/null; then
  log "compiling the plot worker's imports (-OO)"
  PYTHONPATH="$root/ros2_ws/src/mshoot_core" "$venv/bin/python" -c \
    'import mshoot_core.plotting as p; raise SystemExit(p.prepare_worker())' \
    || log "warning: the plot worker did not start; figures are drawn in the command's process"
fi
log "ready: source env.sh"
