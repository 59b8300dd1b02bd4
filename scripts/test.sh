#!/usr/bin/env bash
# Set everything up, then run all tests: the library tests (pytest) and every notebook (nbval).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/_setup.sh
export MPLBACKEND=Agg
.venv/bin/python -m pytest -q -p no:cacheprovider --nbval-lax tests notebooks "$@"
