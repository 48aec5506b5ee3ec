#!/usr/bin/env bash
# Set up (first time) and run the main job on the bundled sample data.
# Until the browser debugger lands this reconstructs every sample frame and prints the
# evaluation summary; any arguments are passed to `threadrecon evaluate`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/threadrecon reconstruct --stereo sample_data/simulated/flat/flat_1.png \
    --mask sample_data/simulated/flat/flat_1_mask.png \
    --calib sample_data/simulated/flat/calibration.yaml --out out/flat_1.json
.venv/bin/threadrecon evaluate sample_data --out out/sample_evaluation.csv "$@"
