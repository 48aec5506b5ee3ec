#!/usr/bin/env bash
# Regenerate sample_data/: synthetic stereo thread frames with exact ground truth, in the
# paper dataset's layout (see sample_data/README.md, written by the generator).
# Deterministic: fixed seeds. Usage, from anywhere:  bash scripts/make_sample_data.sh
# Python: $PYTHON if set, else the project's .venv if present, else `python`.
set -euo pipefail

cd "$(dirname "$0")/.."
if [[ -z "${PYTHON:-}" && -x .venv/bin/python ]]; then
    PYTHON=.venv/bin/python
fi
PYTHON="${PYTHON:-python}"
OUT=sample_data

# Only what this script writes is removed, so that stale frames never linger.
rm -rf "$OUT/simulated/flat" "$OUT/simulated/tissue" "$OUT/simulated/crossing" "$OUT/simulated/raw" \
    "$OUT/README.md"

"$PYTHON" -m threadrecon.app.generate "$OUT" --count 4 --seed 1 --background flat
"$PYTHON" -m threadrecon.app.generate "$OUT" --count 4 --seed 2 --background tissue --noise 2 --blur 0.5
"$PYTHON" -m threadrecon.app.generate "$OUT" --count 2 --seed 3 --background flat --crossing
# Raw frames, no mask: the segmentation must find the thread among vessels and fibres as wide
# as the thread, under uneven light, JPEG-compressed (stored as JPEG to keep sample_data small).
# Dyes, graspers and their combinations: scripts/eval_suites.py (the combined suite is harder).
"$PYTHON" -m threadrecon.app.generate "$OUT" --count 4 --seed 4 --background tissue --noise 2 --blur 0.5 \
    --distractors 6 --lighting 0.4 --jpeg 85 --no-mask --group raw

du -sh "$OUT"
