"""The Python API: one call from a stereo pair and its calibration to the thread's centerline.

```python
from threadrecon import reconstruct

result = reconstruct("left.png", "right.png", "calibration.yaml")
if result.ok:
    print(result.points.shape, result.unit, result.frame)   # (400, 3) mm left
    print(result.grasp.point, result.grasp.tangent)          # where (and along what) to grasp
result.to_json()                                        # the CLI's JSON (result.schema.json)
```

Images are paths or arrays ((H, W, 3) RGB uint8 or (H, W) grey); the calibration is a path
(OpenCV FileStorage, Kalibr camchain, or a ROS camera_info with ``calib_right``) or a
:class:`threadrecon.core.calibration.StereoCalibration`. A raw pair (distortion, rotated cameras) is
undistorted and rectified first; the curve comes back in the left camera's own frame
(``frame="left"``, default) or in the left rectified frame (``frame="left_rectified"``).
Bad input raises ``ValueError``/``FileNotFoundError`` naming the problem; a reconstruction
that fails is returned with ``status == "failed"`` and its ``reasons``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from threadrecon.app.export import InputFile, polyline_ply, result_json
from threadrecon.app.io import load_calibration, read_image, read_mask
from threadrecon.app.presets import resolve_preset
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.pipeline import Pipeline, ReconParams, Reconstruction
from threadrecon.core.rectify import (
    FRAMES,
    Frame,
    Rectification,
    in_frame,
    rectification,
    rectify_pair,
)
from threadrecon.core.segmentation import StereoPair, split_side_by_side

Image = str | Path | np.ndarray


@dataclass(frozen=True)
class Grasp:
    """The check stage's grasp point in the result's frame: ``point`` (3,), ``tangent`` (3,)
    unit vector along the curve (start -> end), ``confidence`` in [0, 1], ``distance`` (arc
    length, calibration units) from the end taken as free, ``from_end`` ("start" or "end")."""

    point: np.ndarray
    tangent: np.ndarray
    confidence: float
    distance: float
    from_end: str


@dataclass(frozen=True)
class ThreadResult:
    """A reconstruction in ``frame`` and ``unit``.

    ``points``: (n, 3) dense centerline; ``control_points`` (m, 3), ``knots`` (m + degree + 1,),
    ``degree``: the B-spline over u in [0, 1]; ``length``: arc length. These are None when
    the pipeline produced no final spline (then ``reasons`` says why). ``reconstruction``: every
    stage's result (in the left rectified frame, on the rectified pair); ``rectification``:
    how the raw pair was rectified (``R1``: p_rect = R1 p_left; identity for a rectified pair).
    ``confidence``: (n,) per point in [0, 1]; ``grasp``: the most confident point at the
    configured distance from the free end (:class:`Grasp`); ``rating``: the automatic
    quality score on the paper's 1-5 scale, continuous; ``score``: its integer class (for a
    person's 1-5 ratings). These four are None when the check stage did not run (a failed
    stage).
    ``point_at(0.5)``: the point halfway along the curve.
    """

    status: str
    reasons: tuple[str, ...]
    frame: Frame
    unit: str
    points: np.ndarray | None
    control_points: np.ndarray | None
    knots: np.ndarray | None
    degree: int | None
    length: float | None
    confidence: np.ndarray | None
    grasp: Grasp | None
    score: int | None
    rating: float | None
    timings_ms: dict[str, float]
    params: ReconParams
    preset: str | None
    inputs: tuple[InputFile, ...]
    reconstruction: Reconstruction
    rectification: Rectification
    pair: StereoPair
    """The (rectified) pair the pipeline ran on."""

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def point_at(self, s: float) -> np.ndarray:
        """(3,) point at fraction ``s`` in [0, 1] of the arc length from the curve's start."""
        if self.points is None:
            raise ValueError(f"no curve: {'; '.join(self.reasons)}")
        if not 0.0 <= s <= 1.0:
            raise ValueError(f"s must be in [0, 1], got {s}")
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        target = s * cum[-1]
        return np.array([np.interp(target, cum, self.points[:, a]) for a in range(3)])

    def to_json(self) -> dict[str, Any]:
        """The JSON of ``docs/result.schema.json`` (the CLI's and the page's)."""
        return result_json(
            self.reconstruction, self.rectification, self.frame, self.preset, self.inputs
        )

    def to_ply(self) -> bytes:
        """The curve as a PLY polyline (vertices + edges) in ``frame``."""
        if self.points is None:
            raise ValueError(f"no curve: {'; '.join(self.reasons)}")
        return polyline_ply(self.points, self.unit, self.frame)


