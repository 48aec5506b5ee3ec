"""How far a few clicks take the raw segmentation: a simulated user on frames with exact masks.

For every frame of a dataset folder whose ``*_mask.png`` is known, the masks are withheld and
the pair is segmented raw; then a simulated user clicks, in each view, the middle pixel of
every missed piece of the thread (a connected part of the exact mask with no segmented pixel
within 3 px: "add") and of every wrongly segmented piece (a connected part of P with no exact
thread pixel within 3 px: "remove"). Printed per frame and in total: the mask IoU against the
exact mask (thread pixels, both views) before and after, the clicks, the time of
``apply_corrections`` and the reconstruction's status and length error before and after.

    python scripts/eval_corrections.py DATA_DIR [--max-clicks N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from threadrecon.app.dataset import discover, evaluate_reconstruction, load_frame
from threadrecon.core.corrections import Correction, apply_corrections
from threadrecon.core.pipeline import Pipeline
from threadrecon.core.segmentation import StereoPair

NEAR_PX = 3  # a piece is matched when the other mask has a pixel this close


def _pieces_away(mask: np.ndarray, other: np.ndarray) -> list[tuple[int, int]]:
    """(x, y) of the middle pixel of each connected piece of ``mask`` with no ``other`` pixel
    within NEAR_PX."""
    near = cv2.dilate(other.astype(np.uint8), np.ones((2 * NEAR_PX + 1,) * 2, np.uint8)) > 0
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    out = []
    for k in range(1, n):
        piece = labels == k
        if (piece & near).any() or piece.sum() < 10:
            continue
        ys, xs = np.nonzero(piece)
        i = len(ys) // 2
        out.append((int(xs[i]), int(ys[i])))
    return out


def _iou(P: tuple[np.ndarray, np.ndarray], T: tuple[np.ndarray, np.ndarray]) -> float:
    inter = sum(int((p & t).sum()) for p, t in zip(P, T, strict=True))
    union = sum(int((p | t).sum()) for p, t in zip(P, T, strict=True))
    return inter / max(union, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--max-clicks", type=int, default=6, help="per view and kind")
    args = ap.parse_args()
    totals = {"frames": 0, "iou0": [], "iou1": [], "clicks": 0, "ms": [], "ok0": 0, "ok1": 0}
    for frame in discover(args.data_dir):
        if frame.mask is None and frame.mask_left is None:
            continue
        given, calib, gt = load_frame(frame)
        truth = (given.mask_left, given.mask_right)
        pair = StereoPair(given.left, given.right)
        pipe = Pipeline(pair, calib)
        rec0 = pipe.run()
        if "segment" not in rec0.runs:
            print(f"{frame.id}: segment failed: {rec0.error}")
            continue
        seg = rec0["segment"]
        ops = []
        for view, P, T in (("left", seg.P_L, truth[0]), ("right", seg.P_R, truth[1])):
            ops += [Correction("add", view, (xy,)) for xy in _pieces_away(T, P)[: args.max_clicks]]
            ops += [
                Correction("remove", view, (xy,)) for xy in _pieces_away(P, T)[: args.max_clicks]
            ]
        t0 = time.perf_counter()
        fixed = apply_corrections(seg, tuple(ops), 1, (pair.left, pair.right))
        ms = 1000.0 * (time.perf_counter() - t0)
        rec1 = pipe.run(corrections=tuple(ops)) if ops else rec0
        m0 = evaluate_reconstruction(rec0, calib, gt)
        m1 = evaluate_reconstruction(rec1, calib, gt)
        i0, i1 = _iou((seg.P_L, seg.P_R), truth), _iou((fixed.P_L, fixed.P_R), truth)
        good = [
            r.status == "ok" and abs(m["e_length_mm"]) <= 20 and m["e_S_max_mm"] <= 20
            for r, m in ((rec0, m0), (rec1, m1))
        ]
        print(
            f"{frame.id}: IoU {i0:.3f} -> {i1:.3f}, {len(ops)} clicks "
            f"({sum(o.op == 'add' for o in ops)} add), {ms:.0f} ms; "
            f"{rec0.status} e_len {m0['e_length_mm']:.1f} mm -> {rec1.status} "
            f"e_len {m1['e_length_mm']:.1f} mm"
        )
        totals["frames"] += 1
        totals["iou0"].append(i0)
        totals["iou1"].append(i1)
        totals["clicks"] += len(ops)
        totals["ms"].append(ms / max(len(ops), 1))
        totals["ok0"] += good[0]
        totals["ok1"] += good[1]
    n = totals["frames"]
    if n:
        print(
            f"{n} frames: mean IoU {np.mean(totals['iou0']):.3f} -> {np.mean(totals['iou1']):.3f},"
            f" min {np.min(totals['iou0']):.3f} -> {np.min(totals['iou1']):.3f}; "
            f"{totals['clicks']} clicks; median {np.median(totals['ms']):.1f} ms per click; "
            f"good frames {totals['ok0']} -> {totals['ok1']}"
        )


if __name__ == "__main__":
    main()
