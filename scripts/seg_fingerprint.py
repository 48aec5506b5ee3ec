"""Per-frame fingerprints of the segmentation alone (masks P_L, P_R, scores, method, or the error),
bit for bit, to show that a speed-up of the segmentation changed nothing; and its CPU time.

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/seg_fingerprint.py write before.json DATA_DIR[,DATA_DIR...] [--set ...]
    python scripts/seg_fingerprint.py compare before.json after.json

``write`` also prints the median CPU time of ``segment`` per frame (best of ``--repeat`` runs).
Scores are hashed to 1e-4: cv2.magnitude's result depends on its buffers' memory alignment in
the last bit, so two runs of one code version may differ there (masks do not).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stage_fingerprint import compare  # noqa: E402  (scripts/, this folder)

from threadrecon.app.bench import _with_overrides  # noqa: E402
from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.segmentation import segment  # noqa: E402


def _h(a: Any) -> str:
    a = np.ascontiguousarray(np.asarray(a))
    return hashlib.sha1(a.tobytes() + f"{a.dtype}{a.shape}".encode()).hexdigest()[:16]


def _write(args: argparse.Namespace) -> None:
    params = _with_overrides(resolve_preset(args.config), args.set).segment
    out: dict[str, Any] = {}
    cpu: list[float] = []
    with threadpool_limits(1):
        for root in args.data.split(","):
            for frame in discover(root):
                pair, _, _ = load_frame(frame)
                best = float("inf")
                for _ in range(args.repeat):
                    c0 = time.thread_time()
                    try:
                        lifted = segment(pair, params)
                        d = {
                            "method": lifted.method,
                            "P": _h(lifted.P_L) + _h(lifted.P_R),
                            "score": None  # masks given: no score
                            if lifted.score_L is None
                            else _h(np.round(lifted.score_L * 1e4))
                            + _h(np.round(lifted.score_R * 1e4)),
                            "px": int(lifted.P_L.sum() + lifted.P_R.sum()),
                        }
                    except ValueError as exc:
                        d = {"error": str(exc)}
                    best = min(best, 1000 * (time.thread_time() - c0))
                cpu.append(best)
                out[f"{root}:{frame.id}"] = d
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True))
    print(
        f"{len(out)} frames -> {args.out}; segment CPU ms median {np.median(cpu):.2f}, "
        f"mean {np.mean(cpu):.2f}, p90 {np.percentile(cpu, 90):.2f}"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write")
    w.add_argument("out")
    w.add_argument("data", help="dataset folders, comma-separated")
    w.add_argument("--config", default=None)
    w.add_argument("--set", action="append", default=[], metavar="STAGE.NAME=VALUE")
    w.add_argument("--repeat", type=int, default=3)
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args)
        return 0
    return compare(args)


if __name__ == "__main__":
    sys.exit(main())
