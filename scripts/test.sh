#!/usr/bin/env bash
# Set up (first time), lint, and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check core app tests
.venv/bin/python -m pytest "$@"
