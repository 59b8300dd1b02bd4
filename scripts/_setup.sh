#!/usr/bin/env bash
# Create the virtual environment .venv (once) and install semlab with everything it needs.
# Needs only Python >= 3.10 with venv and pip. Re-running is cheap: it reinstalls only when
# environment.txt or pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${SEMLAB_VENV:-.venv}
stamp="$VENV/.semlab-installed"
want=$(cat environment.txt pyproject.toml | sha256sum | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ]; then
  echo "== creating virtual environment $VENV"
  "$PY" -m venv "$VENV"
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "== installing requirements (environment.txt) and semlab"
  "$VENV/bin/python" -m pip install --quiet --upgrade pip
  "$VENV/bin/python" -m pip install --quiet -r environment.txt
  "$VENV/bin/python" -m pip install --quiet --no-deps -e .
  echo "$want" > "$stamp"
fi
