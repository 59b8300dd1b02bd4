#!/usr/bin/env bash
# What the browser test (tests/test_browser.py) needs: Debian's Chromium and the playwright
# Python package in the venv. Never downloads a browser build (no `playwright install`).
# Fails soft: when something cannot be installed it says so and the test skips.
# Run after scripts/_setup.sh (the venv must exist).
set -uo pipefail
cd "$(dirname "$0")/.."
VENV=${SEMLAB_VENV:-.venv}
CHROMIUM=/usr/bin/chromium

if [ ! -x "$CHROMIUM" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "== installing chromium (apt-get) for the browser test"
    if ! { DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null \
           && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
                chromium >/dev/null; }; then
      echo "!! could not install chromium with apt-get: the browser test will be skipped" >&2
    fi
  else
    echo "!! $CHROMIUM is missing (install Debian's chromium package as root): the browser" \
         "test will be skipped" >&2
  fi
fi

if ! "$VENV/bin/python" -c "import playwright.sync_api" >/dev/null 2>&1; then
  spec=$(grep -iE '^[[:space:]]*playwright([^a-z0-9_.-]|$)' requirements-dev.txt | head -n 1 \
         | sed -e 's/#.*//' -e 's/[[:space:]]//g')
  spec=${spec:-playwright}
  echo "== installing $spec into $VENV for the browser test"
  # the pip package only; browsers come from the system (PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD
  # guards against any install hook that would fetch one)
  if ! PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 "$VENV/bin/python" -m pip install --quiet "$spec"; then
    echo "!! could not install $spec: the browser test will be skipped" >&2
  fi
fi
exit 0
