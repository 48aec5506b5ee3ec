"""Per-frame fingerprints of the segmentation alone (masks P_L, P_R, scores, method, or the error),
bit for bit, to show that a speed-up of the segmentation changed nothing; and its CPU time.

    # once per code version (PYTHONPATH selects the package), then compare:
    python scripts/seg_fingerprint.py write before.json DATA_DIR[,DATA_DIR...] [--set ...]
    python scripts/seg_fingerprint.py compare before.json after.json

``write --masks`` also keeps the masks (``before.masks.npz``, bit-packed); ``compare`` then
says how many pixels differ where the masks of a frame differ.

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

from stage_fingerprint import compare, parser  # noqa: E402  (scripts/, this folder)

from threadrecon.app.bench import with_overrides  # noqa: E402
from threadrecon.app.dataset import discover, load_frame  # noqa: E402
from threadrecon.app.presets import resolve_preset  # noqa: E402
from threadrecon.core.segmentation import segment  # noqa: E402


def _h(a: Any) -> str:
    a = np.ascontiguousarray(np.asarray(a))
    return hashlib.sha1(a.tobytes() + f"{a.dtype}{a.shape}".encode()).hexdigest()[:16]


def _write(args: argparse.Namespace) -> None:
    params = with_overrides(resolve_preset(args.config), args.set).segment
    out: dict[str, Any] = {}
    masks: dict[str, np.ndarray] = {}
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
                        if args.masks:
                            masks[f"{root}:{frame.id}"] = np.stack([lifted.P_L, lifted.P_R])
                    except ValueError as exc:
                        d = {"error": str(exc)}
                    best = min(best, 1000 * (time.thread_time() - c0))
                cpu.append(best)
                out[f"{root}:{frame.id}"] = d
    Path(args.out).write_text(json.dumps(out, indent=1, sort_keys=True))
    if args.masks:
        keys = sorted(masks)
        np.savez_compressed(
            _masks_path(args.out),
            keys=np.array(keys),
            shapes=np.array([masks[k].shape for k in keys]).reshape(-1, 3),
            **{f"m{i}": np.packbits(masks[k]) for i, k in enumerate(keys)},
        )
    print(
        f"{len(out)} frames -> {args.out}; segment CPU ms median {np.median(cpu):.2f}, "
        f"mean {np.mean(cpu):.2f}, p90 {np.percentile(cpu, 90):.2f}"
    )


def _masks_path(json_path: str) -> Path:
    return Path(json_path).with_suffix(".masks.npz")


def _load_masks(json_path: str) -> dict[str, np.ndarray] | None:
    path = _masks_path(json_path)
    if not path.exists():
        return None
    z = np.load(path)
    return {
        str(k): np.unpackbits(z[f"m{i}"], count=int(np.prod(shape))).reshape(shape).astype(bool)
        for i, (k, shape) in enumerate(zip(z["keys"], z["shapes"], strict=True))
    }


def _compare(args: argparse.Namespace) -> int:
    """The fields that differ (scripts/stage_fingerprint.py), then, where both runs kept their
    masks, the pixels that differ in each frame whose masks differ."""
    status = compare(args)
    a, b = _load_masks(args.before), _load_masks(args.after)
    if a is None or b is None:
        return status
    for k in sorted(set(a) & set(b)):
        if a[k].shape != b[k].shape:
            print(f"{k}: mask shapes {a[k].shape} vs {b[k].shape}")
        elif not np.array_equal(a[k], b[k]):
            only_a = (a[k] & ~b[k]).sum(axis=(1, 2)).tolist()
            only_b = (b[k] & ~a[k]).sum(axis=(1, 2)).tolist()
            print(f"{k}: pixels only before (L, R) {only_a}, only after {only_b}, "
                  f"of {a[k].sum(axis=(1, 2)).tolist()}")  # fmt: skip
    return status


def main() -> int:
    ap, w = parser(__doc__)
    w.add_argument("--repeat", type=int, default=3)
    w.add_argument("--masks", action="store_true", help="keep the masks (OUT.masks.npz)")
    args = ap.parse_args()
    if args.cmd == "write":
        _write(args)
        return 0
    return _compare(args)


if __name__ == "__main__":
    sys.exit(main())
