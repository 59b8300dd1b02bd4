#!/usr/bin/env bash
# Set everything up, then run the main job on the demo experiment in data_samples/.
# Results (executed notebooks, HTML reports, result files) go to a new folder under reports/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/_setup.sh
out="reports/demo-$(date +%Y%m%d-%H%M%S)"
.venv/bin/semlab run data_samples/demo --out "$out" "$@"
echo "open $out/index.html"
