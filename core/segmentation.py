"""Input pair, segmentation and lifting, Eq. (1).

The paper leaves segmentation open ("the most modern technique may be used") and uses colour
thresholds: on its Blender frames greyscale values >= 200 are background. We estimate the
background level B of each image as the mode of its grey histogram and call a pixel thread when
it is darker than ``B - seg_delta``. With ``seg_delta = 6`` this reproduces the paper's ``< 200``
on the Blender frames (B = 206) and keeps every hand-segmented pixel of the real frames
(B = 255), with no per-set flag. Masks given by the user replace the thresholding.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from core.params import Params, param

LIFT_VALUE = 255.0  # Eq. (1): unsegmented pixels are set to 255


@dataclass(frozen=True)
class StereoPair:
    """A rectified stereo pair.

    ``left``, ``right``: (H, W) greyscale or (H, W, 3) RGB images, uint8.
    ``mask_left``, ``mask_right``: optional (H, W) bool thread masks (P_L, P_R).
    """

    left: np.ndarray
    right: np.ndarray
    mask_left: np.ndarray | None = None
    mask_right: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("left", "right"):
            a = getattr(self, name)
            if (
                not isinstance(a, np.ndarray)
                or a.ndim not in (2, 3)
                or (a.ndim == 3 and a.shape[2] not in (1, 3, 4))
            ):
                shape = getattr(a, "shape", type(a).__name__)
                raise ValueError(f"{name} image must be (H, W) or (H, W, 3), got {shape}")
            if a.shape[0] < 8 or a.shape[1] < 8:
                raise ValueError(f"{name} image is too small: {a.shape}")
        if self.left.shape[:2] != self.right.shape[:2]:
            raise ValueError(
                f"left and right images differ in size: {self.left.shape[:2]} vs {self.right.shape[:2]}"
            )
        if (self.mask_left is None) != (self.mask_right is None):
            raise ValueError("give both masks or neither")
        for name in ("mask_left", "mask_right"):
            m = getattr(self, name)
            if m is not None and m.shape[:2] != self.left.shape[:2]:
                raise ValueError(f"{name} must be {self.left.shape[:2]}, got {m.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.left.shape[0]), int(self.left.shape[1]))


def split_side_by_side(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a side-by-side composite (left half, right half) into two views."""
    if image.ndim not in (2, 3) or image.shape[1] % 2:
        raise ValueError(f"side-by-side image must have an even width, got shape {image.shape}")
    w = image.shape[1] // 2
    return image[:, :w], image[:, w:]


@dataclass(frozen=True)
class SegmentationParams(Params):
    seg_delta: float = param(
        6.0,
        lo=0,
        hi=255,
        unit="grey levels",
        symbol="delta",
        slider=(0, 60, 1),
        label="seg threshold δ",
    )
    """Grey levels below the background level B that count as thread."""
    background: float | None = param(None, lo=0, hi=255, unit="grey levels")
    """Fixed background level B (0-255); None estimates it per image (histogram mode)."""
    min_component_px: int = param(
        4, lo=0, hi=10000, unit="px", slider=(0, 100, 1), label="min component px"
    )
    """Connected thread components smaller than this (px) are dropped as specks."""
    lift_dilate_px: int = param(
        1, lo=0, hi=10, unit="px", slider=(0, 4, 1), label="lift dilation px"
    )
    """Lift (Eq. (1)) outside P dilated by this many px; 0 is the paper's exact Eq. (1).

    Deviation: a thread 1-3 px wide crosses the threshold at different pixels in the two views,
    and lifting those to 255 dominates E(d); keeping the true intensities 1 px around the thread
    raised reliable pixels by 10-60 % and halved the p90 depth error on the Blender frames."""


@dataclass(frozen=True)
class LiftedPair:
    """Eq. (1): ``I_L^lift``, ``I_R^lift`` as (H, W) float32, and the masks P_L, P_R (H, W) bool."""

    I_L: np.ndarray
    I_R: np.ndarray
    P_L: np.ndarray
    P_R: np.ndarray
    grey_L: np.ndarray
    grey_R: np.ndarray
    background: tuple[float, float]
    """Background level B of the left and right image (grey levels)."""


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 greyscale of an RGB or grey uint8 image."""
    if image.ndim == 2:
        return image.astype(np.float32)
    if image.shape[2] == 1:
        return image[:, :, 0].astype(np.float32)
    return cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2GRAY).astype(
        np.float32
    )


def segment(pair: StereoPair, p: SegmentationParams = SegmentationParams()) -> LiftedPair:
    """Segment (unless masks are given) and lift the pair, Eq. (1)."""
    if p.seg_delta < 0:
        raise ValueError(f"seg_delta must be >= 0, got {p.seg_delta}")
    grey_L, grey_R = to_grey(pair.left), to_grey(pair.right)
    bg = (_background_level(grey_L, p), _background_level(grey_R, p))
    if pair.mask_left is not None and pair.mask_right is not None:
        P_L, P_R = pair.mask_left.astype(bool), pair.mask_right.astype(bool)
    else:
        P_L = _drop_specks(grey_L < bg[0] - p.seg_delta, p.min_component_px)
        P_R = _drop_specks(grey_R < bg[1] - p.seg_delta, p.min_component_px)
    if not P_L.any():
        raise ValueError("empty segmentation: no thread pixel in the left image")
    if not P_R.any():
        raise ValueError("empty segmentation: no thread pixel in the right image")
    if p.lift_dilate_px < 0:
        raise ValueError(f"lift_dilate_px must be >= 0, got {p.lift_dilate_px}")
    I_L = _lift(grey_L, P_L, p.lift_dilate_px)
    I_R = _lift(grey_R, P_R, p.lift_dilate_px)
    return LiftedPair(
        I_L=I_L, I_R=I_R, P_L=P_L, P_R=P_R, grey_L=grey_L, grey_R=grey_R, background=bg
    )


def _lift(grey: np.ndarray, P: np.ndarray, dilate_px: int) -> np.ndarray:
    """Eq. (1): keep the image on P (dilated by ``dilate_px``), 255 elsewhere."""
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        P = cv2.dilate(P.astype(np.uint8), k).astype(bool)
    return np.where(P, grey, np.float32(LIFT_VALUE)).astype(np.float32)


def _background_level(grey: np.ndarray, p: SegmentationParams) -> float:
    if p.background is not None:
        return float(p.background)
    hist = cv2.calcHist([np.clip(grey, 0, 255).astype(np.uint8)], [0], None, [256], [0, 256])
    return float(np.argmax(hist))


def _drop_specks(mask: np.ndarray, min_px: int) -> np.ndarray:
    if min_px <= 1 or not mask.any():
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False
    return keep[labels]
