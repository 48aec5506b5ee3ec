"""Identity of the refined curve across two code versions, to a tolerance in disparity.

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/refine_identity.py write before.json DATA_DIR[,DATA_DIR...] [--set ...]
    python scripts/refine_identity.py compare before.json after.json [--tol-px 1e-6] [-v]

``scripts/stage_fingerprint.py`` hashes the curve, so it tells a change of the last bit from a
change of the result. A solve that is exact in arithmetic but not in its rounding (the
refinement's banded QR against a dense one) differs in the last bits; this script stores per
frame the stage fingerprint without the curve hash, plus the refined depth control values S_z
and the spline's knots, and ``compare`` requires every fingerprint field equal (e_S and the
length to 2e-6 mm, their rounding) and the refined curves' disparity f B / S_z(u) to agree
within ``--tol-px`` at 500 points along the curve.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import BSpline
from threadpoolctl import threadpool_limits

sys.path.append(str(Path(__file__).resolve().parent))  # stage_fingerprint; PYTHONPATH: the package

from stage_fingerprint import _fingerprint, _flat, _same, parser  # noqa: E402

from threadrecon.app.bench import with_overrides  # noqa: E402
from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.evaluation import evaluate_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402

ROUNDED_MM = 2e-6  # e_S and length are stored to 6 decimals: a rounding apart


def _write(out_path: str, data: str, config: str | None, overrides: list[str]) -> None:
    params = with_overrides(resolve_preset(config), overrides)
    out: dict[str, Any] = {}
    with threadpool_limits(1):
        for root in data.split(","):
            for frame in discover(root):
                try:
                    loaded = load_frame(frame)
                except Exception:  # the evaluation's row says what failed
                    loaded = None
                row, rec = evaluate_frame(frame, params, loaded)
                fp = _fingerprint(row, rec)
                fp.pop("curve", None)
                if rec is not None and "refine" in rec.runs:
                    s = rec["refine"]
                    fp["refine"] = {
                        "knots": s.knots.tolist(),
                        "degree": int(s.degree),
                        "z": s.ctrl[:, 2].tolist(),
                        "fB": float(loaded[1].focal * loaded[1].baseline),  # type: ignore[index]
                    }
                out[f"{root}:{frame.id}"] = fp
    Path(out_path).write_text(json.dumps(out, indent=1, sort_keys=True))
    print(f"{len(out)} frames -> {out_path}")


def _disparity(r: dict[str, Any], fB: float) -> np.ndarray:
    t = np.asarray(r["knots"])
    k = r["degree"]
    u = np.linspace(t[k], t[-k - 1], 500)
    with np.errstate(divide="ignore", invalid="ignore"):
        return fB / BSpline(t, np.asarray(r["z"]), k)(u)


def compare(before: str, after: str, tol_px: float, verbose: bool) -> int:
    a = json.loads(Path(before).read_text())
    b = json.loads(Path(after).read_text())
    if set(a) != set(b):
        print(f"different frames: {sorted(set(a) ^ set(b))}")
        return 1
    fields: dict[str, int] = {}
    worst = 0.0
    refined = 0
    for key in sorted(a):
        ra, rb = a[key].pop("refine", None), b[key].pop("refine", None)
        fa, fb = _flat(a[key]), _flat(b[key])
        diff = [
            f
            for f in sorted(set(fa) | set(fb))
            if not _same(fa.get(f), fb.get(f))
            and not (
                f in ("e_S_mm", "length_mm")
                and isinstance(fa.get(f), float)
                and isinstance(fb.get(f), float)
                and abs(fa[f] - fb[f]) <= ROUNDED_MM
            )
        ]
        if (ra is None) != (rb is None):
            diff.append("refine")
        elif ra is not None:
            if ra["knots"] != rb["knots"] or ra["degree"] != rb["degree"]:
                diff.append("refine.knots")
            else:
                refined += 1
                fB = ra["fB"]
                err = float(np.nanmax(np.abs(_disparity(ra, fB) - _disparity(rb, fB))))
                worst = max(worst, err)
                if not err <= tol_px:
                    diff.append("refine.disparity")
        for f in diff:
            fields[f] = fields.get(f, 0) + 1
        if diff and verbose:
            print(key, {f: (fa.get(f), fb.get(f)) for f in diff})
    print(
        f"{len(a)} frames ({refined} with a refined curve); max |disparity difference| "
        f"{worst:.2e} px (tolerance {tol_px:g}); fields that differ (frames): {fields or 'none'}"
    )
    return 0 if not fields else 1


def main() -> int:
    ap, _ = parser(__doc__)
    for name, sub in ap._subparsers._group_actions[0].choices.items():  # type: ignore[union-attr]
        if name == "compare":
            sub.add_argument("--tol-px", type=float, default=1e-6)
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args.out, args.data, args.config, args.set)
        return 0
    return compare(args.before, args.after, args.tol_px, args.verbose)


if __name__ == "__main__":
    sys.exit(main())
