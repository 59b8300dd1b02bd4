#!/usr/bin/env bash
# Set everything up, then run all tests: the library tests (pytest) and every notebook (nbval).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/_setup.sh
bash scripts/_setup_browser.sh   # Debian's chromium + playwright for tests/test_browser.py
export MPLBACKEND=Agg
.venv/bin/python -m pytest -q -p no:cacheprovider --nbval-lax tests notebooks "$@"
