#!/usr/bin/env bash
# A clean environment with the ROS-free I/O part of playseg alone, for scripts/io_check.py
# (`make io-check`): Python 3.11, requirements-io.txt (exact pins; no ROS 2 wheels, no playseg_msgs, no
# torch) and playseg installed from the work tree without dependencies. The pinned packages are installed
# once (stamp file in the venv, keyed on the interpreter and requirements-io.txt); playseg itself is
# reinstalled from the work tree on every run, so the check sees the current code.
# Override: IO_VENV=DIR, PYTHON=/path/to/python3.11.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${IO_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/playseg/io-venv}"
PYTHON="${PYTHON:-python3.11}"
REQS="$ROOT/requirements-io.txt"
LOG="$ROOT/build/setup-logs/io-venv.log"
mkdir -p "$(dirname "$LOG")"

fail() {
  echo "[io-env] FAILED; last lines of $LOG:" >&2
  grep -v "is ignored: it is neither a file nor a directory" "$LOG" | tail -n 25 >&2
  exit 1
}

"$PYTHON" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' >/dev/null 2>&1 ||
  { echo "[io-env] $PYTHON is not Python 3.11 (set PYTHON)" >&2; exit 1; }
KEY="$("$PYTHON" --version 2>&1) $(sha256sum "$REQS" | cut -c1-16)"
STAMP="$VENV/.playseg-stamp"
: >"$LOG"
if [[ ! -f "$STAMP" || "$(cat "$STAMP")" != "$KEY" ]]; then
  echo "[io-env] building $VENV with $PYTHON (log: $LOG) ..."
  t0=$SECONDS
  (
    set -e
    rm -rf "$VENV"
    "$PYTHON" -m venv "$VENV"
    "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off -r "$REQS"
  ) >>"$LOG" 2>&1 || fail
  echo "$KEY" >"$STAMP"
  echo "[io-env] dependencies installed ($((SECONDS - t0)) s)"
fi

# Built from a copy of the sources so that the build leaves nothing in the work tree.
SRC="$(mktemp -d)"
trap 'rm -rf "$SRC"' EXIT
cp -r "$ROOT/setup.py" "$ROOT/package.xml" "$ROOT/resource" "$ROOT/requirements-io.txt" \
  "$ROOT/msg_defs" "$ROOT/playseg_core" "$ROOT/playseg_ros" "$SRC/"
find "$SRC" -name __pycache__ -prune -exec rm -rf {} +
(
  set -e
  "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off --no-deps \
    --force-reinstall "$SRC"
  "$VENV/bin/python" -m pip check
) >>"$LOG" 2>&1 || fail
echo "[io-env] playseg installed from the work tree into $VENV"
