#!/usr/bin/env bash
# Issue 14's "Must show" as a new user: a clean clone of this checkout's HEAD installed (not
# editable) into a new venv in a new folder, then the commands a user types.
#
#   scripts/check_install.sh WORKDIR [PAPER_DATASET]
#
# WORKDIR (new, empty or missing) gets clone/, venv/, run/ and screenshots/; PAPER_DATASET
# (default ../shared/data/paper-dataset) gives the real frame for --config paper-real. The page
# and its 3D view are driven by scripts/check_install_browser.py (playwright and the system
# chromium of the checkout's own environment: the installed package needs neither).
set -euo pipefail
work=$(realpath -m "${1:?usage: scripts/check_install.sh WORKDIR [PAPER_DATASET]}")
here=$(cd "$(dirname "$0")/.." && pwd)
data=$(realpath "${2:-$here/../shared/data/paper-dataset}")
python=${PYTHON:-python3}
dev_python=${DEV_PYTHON:-$here/.venv/bin/python}
[ -e "$work" ] && [ -n "$(ls -A "$work")" ] && { echo "$work is not empty" >&2; exit 2; }
mkdir -p "$work/run" "$work/screenshots"
branch=$(git -C "$here" rev-parse --abbrev-ref HEAD)
git clone -q --branch "$branch" "$here" "$work/clone"  # the committed state of this branch
git -C "$work/clone" log --oneline -1
[ "$(git -C "$work/clone" rev-parse HEAD)" = "$(git -C "$here" rev-parse HEAD)" ] || { echo "clone is not HEAD" >&2; exit 2; }
"$python" -m venv "$work/venv"
"$work/venv/bin/pip" install -q "$work/clone"
cd "$work/run"
V="$work/venv/bin"
"$V/threadrecon" --version
for name in app core; do
  if "$V/python" -c "import $name" 2>/dev/null; then echo "FAIL: '$name' is importable"; exit 1; fi
  echo "import $name: ModuleNotFoundError (as it should)"
done
"$V/threadrecon" evaluate --out sample_eval.csv
R="$data/real/thread_1_seg"
"$V/threadrecon" reconstruct --config paper-real --left "$R/thread1_left_99_final.png" \
  --right "$R/thread1_right_99_final.png" --calib "$data/real/camera_calibration.yaml" \
  --out real99.json --ply real99.ply
"$dev_python" - "$work" <<'PY'
import json, sys
from pathlib import Path

import jsonschema
import trimesh

work = Path(sys.argv[1])
schema_file = next((work / "venv").glob("lib/python*/site-packages/threadrecon/docs/result.schema.json"))
result = json.loads((work / "run" / "real99.json").read_text())
jsonschema.validate(result, json.loads(schema_file.read_text()))
print(f"real99.json validates against the installed schema: {result['status']}, preset "
      f"{result['preset']}, frame {result['frame']}, {len(result['points'])} points")
ply = trimesh.load(work / "run" / "real99.ply")
assert isinstance(ply, trimesh.path.Path3D), type(ply)
print(f"real99.ply loads as a line set ({type(ply).__name__}, {len(ply.entities)} polyline)")
PY
"$dev_python" "$here/scripts/check_install_browser.py" "$V/threadrecon" "$work/screenshots"
echo "all checks passed"
