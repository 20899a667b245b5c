#!/usr/bin/env bash
# Idempotent set-up of the development environment in .venv:
#   1. create .venv (Python 3.11)
#   2. install the exactly pinned dependencies (requirements.txt)
#   3. repair the ROS 2 wheels' CMake files (they name the build machine's Python paths)
#   4. build and install msg_defs/playseg_msgs into the venv with the real rosidl generators
#   5. install Debian's chromium and chromium-driver (the review page's browser tests) when missing
#   6. install playseg (playseg_core + playseg_ros) in development mode
# Each step is skipped when its inputs did not change (stamp files in .venv/.stamps), so a warm run takes
# seconds. On failure it stops, names the step and shows the end of that step's log.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PLAYSEG_VENV:-$ROOT/.venv}"
PYTHON="${PYTHON:-python3.11}"
STAMPS="$VENV/.stamps"
LOGS="$ROOT/build/setup-logs"
mkdir -p "$LOGS"

step() {  # step NAME STAMP_KEY COMMAND...
  local name="$1" key="$2"; shift 2
  local stamp="$STAMPS/$name"
  if [[ -f "$stamp" && "$(cat "$stamp")" == "$key" ]]; then
    return 0
  fi
  local log="$LOGS/$name.log"
  echo "[setup] $name ..."
  local t0=$SECONDS
  # Run in a background subshell so that `set -e` holds inside the step (it is off in an `if` condition).
  ( set -e; "$@" ) >"$log" 2>&1 &
  if ! wait $!; then
    echo "[setup] FAILED at step '$name'. Last lines of $log:" >&2
    grep -v "is ignored: it is neither a file nor a directory" "$log" | tail -n 25 >&2
    exit 1
  fi
  mkdir -p "$STAMPS"
  echo "$key" >"$stamp"
  echo "[setup] $name done ($((SECONDS - t0)) s)"
}

hash_of() { cat "$@" | sha256sum | cut -c1-16; }

create_venv() {
  command -v "$PYTHON" >/dev/null || { echo "$PYTHON not found: playseg needs Python 3.11"; return 1; }
  "$PYTHON" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' ||
    { echo "$PYTHON is not Python 3.11"; return 1; }
  rm -rf "$VENV"
  "$PYTHON" -m venv "$VENV"
}

install_requirements() {
  "$VENV/bin/python" -m pip install --disable-pip-version-check -r "$ROOT/requirements.txt"
  "$VENV/bin/python" -m pip check
}

fix_wheel_cmake_paths() {
  # The ROS 2 wheels were built under /opt/python/cp311-cp311; point their CMake exports at this venv's
  # interpreter, or cmake's generate step rejects the non-existent include and site-packages dirs.
  local inc site
  inc="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
  site="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  { grep -rlE '/opt/python/cp311-cp311/(include/python3.11|lib/python3.11/site-packages)' \
    --include='*.cmake' "$VENV/share" || true; } | while read -r f; do
    sed -i -e "s#/opt/python/cp311-cp311/include/python3.11#$inc#g" \
      -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages#$site#g" "$f"
  done
  if grep -rqE '/opt/python/cp311-cp311' --include='*.cmake' "$VENV/share"; then
    echo "some CMake files still name /opt/python/cp311-cp311:"
    grep -rlE '/opt/python/cp311-cp311' --include='*.cmake' "$VENV/share" | head
    return 1
  fi
}

build_msgs() {
  local build="$ROOT/build/playseg_msgs"
  rm -rf "$build"
  export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
  cmake -S "$ROOT/msg_defs/playseg_msgs" -B "$build" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF
  cmake --build "$build" -j2
  cmake --install "$build"
  "$VENV/bin/python" -c 'from playseg_msgs.msg import PlayStep, Annotation, LabelledSegment, TrainerStatus'
}

install_project() {
  "$VENV/bin/python" -m pip install --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT"
  "$VENV/bin/python" -c 'import playseg_core, playseg_ros'
}

install_browser() {
  # Debian's headless Chromium and its WebDriver: tests/test_review_browser.py drives them (Selenium).
  if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then return 0; fi
  if [[ "$(id -u)" != 0 ]]; then
    echo "not root: install chromium and chromium-driver with apt-get (the review page's browser tests skip without them)"
    return 0
  fi
  apt-get update
  DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium chromium-driver
}

step venv "$("$PYTHON" --version 2>&1)" create_venv
step requirements "$(hash_of "$ROOT/requirements.txt")" install_requirements
step fix-cmake "$(hash_of "$ROOT/requirements.txt")" fix_wheel_cmake_paths
# The interface build depends on the ROS 2 pins only: another Python package pinned does not rebuild it.
ros_pins_key="$(grep -E '^(ros-kilted-|catkin-pkg)' "$ROOT/requirements.txt" | sha256sum | cut -c1-16)"
step playseg_msgs "$ros_pins_key-$(hash_of "$ROOT"/msg_defs/playseg_msgs/CMakeLists.txt \
  "$ROOT"/msg_defs/playseg_msgs/package.xml "$ROOT"/msg_defs/playseg_msgs/msg/* "$ROOT"/msg_defs/playseg_msgs/srv/*)" build_msgs
step browser "$(command -v chromedriver || echo none)" install_browser
step project "$(hash_of "$ROOT/requirements.txt" "$ROOT/setup.py" "$ROOT/package.xml")" install_project
