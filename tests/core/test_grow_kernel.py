"""core/grow_kernel.py: the raw segmentation's mask growth gives the plain numpy/cv2
computation's mask bit for bit (the plain form is kept here as the reference)."""

import cv2
import numpy as np
import pytest

from threadrecon.core import segment_raw as sr
from threadrecon.core.segmentation import SegmentationParams
from threadrecon.core.synthetic import RenderParams, SyntheticParams, ThreadParams, generate_frame

_SQUARE3 = np.ones((3, 3), np.uint8)


def _plain_grow_mask(v: sr._View, core: np.ndarray) -> np.ndarray:
    """:func:`segment_raw._grow_mask` as numpy and cv2 steps, before it became one compiled
    pass: the reference the kernel must match bit for bit (its docstring says what it does)."""
    h, w = core.shape
    out = np.zeros(core.shape, bool)
    pts = cv2.findNonZero(core)
    if pts is None:
        return out
    x0, y0, bw, bh = cv2.boundingRect(pts)
    # The box: the core's bounding box grown by the band and by the 2 px the coverage test
    # looks at (zeros there, as in the full image), clipped to the image.
    m = sr._BAND_PX + 2
    r0, r1, c0, c1 = max(y0 - m, 0), min(y0 + bh + m, h), max(x0 - m, 0), min(x0 + bw + m, w)
    core_b = core[r0:r1, c0:c1]
    a = v.img if v.img.ndim == 3 else v.img[:, :, None]
    a = a[r0:r1, c0:c1, : v.bg_rgb.shape[2]]
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * sr._BAND_PX + 1, 2 * sr._BAND_PX + 1))
    band = cv2.dilate(core_b, k)
    rows, cols = sr._points(band)  # in the box
    bg = v.bg_rgb
    diff = a[rows, cols].astype(np.float32) - bg[sr._qi(rows + r0, bg.shape[0]),
                                                 sr._qi(cols + c0, bg.shape[1])]  # fmt: skip
    on_core = core_b[rows, cols] > 0
    body, glint = sr._body_contrast(diff, rows + r0, cols + c0, on_core, bg.shape[:2])
    # |T - B| is the largest body contrast of a core pixel within the band (the thread's axis
    # is there), net of a highlight (a core pixel is thread: no enclosure needed).
    c2 = np.square(np.maximum(body[0], 0.0))
    g = np.flatnonzero(glint)  # the pixels a highlight fit applies to (few)
    net2 = np.square(np.maximum(body[1][g], 0.0))
    dense = np.zeros(core_b.shape, np.float32)
    dense[rows[on_core], cols[on_core]] = c2[on_core]
    axis = on_core[g]
    dense[rows[g[axis]], cols[g[axis]]] = np.maximum(net2[axis], c2[g[axis]])
    box = np.ones((2 * sr._BAND_PX + 1, 2 * sr._BAND_PX + 1), np.uint8)
    peak = cv2.dilate(dense, box)[rows, cols]
    keep = (c2 >= 0.25 * peak) & (peak > 0)
    # Elsewhere a highlight lies inside the thread: only pixels enclosed by thread pixels (a
    # 3 x 3 closing of the mask) take their coverage net of one; beside the thread the same
    # fit would take the colour bleeding out of it (JPEG chroma) for thread.
    add = ~keep[g] & (net2 >= 0.25 * peak[g]) & (peak[g] > 0)
    if add.any():
        g, net2 = g[add], net2[add]
        dense = np.zeros(core_b.shape, np.uint8)
        dense[rows[keep], cols[keep]] = 1
        inside = cv2.morphologyEx(dense, cv2.MORPH_CLOSE, _SQUARE3)[rows[g], cols[g]] > 0
        g, net2 = g[inside], net2[inside]
        keep[g] = True
        c2[g] = net2
    # Coverage is conserved: a cross-section of two pixels (its outer neighbours below 0.5)
    # whose coverages sum to < sr._SHARED_PX holds less than that much thread (a 1-2 px thread
    # crossing from one pixel row or column to the next); coverage 0.5 takes the larger only.
    cov = np.zeros(core_b.shape, np.float32)
    cov[rows[keep], cols[keep]] = np.sqrt(c2[keep] / peak[keep])
    # Neighbours up to 2 px away by flat index into a copy padded by replicating the edge: the
    # box's own 2 px margin inside the image, the image's edge pixel outside it (clipping).
    cov = cv2.copyMakeBorder(cov, 2, 2, 2, 2, cv2.BORDER_REPLICATE).ravel()
    stride = core_b.shape[1] + 4
    at0 = (rows + 2) * stride + (cols + 2)
    c = cov[at0]
    for step in (stride, -stride, 1, -1):
        nb = cov[at0 + step]
        alone = (cov[at0 + 2 * step] < 0.5) & (cov[at0 - step] < 0.5)
        keep &= ~((nb > c) & (nb + c < sr._SHARED_PX) & alone)
    out[rows[keep] + r0, cols[keep] + c0] = True
    return out


