#!/usr/bin/env bash
# Set up (first time) and start the browser debugger on the bundled sample data.
# Open the URL it prints. Extra arguments go to `threadrecon serve` (e.g. --port 8010, or a
# data folder of your own: bash scripts/run.sh /path/to/dataset).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [[ $# -gt 0 && "$1" != -* ]]; then
    exec .venv/bin/threadrecon serve "$@"
fi
exec .venv/bin/threadrecon serve sample_data "$@"