def reconstruct(
    left: Image,
    right: Image | None = None,
    calib: str | Path | StereoCalibration | None = None,
    *,
    stereo: Image | None = None,
    mask: Image | None = None,
    calib_right: str | Path | None = None,
    units: str | None = None,
    params: ReconParams | str | None = None,
    mask_left: Image | None = None,
    mask_right: Image | None = None,
    frame: Frame = "left",
) -> ThreadResult:
    """Reconstruct the thread of one stereo pair.

    ``left``, ``right``: the two views (paths or arrays); or ``stereo``: one side-by-side
    composite (then pass ``left=None``). ``calib``: calibration file or object; ``calib_right``:
    the right camera_info for a ROS pair; ``units``: the calibration's length unit when its
    file does not say. ``params``: a :class:`ReconParams`, a preset name or path, or None for
    the default preset. ``mask_left``/``mask_right``: optional thread masks (both or neither),
    or ``mask``: one side-by-side mask.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    if calib is None:
        raise ValueError("a calibration is needed (calib=path or StereoCalibration)")
    inputs: list[InputFile] = []
    if stereo is not None:
        if left is not None or right is not None:
            raise ValueError("give either stereo= or left and right, not both")
        L, R = split_side_by_side(_image(stereo, "stereo", inputs))
    else:
        if left is None or right is None:
            raise ValueError("need left and right images, or stereo=")
        L, R = _image(left, "left", inputs), _image(right, "right", inputs)
    mL = mR = None
    if mask is not None:
        if mask_left is not None or mask_right is not None:
            raise ValueError("give either mask= or mask_left and mask_right, not both")
        mL, mR = split_side_by_side(_mask(mask, "mask", inputs), "mask")
    elif (mask_left is None) != (mask_right is None):
        raise ValueError("give both masks or neither")
    if mask_left is not None and mask_right is not None:
        mL, mR = _mask(mask_left, "mask_left", inputs), _mask(mask_right, "mask_right", inputs)
    if isinstance(calib, StereoCalibration):
        if calib_right is not None:
            raise ValueError("calib_right goes with a calibration file, not an object")
        cal = calib
    else:
        cal = load_calibration(calib, unit=units, right=calib_right)
        inputs.append(InputFile.of_file("calibration", calib))
        if calib_right is not None:
            inputs.append(InputFile.of_file("calibration_right", calib_right))
    preset = params if isinstance(params, str) else None
    p = params if isinstance(params, ReconParams) else resolve_preset(params)
    if preset is None and params is None:
        preset = "default"
    rect = rectification(cal)
    pair = rectify_pair(StereoPair(L, R, mL, mR), rect)
    rec = Pipeline(pair, rect.calib).run(p)
    return _result(rec, rect, pair, frame, preset, tuple(inputs))


def _result(
    rec: Reconstruction,
    rect: Rectification,
    pair: StereoPair,
    frame: Frame,
    preset: str | None,
    inputs: Sequence[InputFile],
) -> ThreadResult:
    fields: dict[str, Any] = dict.fromkeys(
        (
            "points",
            "control_points",
            "knots",
            "degree",
            "length",
            "confidence",
            "grasp",
            "score",
            "rating",
        )
    )
    unit = rect.calib.unit
    if "camera" in rec.runs:
        cam = rec["camera"]
        fields.update(
            points=in_frame(cam.points, rect, frame),
            control_points=in_frame(cam.ctrl, rect, frame),
            knots=cam.knots,
            degree=cam.degree,
            length=cam.length,
        )
    if "check" in rec.runs:
        chk = rec["check"]
        fields.update(confidence=chk.confidence, score=chk.score, rating=chk.rating)
        if chk.grasp is not None:
            g = chk.grasp
            fields["grasp"] = Grasp(
                point=in_frame(g.point[None], rect, frame)[0],
                tangent=in_frame(g.tangent[None], rect, frame)[0],  # a rotation: no offset
                confidence=g.confidence,
                distance=g.distance,
                from_end=g.from_end,
            )
    return ThreadResult(
        status=rec.status,
        reasons=rec.reasons,
        frame=frame,
        unit=unit,
        timings_ms=dict(rec.timings_ms),
        params=rec.params,
        preset=preset,
        inputs=tuple(inputs),
        reconstruction=rec,
        rectification=rect,
        pair=pair,
        **fields,
    )


def _image(img: Image, role: str, inputs: list[InputFile]) -> np.ndarray:
    if isinstance(img, np.ndarray):
        if img.dtype != np.uint8:
            raise ValueError(f"{role} image must be uint8, got {img.dtype}")
        inputs.append(InputFile.of_array(role, img))
        return img
    inputs.append(InputFile.of_file(role, _existing(img, role)))
    return read_image(img)


def _mask(img: Image, role: str, inputs: list[InputFile]) -> np.ndarray:
    if isinstance(img, np.ndarray):
        if img.ndim != 2:
            raise ValueError(f"{role} must be (H, W), got {img.shape}")
        inputs.append(InputFile.of_array(role, img))
        return img.astype(bool) if img.dtype == bool else img > 127
    inputs.append(InputFile.of_file(role, _existing(img, role)))
    return read_mask(img)


def _existing(path: str | Path, role: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: {role} image file not found")
    return p