def _view(img: np.ndarray, rng: np.random.Generator) -> sr._View:
    """A view holding what the growth reads: the image and a quarter-resolution background
    (its block means, smoothed, with noise: any background must do)."""
    a = img if img.ndim == 3 else img[:, :, None]
    h, w, c = a.shape
    bg = cv2.resize(a.astype(np.float32), (max(w // sr._Q, 1), max(h // sr._Q, 1)),
                    interpolation=cv2.INTER_AREA).reshape(max(h // sr._Q, 1), -1, c)  # fmt: skip
    bg = bg + rng.normal(0, 3, bg.shape).astype(np.float32)
    none = np.zeros(0)
    return sr._View(img, none, 1.0, none, none, none, none, none, none, bg, none)


@pytest.mark.parametrize("trial", range(24))
def test_grow_mask_equals_the_plain_computation_on_raw_frames(trial: int) -> None:
    """Frames of several kinds (dyes, highlights, distractors, JPEG, an instrument): the
    segmentation's own views and cores."""
    rng = np.random.default_rng([31, trial])
    render = RenderParams(
        background="tissue",
        thread_colour="random" if trial % 2 else None,
        specular=[0.08, 0.4, 0.8][trial % 3],
        noise_sigma=float(rng.uniform(0, 4)),
        blur_sigma=float(rng.uniform(0, 1)),
        distractors=int(trial % 4),
        instrument=trial % 5 == 0,
        jpeg_quality=[0, 80][trial % 2],
    )
    thread = ThreadParams(
        hairpin=trial % 6 == 1, crossing=trial % 6 == 2, leaves_image=trial % 7 == 3
    )
    frame = generate_frame(SyntheticParams(thread=thread, render=render), rng)
    p = SegmentationParams(method="raw")
    views = [sr._View.build(img, p) for img in (frame.left, frame.right)]
    found, _, _, _ = sr._select(views, p)
    if found is None:
        pytest.skip("no thread found in this frame")
    for v, core in zip(views, found, strict=True):
        assert np.array_equal(sr._grow_mask(v, core), _plain_grow_mask(v, core))


@pytest.mark.parametrize("trial", range(40))
def test_grow_mask_equals_the_plain_computation_on_random_cores(trial: int) -> None:
    """Random images and cores: thick and thin strokes, blobs, single pixels, cores at the
    image's edges, bright pixels inside strokes (highlights), grey, uint8 and float images."""
    rng = np.random.default_rng([32, trial])
    h, w = int(rng.integers(8, 90)), int(rng.integers(8, 90))
    c = 1 if trial % 5 == 4 else 3
    img = rng.normal(120, 25, (h, w, c)).clip(0, 255)
    core = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 5))):
        pts = rng.integers(0, [w, h], (int(rng.integers(2, 6)), 2)).astype(np.int32)
        thick = int(rng.integers(1, 4))
        cv2.polylines(core, [pts], False, 1, thick)
        colour = rng.uniform(0, 255, c)
        lines = np.zeros((h, w), np.uint8)
        cv2.polylines(lines, [pts], False, 1, thick + 2)
        img[lines > 0] = 0.6 * colour + 0.4 * img[lines > 0]
    if trial % 3 == 0:  # highlights: white pixels on the strokes
        img[(core > 0) & (rng.random((h, w)) < 0.2)] = 250.0
    if trial % 4 == 1:  # a few lone core pixels
        core[rng.integers(0, h, 5), rng.integers(0, w, 5)] = 1
    if trial % 7 == 6:
        core[:] = 0  # no core: nothing grows
    img = img.astype(np.float32 if trial % 2 else np.uint8)
    if trial % 8 == 2:  # RGB as loaded: a reversed view of BGR
        img = np.ascontiguousarray(img[:, :, ::-1])[:, :, ::-1]
    v = _view(img[:, :, 0] if c == 1 and trial % 10 == 4 else img, rng)
    assert np.array_equal(sr._grow_mask(v, core), _plain_grow_mask(v, core))
