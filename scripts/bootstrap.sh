# Sourced by scripts/main and scripts/test: make the project venv (.venv) ready.
# Idempotent and quick the second time: each stage re-runs only when its inputs changed.
#   1. pip install -r requirements.txt            (stamp: hash of requirements.txt)
#   2. build + install msg_defs into the venv     (stamp: hash of msg_defs/)
#   3. install this ament_python package the colcon way into the venv prefix
#      (executables in .venv/lib/exit_decision, share/exit_decision, ament index marker)
#   4. its C extension (exit_decision/ros/_drain.c) built in the checkout too, for its imports
# The venv is an ament prefix: a .pth file sets AMENT_PREFIX_PATH to it when unset, so
# nothing needs sourcing.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${EXIT_DECISION_VENV:-$ROOT/.venv}"
STAMPS="$VENV/.exit_decision_stamps"
PY="$VENV/bin/python"

# Logs stay out of ~/.ros. (DDS stays on loopback unless the user sets ROS_AUTOMATIC_DISCOVERY_RANGE:
# exit_decision/ros/dds_defaults.py, the one place, sets the default for every process and node.)
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROOT/.ros_log}"
unset _ROS_WHEELS_BOOTSTRAP_COMPLETE

_hash() { (cd "$ROOT" && find "$@" -type f ! -name '*.pyc' ! -name '*.so' ! -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum | sha256sum | cut -c1-16); }
_stage_needed() { [ ! -f "$STAMPS/$1" ] || [ "$(cat "$STAMPS/$1")" != "$2" ]; }
_stage_done() { mkdir -p "$STAMPS"; echo "$2" > "$STAMPS/$1"; }
_log() { echo "[bootstrap] $*" >&2; }

if [ ! -x "$PY" ]; then
  _log "creating $VENV"
  python3.11 -m venv "$VENV"
fi

h=$(_hash requirements.txt)
if _stage_needed deps "$h"; then
  _log "installing pinned requirements (first time: about 2 minutes)"
  "$PY" -m pip install --quiet --disable-pip-version-check -r "$ROOT/requirements.txt" 2>&1 | grep -v "^WARNING: Location" || true
  "$PY" -c "import rclpy, libsumo, torch, rosbags" || { _log "dependency install failed"; exit 1; }
  site=$("$PY" -c 'import site; print(site.getsitepackages()[0])')
  # Default AMENT_PREFIX_PATH to the venv so ament index look-ups (ros2cli, the nodes) work unsourced.
  echo "import os, sys; os.environ.setdefault('AMENT_PREFIX_PATH', sys.prefix)" > "$site/exit_decision_ament_prefix.pth"
  _stage_done deps "$h"
fi

h=$(_hash msg_defs requirements.txt)
if _stage_needed msgs "$h"; then
  _log "building the interface package msg_defs (exit_decision_msgs)"
  build="$VENV/build/exit_decision_msgs"
  rm -rf "$build"; mkdir -p "$build"
  (
    cd "$build"
    export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
    cmake "$ROOT/msg_defs" -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$PY" \
      -DBUILD_TESTING=OFF > configure.log 2>&1 || { cat configure.log; exit 1; }
    cmake --build . -j"$(nproc)" > build.log 2>&1 || { tail -50 build.log; exit 1; }
    cmake --install . > install.log 2>&1 || { cat install.log; exit 1; }
  )
  _stage_done msgs "$h"
fi

h=$(_hash exit_decision config launch policies setup.py setup.cfg package.xml resource requirements.txt)
if _stage_needed package "$h"; then
  _log "installing the exit_decision package into the venv prefix"
  build="$VENV/build/exit_decision"
  rm -rf "$build"; mkdir -p "$build"
  (
    cd "$ROOT"
    "$PY" setup.py --quiet egg_info --egg-base "$build" build --build-base "$build" \
      install --prefix "$VENV" --record "$build/install_manifest.txt" \
      --single-version-externally-managed --install-scripts "$VENV/lib/exit_decision" \
      > "$build/install.log" 2>&1 || { cat "$build/install.log"; exit 1; }
  )
  ln -sf "$VENV/lib/exit_decision/exit-decision" "$VENV/bin/exit-decision"
  _stage_done package "$h"
fi
# the C extension in the checkout too, for its imports (the tests, `python -m exit_decision`)
if _stage_needed inplace "$h" || ! compgen -G "$ROOT/exit_decision/ros/_drain.*.so" > /dev/null; then
  _log "building the C extension in place"
  build="$VENV/build/exit_decision_inplace"
  mkdir -p "$build"
  (cd "$ROOT" && "$PY" setup.py --quiet build_ext --inplace --build-temp "$build" > "$build/build.log" 2>&1) \
    || { cat "$build/build.log"; exit 1; }
  _stage_done inplace "$h"
fi

export PATH="$VENV/bin:$PATH"
