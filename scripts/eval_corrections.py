"""How far a few clicks take the raw segmentation: a simulated user on frames with exact masks.

For every frame of a dataset folder whose ``*_mask.png`` is known, the masks are withheld and
the pair is segmented raw; then a simulated user clicks, in each view, the middle pixel of
every missed piece of the thread (a connected part of the exact mask with no segmented pixel
within 3 px: "add") and of every wrongly segmented piece (a connected part of P with no exact
thread pixel within 3 px: "remove"). Printed per frame and in total: the mask IoU against the
exact mask (thread pixels, both views) before and after, the clicks, the time of
``apply_corrections`` and the reconstruction's status and length error before and after.

    python scripts/eval_corrections.py DATA_DIR [--max-clicks N]

With ``--crafted START STOP`` it writes instead, for each seed, the test frame of
``tests/app/correction_support.write_case`` (a tissue frame whose given masks hold a drawn
vessel and miss the thread's last third) into DATA_DIR, and clicks as a user would: one
*remove* with both views on the vessel, one *add* per view on the missed piece.
"""

from __future__ import annotations

import argparse
import sys
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


def crafted(root: Path, start: int, stop: int) -> None:
    """The crafted frames of the tests, one per seed, and the user's three clicks."""
    tests = Path(__file__).resolve().parents[1] / "tests"
    sys.path[:0] = [str(tests), str(tests / "app")]
    from correction_support import write_case

    from threadrecon.app.library import FrameLibrary

    rows = []
    for seed in range(start, stop):
        case = write_case(root / f"seed{seed}", seed)
        lf = FrameLibrary(case.root).load(case.frame_id)
        pipe = Pipeline(lf.pair, lf.calib)
        rec0 = pipe.run()
        ops = (Correction("remove", "left", (case.vessel["left"],), stereo=True),) + tuple(
            Correction("add", v, (case.missed[v],)) for v in ("left", "right")
        )
        t0 = time.perf_counter()
        fixed = apply_corrections(rec0["segment"], ops, 1, (lf.pair.left, lf.pair.right))
        ms = 1000.0 * (time.perf_counter() - t0) / len(ops)
        rec1 = pipe.run(corrections=ops)
        truth = (case.true_masks["left"], case.true_masks["right"])
        seg = rec0["segment"]
        i0, i1 = _iou((seg.P_L, seg.P_R), truth), _iou((fixed.P_L, fixed.P_R), truth)
        m0, m1 = (evaluate_reconstruction(r, lf.calib, lf.ground_truth) for r in (rec0, rec1))
        good = [_good(r, m) for r, m in ((rec0, m0), (rec1, m1))]
        rows.append((i0, i1, *good, m1["e_S_mm"], ms))
        print(
            f"seed {seed}: IoU {i0:.3f} -> {i1:.3f}; {rec0.status} e_len "
            f"{m0['e_length_mm']:.1f} mm -> {rec1.status} e_len {m1['e_length_mm']:.1f} mm, "
            f"e_S {m1['e_S_mm']:.2f} mm; {ms:.1f} ms per click"
        )
    r = np.array(rows, float)
    print(
        f"{len(r)} frames: mean IoU {r[:, 0].mean():.3f} -> {r[:, 1].mean():.3f} (min "
        f"{r[:, 1].min():.3f}); good {int(r[:, 2].sum())} -> {int(r[:, 3].sum())}; median e_S "
        f"{np.median(r[:, 4]):.2f} mm; median {np.median(r[:, 5]):.1f} ms per click"
    )


def _good(rec: object, m: dict[str, float]) -> bool:
    """The issue's "good": status ok, |length error| <= 20 mm, max error <= 20 mm."""
    return rec.status == "ok" and abs(m["e_length_mm"]) <= 20 and m["e_S_max_mm"] <= 20  # type: ignore[attr-defined]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--max-clicks", type=int, default=6, help="per view and kind")
    ap.add_argument("--crafted", type=int, nargs=2, metavar=("START", "STOP"))
    args = ap.parse_args()
    if args.crafted:
        crafted(args.data_dir, *args.crafted)
        return
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
        good = [_good(r, m) for r, m in ((rec0, m0), (rec1, m1))]
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
