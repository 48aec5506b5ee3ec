"""Bit-for-bit identity of the spline re-runs across two code versions (issue 13: a speed-up of
the re-run path changes nothing).

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/rerun_identity.py write before.json DATA_DIR[,DATA_DIR...] [--config ...]
    python scripts/rerun_identity.py compare before.json after.json [-v]

Per frame, on one pipeline as ``threadrecon bench`` and the debugger's sliders run it: the full
run, then the spline re-run (n_ctrl - 1: a new set-up), then the solver re-run (data_weight + 1:
the set-up reused), then back to the full run's parameters (every re-run stage from caches
of the segmentation). After each, sha1 hashes of the exact bytes of the spline, refine and
camera results and of the check's result (status, reasons, score, evidence repr, per-point
arrays), so a cache that returned a stale or shared value shows as a difference.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))  # stage_fingerprint (this folder)

from stage_fingerprint import compare, parser  # noqa: E402

from threadrecon.app.bench import with_overrides  # noqa: E402
from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.pipeline import Pipeline  # noqa: E402

STAGES = ("spline", "refine", "camera", "check")


def _h(value: Any) -> str:
    """sha1 of a result's exact content: arrays by bytes, dtype and shape; dataclasses field
    by field; floats by repr."""
    h = hashlib.sha1()

    def feed(v: Any) -> None:
        if isinstance(v, np.ndarray):
            a = np.ascontiguousarray(v)
            h.update(f"A{a.dtype}{a.shape}".encode() + a.tobytes())
        elif is_dataclass(v) and not isinstance(v, type):
            h.update(type(v).__name__.encode())
            for f in fields(v):
                if f.name.startswith("_"):
                    continue
                h.update(f.name.encode())
                feed(getattr(v, f.name))
        elif isinstance(v, dict):
            for k in sorted(v, key=repr):
                feed(k)
                feed(v[k])
        elif isinstance(v, list | tuple):
            h.update(f"L{len(v)}".encode())
            for x in v:
                feed(x)
        else:
            h.update(repr(v).encode())

    feed(value)
    return h.hexdigest()[:16]


def _result(rec: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"failed": rec.failed_stage, "message": rec.message}
    for s in STAGES:
        if s in rec.runs:
            out[s] = _h(rec[s])
    if "check" in rec.runs:
        out["evidence"] = repr(rec["check"].evidence())
    return out


def _write(out_path: str, data: str, config: str | None, overrides: list[str]) -> None:
    params = with_overrides(resolve_preset(config), overrides)
    sp = params.spline
    variants = {
        "run": params,
        "n_ctrl-1": replace(params, spline=replace(sp, n_ctrl=sp.n_ctrl - 1)),
        "data_weight+1": replace(params, spline=replace(sp, data_weight=sp.data_weight + 1.0)),
        "back": params,
    }
    out: dict[str, Any] = {}
    with threadpool_limits(1):
        for root in data.split(","):
            for frame in discover(root):
                pair, calib, _ = load_frame(frame)
                pipe = Pipeline(pair, calib)
                out[f"{root}:{frame.id}"] = {
                    name: _result(pipe.run(p)) for name, p in variants.items()
                }
    Path(out_path).write_text(json.dumps(out, indent=1, sort_keys=True))
    print(f"{len(out)} frames -> {out_path}")


def main() -> int:
    ap, _ = parser(__doc__)
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args.out, args.data, args.config, args.set)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
