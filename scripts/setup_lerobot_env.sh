#!/usr/bin/env bash
# Idempotent set-up of lerobot's own environment, .venv-lerobot (Python 3.12), for
# scripts/lerobot_check.py (`make lerobot-check`): lerobot needs Python >= 3.12 and torch < 2.12, which
# cannot share playseg's .venv (Python 3.11, torch 2.13). Installs requirements-lerobot.txt (exact pins)
# and is skipped when the venv was built from the same pins and interpreter (stamp file in the venv).
# From scratch: ~2.5 min and ~5.4 GB here (PyPI's torch for Python 3.12 is the CUDA build; its nvidia-*
# libraries are ~2.7 GB of it). Override: LEROBOT_VENV=DIR, LEROBOT_PYTHON=/path/to/python3.12.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# outside the work tree: 5.4 GB of third-party code, kept between clones and CI runs on one machine
VENV="${LEROBOT_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/playseg/lerobot-venv}"
REQS="$ROOT/requirements-lerobot.txt"
LOG="$ROOT/build/setup-logs/lerobot-venv.log"
mkdir -p "$(dirname "$LOG")"

find_python() {
  local candidate
  for candidate in "${LEROBOT_PYTHON:-}" python3.12 "$HOME"/.pyenv/versions/3.12*/bin/python3.12 \
    /usr/bin/python3.12 /usr/local/bin/python3.12; do
    [[ -n "$candidate" ]] || continue
    if "$candidate" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
      command -v "$candidate" || echo "$candidate"
      return 0
    fi
  done
  echo "no Python 3.12 found (lerobot needs >= 3.12; set LEROBOT_PYTHON)" >&2
  return 1
}

PYTHON="$(find_python)"
KEY="$("$PYTHON" --version 2>&1) $(sha256sum "$REQS" | cut -c1-16)"
STAMP="$VENV/.playseg-stamp"
if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$KEY" ]]; then
  exit 0
fi
echo "[lerobot-env] building $VENV with $PYTHON (log: $LOG) ..."
t0=$SECONDS
(
  set -e
  rm -rf "$VENV"
  "$PYTHON" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --disable-pip-version-check --progress-bar off -r "$REQS"
  "$VENV/bin/python" -m pip check
  "$VENV/bin/python" -c 'import lerobot.datasets.lerobot_dataset, torch; print("lerobot", torch.__version__)'
) >"$LOG" 2>&1 || {
  echo "[lerobot-env] FAILED; last lines of $LOG:" >&2
  grep -v "is ignored: it is neither a file nor a directory" "$LOG" | tail -n 25 >&2
  exit 1
}
echo "$KEY" >"$STAMP"
echo "[lerobot-env] done ($((SECONDS - t0)) s, $(du -sh "$VENV" | cut -f1))"
