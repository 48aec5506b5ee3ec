"""A frame whose given thread masks hold the two errors the corrections fix: a vessel taken for
thread (a dark red, thread-wide stripe on the tissue, in both views and in both masks) and a
missed piece (the last third of the thread, absent from both masks). Shared by the server
and the browser tests of the corrections."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from rig_support import opencv_yaml
from support import far_spot

from threadrecon.core.synthetic import RenderParams, SyntheticParams, generate_frame

FRAME_ID = "case/vessel"
VESSEL_RGB = (120, 30, 35)  # darker and redder than the tissue, as the generator's vessels
VESSEL_DISPARITY = 25  # px: the stripe lies on the tissue, about the thread's depth


@dataclass(frozen=True)
class Case:
    root: Path
    frame_id: str
    vessel: dict[str, tuple[int, int]]
    """(x, y) of a pixel of the vessel stripe in each view."""
    missed: dict[str, tuple[int, int]]
    """(x, y) of a pixel of the missed thread piece in each view."""
    true_masks: dict[str, np.ndarray]
    """The generator's exact thread masks."""
    length_mm: float


def write_case(root: Path, seed: int = 11) -> Case:
    """Write the frame (side-by-side PNG, its mask, ground truth, calibration) under ``root``."""
    frame = generate_frame(
        SyntheticParams(render=RenderParams(background="tissue", distractors=0)), rng=seed
    )
    folder = root / FRAME_ID.split("/")[0]
    folder.mkdir(parents=True, exist_ok=True)
    left, right = frame.left.copy(), frame.right.copy()
    masks = {"left": frame.mask_left.copy(), "right": frame.mask_right.copy()}
    # the vessel: a stripe 2 px wide and 120 px long, away from the thread in both views
    both = masks["left"] | np.roll(masks["right"], VESSEL_DISPARITY, axis=1)
    x, y = far_spot(both, 140, margin=30)
    vessel = {}
    for view, img, shift in (("left", left, 0), ("right", right, -VESSEL_DISPARITY)):
        a, b = (x + shift, y), (x + shift + 120, y + 25)
        cv2.line(img, a, b, VESSEL_RGB, 2, cv2.LINE_AA)
        stripe = np.zeros(masks[view].shape, np.uint8)
        cv2.line(stripe, a, b, 1, 2)
        masks[view] |= stripe.astype(bool)
        vessel[view] = (x + shift + 60, y + 12)
    # the missed piece: the thread's last third (by arc length along the image x of one end)
    missed = {}
    for view, true in (("left", frame.mask_left), ("right", frame.mask_right)):
        ys, xs = np.nonzero(true)
        end = true & (np.arange(true.shape[1]) > xs.min() + 0.67 * (xs.max() - xs.min()))
        n, labels, stats, _ = cv2.connectedComponentsWithStats(end.astype(np.uint8))
        piece = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        masks[view] &= ~piece
        py, px = np.argwhere(piece)[len(np.argwhere(piece)) // 2]
        missed[view] = (int(px), int(py))
    png = np.hstack([left, right])
    cv2.imwrite(str(folder / "vessel.png"), cv2.cvtColor(png, cv2.COLOR_RGB2BGR))
    cv2.imwrite(
        str(folder / "vessel_mask.png"),
        np.hstack([masks["left"], masks["right"]]).astype(np.uint8) * 255,
    )
    np.save(folder / "vessel.npy", frame.truth.control_points)
    (folder / "calibration.yaml").write_text(opencv_yaml(frame.camera.calibration()))
    return Case(
        root, FRAME_ID, vessel, missed,
        {"left": frame.mask_left, "right": frame.mask_right}, frame.truth.length_mm,
    )  # fmt: skip
