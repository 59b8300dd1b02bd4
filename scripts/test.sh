#!/usr/bin/env bash
# Set everything up, then run all tests: the library tests (pytest) and every notebook (nbval).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/_setup.sh
bash scripts/_setup_browser.sh   # Debian's chromium + playwright for tests/test_browser.py
export MPLBACKEND=Agg
# Test files in parallel (pytest-xdist, one worker per core up to 4; a file's tests, and a
# notebook's cells, stay on one worker; files with slow tests first: tests/conftest.py), each
# worker single-threaded: numpy's BLAS, OpenCV and the tests' own threads otherwise
# oversubscribe the cores (2-core machine, 2026-12-07: 1805 s one process, 1599 s two workers
# multi-threaded, 1085 s two single-threaded workers). Pass -n 0 to run in one process.
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENCV_FOR_THREADS_NUM=1
.venv/bin/python -m pytest -q -p no:cacheprovider --nbval-lax -n auto --maxprocesses 4 \
  --dist loadfile --no-loadscope-reorder tests notebooks "$@"
