"""Synthetic rectified stereo frames of a suture thread with exact 3D ground truth.

A random smooth thread is drawn as a clamped cubic B-spline, placed in front of a rectified
stereo camera and rendered as an anti-aliased, shaded tube into both views. The ground truth
follows the paper dataset's convention (README of ``simulated/``): control points (n, 3) of a
degree-3 B-spline with knots ``[0, 0, 0] + linspace(0, 1, n - 2) + [1, 1, 1]``, here in mm.

Conventions, used throughout this module:

* Points ``p_left`` are in the left camera frame, OpenCV axes (x right, y down, z forward), mm.
* The right camera is the left camera translated by ``+baseline`` along x, so a point projects
  to the same row in both views with disparity ``x_left - x_right = fx * baseline / Z``.
* Image points are ``(x, y) = (col, row)`` in px; integer coordinates are pixel *centres*
  (OpenCV convention).
* Images are RGB ``uint8`` (H, W, 3), **not** BGR: convert before ``cv2.imwrite``.

Rendering is exact in the sense the tests check: every pixel's coverage is a function of its
exact distance to the projected centreline (a dense polyline with chord error below 0.01 px),
and the tube's shading is symmetric about that centreline, so the darkness centroid of a cut
across the thread lies on the projected ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final, Literal

import cv2
import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from threadrecon.core.calibration import StereoCalibration, make_calibration

DEGREE: Final = 3  # cubic B-spline, as in the paper dataset's ground truth
_ARC_TABLE_SIZE: Final = 4096  # parameter samples for arc-length tables (relative error ~1e-7)
_MIN_CLEARANCE_STEP_MM: Final = 0.01  # a thread thinner than 0.02 mm (a thread-free test
# frame) is checked at 0.01 mm steps, not at half its diameter (1e-6 mm took minutes)
_CENTERLINE_STEP_MM: Final = 0.25  # step of the ground-truth centreline along the arc
_RENDER_STEP_PX: Final = 0.4  # max image step of the rendered polyline; chord error < 0.01 px
_MAX_ATTEMPTS: Final = 300  # shape/placement retries before settings are declared impossible
_EXIT_PX: Final = 20.0  # with leaves_image, the free end lies this far beyond the border
_EDGE_SHADE: Final = 0.75  # tube brightness at its silhouette relative to its axis (cylinder)
_HIGHLIGHT_HALF_WIDTH: Final = 0.3  # specular stripe half-width, fraction of the tube radius
_SPIRAL_TURNS: Final = (1.5, 3.0)  # turns of a spiral coil (issue 12)
_SPIRAL_GAP_MM: Final = (2.0, 6.0)  # 3D distance between neighbouring turns, mm
_SPIRAL_TILT_DEG: Final = 40.0  # max angle between the coil's axis and the view direction
_SPIRAL_CTRL_PER_TURN: Final = 8  # control points per turn of the coil
# A uniform cubic B-spline through 8 points per turn of a circle has (4 + 2 cos(2 pi / 8)) / 6
# of its radius: the control radii are divided by this so that the curve's gap is the drawn one.
_SPIRAL_SHRINK: Final = (4.0 + 2.0 * math.cos(2.0 * math.pi / _SPIRAL_CTRL_PER_TURN)) / 6.0
_MIN_CROSSING_SIN: Final = math.sin(math.radians(25.0))  # crossings must not be grazing

Background = Literal["flat", "tissue"]
ThreadColour = Literal["violet", "blue", "green", "black", "white", "red", "random"]
THREAD_COLOURS: Final = {
    "violet": (75.0, 55.0, 105.0),  # braided polyglactin (Vicryl)
    "blue": (45.0, 70.0, 150.0),  # polypropylene (Prolene)
    "green": (45.0, 120.0, 80.0),  # dyed polyester
    "black": (35.0, 33.0, 38.0),  # silk, nylon
    "white": (225.0, 220.0, 205.0),  # undyed
    "red": (165.0, 35.0, 45.0),  # dyed, close to a vessel's hue
}  # thread colour on its axis, RGB


@dataclass(frozen=True)
class StereoCamera:
    """Rectified pinhole stereo pair; the right camera sits at ``+baseline`` on the x axis."""

    fx: float = 890.0  # focal length, px (fx = fy)
    cx: float = 320.0  # principal point, column, px
    cy: float = 240.0  # principal point, row, px
    baseline: float = 5.0  # distance between the camera centres along x, mm
    width: int = 640  # image width, px
    height: int = 480  # image height, px

    def __post_init__(self) -> None:
        if not self.fx > 0:
            raise ValueError(f"camera.fx must be > 0, got {self.fx}")
        if not self.baseline > 0:
            raise ValueError(f"camera.baseline must be > 0, got {self.baseline}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"camera.width/height must be >= 16, got {self.width}x{self.height}")

    @property
    def fy(self) -> float:
        """Focal length along y, px (equal to ``fx``)."""
        return self.fx

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix, shared by both views."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fx, self.cy], [0.0, 0.0, 1.0]])

    def calibration(self) -> StereoCalibration:
        """This rectified rig as a :class:`StereoCalibration` (mm; OpenCV's T = -baseline x)."""
        return make_calibration(
            K1=self.K,
            D1=np.zeros(5),
            K2=self.K,
            D2=np.zeros(5),
            R=np.eye(3),
            T=np.array([-self.baseline, 0.0, 0.0]),
            image_size=(self.height, self.width),
            unit="mm",
        )

    def disparity(self, z: np.ndarray | float) -> np.ndarray:
        """Disparity ``x_left - x_right`` in px of points at depth ``z`` (mm)."""
        return self.fx * self.baseline / np.asarray(z, dtype=float)

    def project(self, p_left: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) points, left camera frame, mm -> ((N, 2) left, (N, 2) right) (x, y) px."""
        p = np.asarray(p_left, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"p_left must be (N, 3), got {p.shape}")
        z = p[:, 2]
        uv_left = np.stack([self.fx * p[:, 0] / z + self.cx, self.fx * p[:, 1] / z + self.cy], 1)
        uv_right = uv_left - np.stack([self.disparity(z), np.zeros_like(z)], 1)
        return uv_left, uv_right


@dataclass(frozen=True)
class ThreadParams:
    """Random thread shape and placement."""

    length_mm: tuple[float, float] = (60.0, 140.0)  # 3D arc length range, mm
    depth_mm: tuple[float, float] = (70.0, 150.0)  # allowed Z range of the whole centreline, mm
    n_control: tuple[int, int] = (7, 11)  # number of control points n, inclusive range
    curliness: float = 0.7  # std of the heading change between control legs, rad
    diameter_mm: float = 0.5  # tube diameter, mm (fx * d / Z = 3-6.4 px at the default depths)
    crossing: bool = False  # the thread crosses itself in the left image at least once
    leaves_image: bool = False  # one end leaves both images; the rest keeps margin_px
    hairpin: bool = False  # a tight U-turn: two strands side by side, a few px apart, not touching
    spiral: bool = False  # a coil of 1.5-3 turns, 2-6 mm apart, axis near the view direction;
    # its control points are 8 per turn plus a tail (n_control does not apply)
    margin_px: float = 10.0  # min distance of the projected centreline to the image border, px

    def __post_init__(self) -> None:
        _check_range("thread.length_mm", self.length_mm)
        _check_range("thread.depth_mm", self.depth_mm)
        _check_range("thread.n_control", self.n_control)
        if any(int(v) != v for v in self.n_control) or self.n_control[0] < DEGREE + 1:
            raise ValueError(
                f"thread.n_control must be integers >= {DEGREE + 1}, got {self.n_control}"
            )
        if self.hairpin and self.crossing:
            raise ValueError("thread.hairpin and thread.crossing cannot both be set")
        if self.spiral and (self.hairpin or self.crossing):
            raise ValueError(
                "thread.spiral cannot be combined with thread.hairpin or thread.crossing"
            )
        if self.crossing and self.n_control[1] < 7:
            raise ValueError(
                f"thread.n_control max must be >= 7 to make a crossing, got {self.n_control}"
            )
        if not (np.isfinite(self.curliness) and self.curliness >= 0):
            raise ValueError(f"thread.curliness must be >= 0, got {self.curliness}")
        if not (np.isfinite(self.diameter_mm) and self.diameter_mm > 0):
            raise ValueError(f"thread.diameter_mm must be > 0, got {self.diameter_mm}")
        if not (np.isfinite(self.margin_px) and self.margin_px >= 0):
            raise ValueError(f"thread.margin_px must be >= 0, got {self.margin_px}")


@dataclass(frozen=True)
class RenderParams:
    """Appearance of the rendered pair."""

    background: Background = "flat"  # "flat" light grey (paper's Blender frames) or "tissue"
    background_level: float = 205.0  # grey level of the flat background, 0-255
    thread_rgb: tuple[float, float, float] | None = None  # tube colour on its axis; None: default
    specular: float = 0.08  # peak of the highlight stripe on the tube axis, fraction of 255
    noise_sigma: float = 0.0  # std of additive Gaussian pixel noise, grey levels
    blur_sigma: float = 0.0  # std of the Gaussian blur (optics), px
    occlusion: bool = False  # an instrument shaft hides part of the thread
    thread_colour: ThreadColour | None = None  # a named dye (overrides thread_rgb); "random"
    distractors: int = 0  # thread-wide dark vessels and light fibres drawn on the tissue
    instrument: bool = False  # a grasper (shaft and open jaws) somewhere in view; may occlude
    lighting: float = 0.0  # uneven light (vignetting + gradient): the darkest spot loses this
    jpeg_quality: int = 0  # JPEG round trip of both views at this quality (1-100); 0: none

    def __post_init__(self) -> None:
        if self.thread_colour is not None and self.thread_colour not in (
            *THREAD_COLOURS,
            "random",
        ):
            raise ValueError(
                f"render.thread_colour must be one of {', '.join(THREAD_COLOURS)} or 'random', "
                f"got {self.thread_colour!r}"
            )
        if not (isinstance(self.distractors, int) and 0 <= self.distractors <= 100):
            raise ValueError(f"render.distractors must be in 0..100, got {self.distractors}")
        if self.distractors and self.background != "tissue":
            raise ValueError("render.distractors needs render.background 'tissue'")
        if not (np.isfinite(self.lighting) and 0 <= self.lighting <= 0.8):
            raise ValueError(f"render.lighting must be in [0, 0.8], got {self.lighting}")
        if not (isinstance(self.jpeg_quality, int) and 0 <= self.jpeg_quality <= 100):
            raise ValueError(f"render.jpeg_quality must be in 0..100, got {self.jpeg_quality}")
        if self.background not in ("flat", "tissue"):
            raise ValueError(
                f"render.background must be 'flat' or 'tissue', got {self.background!r}"
            )
        if not 0 <= self.background_level <= 255:
            raise ValueError(
                f"render.background_level must be in [0, 255], got {self.background_level}"
            )
        if self.thread_rgb is not None and (
            len(self.thread_rgb) != 3 or not all(0 <= c <= 255 for c in self.thread_rgb)
        ):
            raise ValueError(
                f"render.thread_rgb must be 3 values in [0, 255], got {self.thread_rgb}"
            )
        if not 0 <= self.specular <= 1:
            raise ValueError(f"render.specular must be in [0, 1], got {self.specular}")
        if not (np.isfinite(self.noise_sigma) and self.noise_sigma >= 0):
            raise ValueError(f"render.noise_sigma must be >= 0, got {self.noise_sigma}")
        if not (np.isfinite(self.blur_sigma) and self.blur_sigma >= 0):
            raise ValueError(f"render.blur_sigma must be >= 0, got {self.blur_sigma}")


@dataclass(frozen=True)
class SyntheticParams:
    """Everything that defines a synthetic frame, apart from the random seed."""

    camera: StereoCamera = field(default_factory=StereoCamera)
    thread: ThreadParams = field(default_factory=ThreadParams)
    render: RenderParams = field(default_factory=RenderParams)


@dataclass(frozen=True)
class ThreadTruth:
    """Ground-truth centreline, left camera frame, mm."""

    control_points: np.ndarray  # (n, 3) float64 B-spline control points, mm
    knots: np.ndarray  # (n + 4,) float64: [0, 0, 0] + linspace(0, 1, n - 2) + [1, 1, 1]
    degree: int  # spline degree, 3
    centerline: np.ndarray  # (M, 3) float64 curve points, uniform in arc length (0.25 mm), mm
    length_mm: float  # 3D arc length of the curve, mm


@dataclass(frozen=True)
class SyntheticFrame:
    """A rendered rectified pair with its ground truth."""

    left: np.ndarray  # (H, W, 3) uint8 RGB left view
    right: np.ndarray  # (H, W, 3) uint8 RGB right view
    mask_left: np.ndarray  # (H, W) bool, visible thread coverage >= 0.5 (occluder removed)
    mask_right: np.ndarray  # (H, W) bool, same for the right view
    truth: ThreadTruth
    camera: StereoCamera


def thread_knots(n: int) -> np.ndarray:
    """Clamped cubic knot vector of the paper dataset for ``n`` control points, (n + 4,)."""
    if n < DEGREE + 1:
        raise ValueError(f"need at least {DEGREE + 1} control points, got {n}")
    return np.concatenate([np.zeros(DEGREE), np.linspace(0.0, 1.0, n - 2), np.ones(DEGREE)])


def generate_frame(
    params: SyntheticParams | None = None, rng: np.random.Generator | int | None = None
) -> SyntheticFrame:
    """Draw a random thread and render it into a rectified stereo pair (RGB, not BGR).

    Deterministic for a given ``params`` and integer seed. Random draws happen in a fixed order
    (shape, background, occluder, noise), so switching ``occlusion`` or ``noise_sigma`` keeps
    the same thread and background for the same seed.

    Raises ``ValueError`` naming the setting when the thread cannot be placed (e.g. too long
    for the view at the given depth range).
    """
    p = params if params is not None else SyntheticParams()
    rng = np.random.default_rng(rng)
    cam, tp, rp = p.camera, p.thread, p.render
    _check_view(cam, tp)
    ctrl = _random_thread(cam, tp, rng)
    truth = _make_truth(ctrl)
    left, right, mask_left, mask_right = _render_pair(ctrl, cam, tp.diameter_mm, rp, rng)
    return SyntheticFrame(left, right, mask_left, mask_right, truth, cam)


# ----------------------------------------------------------------------------------------------
# Validation


def _check_range(name: str, r: tuple[float, float]) -> None:
    if len(r) != 2 or not all(np.isfinite(v) for v in r):
        raise ValueError(f"{name} must be a finite (min, max) pair, got {r!r}")
    if r[0] <= 0:
        raise ValueError(f"{name} must be > 0, got {r!r}")
    if r[0] > r[1]:
        raise ValueError(f"{name}: min > max in {r!r}")


def _check_view(cam: StereoCamera, tp: ThreadParams) -> None:
    """Reject settings where not even a point fits, or the thread is far too long for the view."""
    z_far = tp.depth_mm[1]
    usable_w = cam.width - 1 - 2 * tp.margin_px - cam.disparity(z_far)
    usable_h = cam.height - 1 - 2 * tp.margin_px
    if usable_w <= 0 or usable_h <= 0:
        raise ValueError(
            f"thread.margin_px={tp.margin_px} leaves no room in a {cam.width}x{cam.height} view "
            f"at thread.depth_mm={tp.depth_mm}"
        )
    # A thread longer than ~8 view diagonals would need an implausibly tight coil.
    diag_mm = math.hypot(float(usable_w), usable_h) * z_far / cam.fx
    if tp.length_mm[0] > 8 * diag_mm and not tp.leaves_image:
        raise ValueError(
            f"thread.length_mm={tp.length_mm} cannot fit the view at thread.depth_mm="
            f"{tp.depth_mm} (view diagonal {diag_mm:.0f} mm at the far depth)"
        )


# ----------------------------------------------------------------------------------------------
# Shape


def _spline(ctrl: np.ndarray) -> BSpline:
    return BSpline(thread_knots(len(ctrl)), ctrl, DEGREE)


def _arc_table(ctrl: np.ndarray) -> tuple[BSpline, np.ndarray, np.ndarray]:
    """Spline, parameter grid u and cumulative arc length s(u) in mm."""
    spl = _spline(ctrl)
    u = np.linspace(0.0, 1.0, _ARC_TABLE_SIZE)
    pts = spl(u)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    return spl, u, s


def _sample_arc(ctrl: np.ndarray, m: int) -> np.ndarray:
    """(m, 3) curve points uniform in 3D arc length."""
    spl, u, s = _arc_table(ctrl)
    return spl(np.interp(np.linspace(0.0, s[-1], m), s, u))


def _arc_length(ctrl: np.ndarray) -> float:
    return float(_arc_table(ctrl)[2][-1])


def _random_polygon(
    n: int, curliness: float, loop: bool, rng: np.random.Generator, hairpin: bool = False
) -> np.ndarray:
    """Control polygon (n, 3) of a random walk with smoothly varying heading and elevation."""
    legs = n - 1
    dtheta = rng.normal(0.0, curliness, legs)
    dphi = rng.normal(0.0, 0.2, legs)
    step = None
    if hairpin:  # a U-turn over two short legs, then the walk runs back nearly parallel
        start = int(rng.integers(1, legs - 3))
        sign = rng.choice([-1.0, 1.0])
        dtheta[start : start + 2] = sign * 0.5 * math.pi + rng.normal(0.0, 0.05, 2)
        dtheta[start + 2 :] *= 0.3
        dtheta[:start] *= 0.3
        dphi[start - 1 : start + 3] *= 0.3
        step = rng.uniform(0.6, 1.4, legs)[:, None]
        step[start] *= rng.uniform(0.08, 0.2)  # the bend leg sets the strands' separation
    if loop:
        k = 5  # legs that wind one loop; 5 legs of ~90 deg overshoot a full turn
        start = int(rng.integers(0, legs - k + 1))
        dtheta[start : start + k] = rng.choice([-1.0, 1.0]) * 2.5 * math.pi / k + rng.normal(
            0.0, 0.1, k
        )
        dphi[start : start + k] += rng.choice([-1.0, 1.0]) * 0.12  # helix: branches part in depth
    theta = rng.uniform(0.0, 2 * math.pi) + np.cumsum(dtheta)
    phi = np.clip(np.cumsum(dphi), -0.6, 0.6)
    if step is None:
        step = rng.uniform(0.6, 1.4, legs)[:, None]
    dirs = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)], 1)
    return np.vstack([np.zeros(3), np.cumsum(step * dirs, axis=0)])


def _random_spiral(length: float, curliness: float, rng: np.random.Generator) -> np.ndarray | None:
    """Control polygon (n, 3) of a conical coil of ``length`` mm (+- 15 %) with a short tail.

    The coil winds 1.5-3 turns about an axis within ``_SPIRAL_TILT_DEG`` of the view direction
    (+Z); neighbouring turns lie 2-6 mm apart in 3D, split between a radial step (the turns
    nest in the image, and at the top and bottom of each turn run along the image rows, a few
    px above each other: the epipolar lines) and an axial step (they part in depth). The inner
    end is free inside the coil; from the outer end the thread leaves along the tangent with
    a random walk of 1-3 legs (heading std ``curliness`` / 2). Returns None when the drawn
    turns and gap cannot make the length with an inner radius of at least the gap.
    """
    turns = rng.uniform(*_SPIRAL_TURNS)
    gap = rng.uniform(*_SPIRAL_GAP_MM)
    axial = gap * rng.uniform(0.0, 0.6)  # share of the gap along the axis (a helix)
    radial = math.sqrt(gap * gap - axial * axial)
    tail_legs = int(rng.integers(1, 4))
    coil = length * rng.uniform(0.75, 0.9)  # the rest of the length is the tail
    # coil length ~ 2 pi T (r0 + radial T / 2) for a flat spiral (axial steps add little)
    r0 = coil / (2.0 * math.pi * turns) - 0.5 * radial * turns
    if r0 < gap:
        return None
    k = int(math.ceil(turns * _SPIRAL_CTRL_PER_TURN))
    theta = np.linspace(0.0, 2.0 * math.pi * turns, k + 1)
    sign = rng.choice([-1.0, 1.0])  # winding sense
    r = (r0 + radial * theta / (2.0 * math.pi)) / _SPIRAL_SHRINK
    coil_pts = np.stack(
        [r * np.cos(sign * theta), r * np.sin(sign * theta), axial * theta / (2.0 * math.pi)], 1
    )
    # tail: continue along the last leg, legs as long as the coil's outer legs
    step = float(np.linalg.norm(coil_pts[-1] - coil_pts[-2]))
    heading = math.atan2(*(coil_pts[-1, 1::-1] - coil_pts[-2, 1::-1]))
    tail = [coil_pts[-1]]
    for _ in range(tail_legs):
        heading += rng.normal(0.0, 0.5 * curliness)
        tail.append(tail[-1] + step * np.array([math.cos(heading), math.sin(heading), 0.0]))
    ctrl = np.vstack([coil_pts, np.array(tail[1:])])
    # tilt the axis away from +Z by up to _SPIRAL_TILT_DEG about a random in-plane axis
    tilt = math.radians(rng.uniform(0.0, _SPIRAL_TILT_DEG))
    a = rng.uniform(0.0, 2.0 * math.pi)
    u = np.array([math.cos(a), math.sin(a), 0.0])
    ux = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    rot = np.eye(3) + math.sin(tilt) * ux + (1.0 - math.cos(tilt)) * ux @ ux  # Rodrigues
    ctrl = ctrl @ rot.T
    if rng.uniform() < 0.5:  # the free inner end first or last along the curve
        ctrl = ctrl[::-1]
    return np.ascontiguousarray(ctrl)


def _fit_length_and_depth(ctrl: np.ndarray, length: float, span: float) -> np.ndarray | None:
    """Scale to arc length ``length`` (mm) with Z extent <= ``span`` (mm), squashing Z if needed."""
    ctrl = ctrl.copy()
    for _ in range(12):
        c = ctrl.mean(axis=0)
        ctrl = c + (ctrl - c) * (length / _arc_length(ctrl))
        z = _sample_arc(ctrl, 256)[:, 2]
        extent = float(np.ptp(z))
        if extent <= 0.95 * span + 1e-9:
            return ctrl
        zc = z.mean()
        ctrl[:, 2] = zc + (ctrl[:, 2] - zc) * (0.9 * span / extent)
    return None


def _rotate_z(pts: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (pts - centre) @ rot.T + centre


def _place(
    ctrl: np.ndarray, cam: StereoCamera, tp: ThreadParams, rng: np.random.Generator
) -> np.ndarray | None:
    """Rotate about the optical axis and translate so that the curve meets the view constraints.

    With Z shifted by ``tz``, "x_left within bounds" is linear in ``tx``: the feasible
    translations are an interval intersection, solved exactly for a set of ``tz`` candidates.
    """
    k = 240
    pts = _sample_arc(ctrl, k)
    frac = np.linspace(0.0, 1.0, k)
    centre = pts.mean(axis=0)
    m, f, b = tp.margin_px, cam.fx, cam.baseline
    if tp.leaves_image:
        end = int(rng.integers(2))  # 0: the start leaves, 1: the far end leaves
        side = int(rng.integers(4))  # 0: +x, 1: -x, 2: +y, 3: -y
        free = rng.uniform(0.1, 0.3)  # arc fraction allowed outside the margin
        keep = frac <= 1 - free if end else frac >= free
        e = pts[-1 if end else 0] - centre
        target = (0.0, math.pi, 0.5 * math.pi, -0.5 * math.pi)[side]
        angles = [target - math.atan2(e[1], e[0]) + rng.normal(0.0, 0.3) for _ in range(3)]
    else:
        keep = np.ones(k, dtype=bool)
        xy = pts[:, :2] - centre[:2]
        evals, evecs = np.linalg.eigh(xy.T @ xy)
        major = evecs[:, np.argmax(evals)]
        aligned = -math.atan2(major[1], major[0])  # major axis along the wide image axis
        angles = [rng.uniform(0.0, 2 * math.pi), aligned, aligned + rng.normal(0.0, 0.2)]
    for angle in angles:
        p = _rotate_z(pts, angle, centre)
        z_lo, z_hi = tp.depth_mm[0] - p[:, 2].min(), tp.depth_mm[1] - p[:, 2].max()
        if z_lo > z_hi + 1e-9:
            return None
        tz = np.concatenate([rng.uniform(z_lo, z_hi, 11), [z_hi]])[:, None]  # deepest view last
        z = p[None, :, 2] + tz  # (T, k)
        x_lo = (m - cam.cx) * z / f + b - p[None, :, 0]
        x_hi = (cam.width - 1 - m - cam.cx) * z / f - p[None, :, 0]
        y_lo = (m - cam.cy) * z / f - p[None, :, 1]
        y_hi = (cam.height - 1 - m - cam.cy) * z / f - p[None, :, 1]
        tx_lo, tx_hi = x_lo[:, keep].max(1), x_hi[:, keep].min(1)
        ty_lo, ty_hi = y_lo[:, keep].max(1), y_hi[:, keep].min(1)
        if tp.leaves_image:
            i = -1 if end else 0
            ze, xe, ye = z[:, i], p[i, 0], p[i, 1]
            if side == 0:
                tx_lo = np.maximum(tx_lo, (cam.width - 1 + _EXIT_PX - cam.cx) * ze / f + b - xe)
            elif side == 1:
                tx_hi = np.minimum(tx_hi, (-_EXIT_PX - cam.cx) * ze / f - xe)
            elif side == 2:
                ty_lo = np.maximum(ty_lo, (cam.height - 1 + _EXIT_PX - cam.cy) * ze / f - ye)
            else:
                ty_hi = np.minimum(ty_hi, (-_EXIT_PX - cam.cy) * ze / f - ye)
        ok = np.flatnonzero((tx_lo <= tx_hi) & (ty_lo <= ty_hi))
        if ok.size:
            t = ok[0]
            shift = np.array(
                [rng.uniform(tx_lo[t], tx_hi[t]), rng.uniform(ty_lo[t], ty_hi[t]), tz[t, 0]]
            )
            return _rotate_z(ctrl, angle, centre) + shift
    return None


def _self_crossings(q: np.ndarray, s: np.ndarray, min_sep: float) -> tuple[np.ndarray, ...]:
    """Proper intersections of polyline segments more than ``min_sep`` apart along the arc.

    ``q`` (N, 2) polyline, ``s`` (N,) its arc coordinate. Returns segment indices i < j, the
    segment fractions t_i, t_j and |sin| of the crossing angle.
    """
    a, d = q[:-1], np.diff(q, axis=0)
    mid = 0.5 * (s[:-1] + s[1:])
    i, j = np.triu_indices(len(a), k=2)
    far = mid[j] - mid[i] > min_sep
    i, j = i[far], j[far]
    den = d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0]
    r = a[j] - a[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        ti = (r[:, 0] * d[j, 1] - r[:, 1] * d[j, 0]) / den
        tj = (r[:, 0] * d[i, 1] - r[:, 1] * d[i, 0]) / den
    hit = (den != 0) & (ti >= 0) & (ti <= 1) & (tj >= 0) & (tj <= 1)
    sin = np.abs(den[hit]) / (np.linalg.norm(d[i[hit]], axis=1) * np.linalg.norm(d[j[hit]], axis=1))
    return i[hit], j[hit], ti[hit], tj[hit], sin


def _acceptable(ctrl: np.ndarray, cam: StereoCamera, tp: ThreadParams) -> bool:
    """Thread does not pass through itself; crossings exactly as requested and clean."""
    diameter = tp.diameter_mm
    length = _arc_length(ctrl)
    # 3D clearance: arc-distant parts of the tube stay >= 1.5 diameters apart.
    step = min(_CENTERLINE_STEP_MM, max(0.5 * diameter, _MIN_CLEARANCE_STEP_MM))
    m3 = int(math.ceil(length / step)) + 1
    p3 = _sample_arc(ctrl, m3)
    s3 = np.linspace(0.0, length, m3)
    pairs = cKDTree(p3).query_pairs(1.5 * diameter, output_type="ndarray")
    if pairs.size and np.any(np.abs(s3[pairs[:, 0]] - s3[pairs[:, 1]]) > 4 * diameter):
        return False
    w_max = cam.fx * diameter / p3[:, 2].min()
    reach = w_max + 4.0  # parts closer than this in the image would merge visually
    p400 = _sample_arc(ctrl, 400)
    for view, uv in enumerate(cam.project(p400)):
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
        i, j, ti, tj, sin = _self_crossings(uv, s, 2 * reach)
        if tp.crossing:
            if view == 0:
                if i.size == 0 or np.any(sin < _MIN_CROSSING_SIN):
                    return False
                z = p400[:, 2]
                zi = z[i] + ti * (z[i + 1] - z[i])
                zj = z[j] + tj * (z[j + 1] - z[j])
                if np.any(np.abs(zi - zj) < 3 * diameter):
                    return False
        else:
            if i.size:
                return False
            n1 = int(math.ceil(s[-1])) + 1  # ~1 px spacing for the near-miss test
            uv1 = cam.project(_sample_arc(ctrl, n1))[view]
            s1 = np.linspace(0.0, s[-1], n1)  # approximately uniform in image arc length
            near = cKDTree(uv1).query_pairs(reach, output_type="ndarray")
            if near.size and np.any(np.abs(s1[near[:, 0]] - s1[near[:, 1]]) > 2.5 * reach):
                return False
            if tp.hairpin and view == 0:  # side by side over >= 4 reach, within 3 reach
                close = cKDTree(uv1).query_pairs(3 * reach, output_type="ndarray")
                far = close[np.abs(s1[close[:, 0]] - s1[close[:, 1]]) > 2.5 * reach]
                if len(np.unique(far[:, 0])) < 4 * reach:
                    return False
    return True


def _random_thread(cam: StereoCamera, tp: ThreadParams, rng: np.random.Generator) -> np.ndarray:
    span = tp.depth_mm[1] - tp.depth_mm[0]
    n_lo = max(tp.n_control[0], 7) if tp.crossing else tp.n_control[0]
    for _ in range(_MAX_ATTEMPTS):
        n = int(rng.integers(n_lo, tp.n_control[1] + 1))
        length = rng.uniform(*tp.length_mm)
        if tp.spiral:  # the coil's gap is fixed in mm: placed as drawn, never rescaled
            ctrl = _random_spiral(length, tp.curliness, rng)
            if ctrl is None or np.ptp(_sample_arc(ctrl, 256)[:, 2]) > 0.95 * span:
                continue
        else:
            poly = _random_polygon(n, tp.curliness, tp.crossing, rng, tp.hairpin)
            ctrl = _fit_length_and_depth(poly, length, span)
            if ctrl is None:
                continue
        ctrl = _place(ctrl, cam, tp, rng)
        if ctrl is not None and _acceptable(ctrl, cam, tp):
            return ctrl
    raise ValueError(
        f"could not place a thread with thread.length_mm={tp.length_mm} in the view at "
        f"thread.depth_mm={tp.depth_mm} (margin_px={tp.margin_px}, crossing={tp.crossing}, "
        f"leaves_image={tp.leaves_image}, spiral={tp.spiral}); try a shorter length or a deeper depth range"
    )


def _make_truth(ctrl: np.ndarray) -> ThreadTruth:
    length = _arc_length(ctrl)
    m = int(math.ceil(length / _CENTERLINE_STEP_MM)) + 1
    return ThreadTruth(
        control_points=np.ascontiguousarray(ctrl, dtype=np.float64),
        knots=thread_knots(len(ctrl)),
        degree=DEGREE,
        centerline=_sample_arc(ctrl, m),
        length_mm=length,
    )


# ----------------------------------------------------------------------------------------------
# Rendering


def _render_pair(
    ctrl: np.ndarray,
    cam: StereoCamera,
    diameter: float,
    rp: RenderParams,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    h, w = cam.height, cam.width
    # Dense samples, uniform in 3D arc, refined until the image step is below _RENDER_STEP_PX.
    m = 2000
    for _ in range(3):
        p3 = _sample_arc(ctrl, m)
        views = cam.project(p3)
        step = max(float(np.linalg.norm(np.diff(uv, axis=0), axis=1).max()) for uv in views)
        if step <= _RENDER_STEP_PX:
            break
        m = int(math.ceil(m * step / _RENDER_STEP_PX * 1.05))
    z = p3[:, 2]
    if rp.background == "tissue":
        z_bg = z.max() + 20.0  # tissue plane behind the thread, with an integer disparity
        d_bg = max(1, int(cam.disparity(z_bg)))
        tex = _tissue_texture(h, w + d_bg, rng)
        backgrounds = (tex[:, :w], tex[:, d_bg : d_bg + w])
        rgb = (75.0, 55.0, 105.0)  # violet braided suture, dark against pink tissue
    else:
        flat = np.full((h, w, 3), rp.background_level, dtype=np.float32)
        backgrounds = (flat, flat.copy())
        rgb = (120.0, 120.0, 120.0)  # like the paper's Blender thread (~107-140 grey)
    if rp.distractors and rp.background == "tissue":
        backgrounds = _add_distractors(tex, w, d_bg, rp.distractors, cam, diameter, z, rng)
    if rp.thread_colour == "random":
        rgb = THREAD_COLOURS[str(rng.choice(sorted(THREAD_COLOURS)))]
    elif rp.thread_colour is not None:
        rgb = THREAD_COLOURS[rp.thread_colour]
    thread_rgb = np.asarray(
        rp.thread_rgb if rp.thread_rgb is not None and rp.thread_colour is None else rgb,
        dtype=np.float32,
    )
    images, coverages = [], []
    for uv, bg in zip(views, backgrounds, strict=True):
        img, cov = _render_tube(uv, z, cam, diameter, thread_rgb, rp.specular, bg)
        images.append(img)
        coverages.append(cov)
    if rp.occlusion:
        _occlude(images, coverages, views, z, cam, rng)
    if rp.instrument:
        _instrument(images, coverages, z, cam, rng)
    if rp.lighting > 0:
        gain = _light_field(h, w, rp.lighting, rng)
        images = [img * gain[:, :, None] for img in images]
    out = []
    for img in images:
        if rp.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), rp.blur_sigma)
        if rp.noise_sigma > 0:
            img = img + rng.normal(0.0, rp.noise_sigma, img.shape).astype(np.float32)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        if rp.jpeg_quality > 0:
            img = _jpeg(img, rp.jpeg_quality)
        out.append(img)
    return out[0], out[1], coverages[0] >= 0.5, coverages[1] >= 0.5


def _foot(q: np.ndarray, poly: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from points q (N, 2) to the polyline near vertex j, and the fractional
    vertex index of the closest point (segments j-1..j and j..j+1)."""
    last = len(poly) - 1
    best_d = np.full(len(q), np.inf)
    best_f = np.zeros(len(q))
    for a_idx in (np.maximum(j - 1, 0), np.minimum(j, last - 1)):
        a, ab = poly[a_idx], poly[a_idx + 1] - poly[a_idx]
        den = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18)
        t = np.clip(np.einsum("ij,ij->i", q - a, ab) / den, 0.0, 1.0)
        d = np.linalg.norm(q - (a + t[:, None] * ab), axis=1)
        better = d < best_d
        best_d = np.where(better, d, best_d)
        best_f = np.where(better, a_idx + t, best_f)
    return best_d, best_f


def _tube(
    d: np.ndarray, width: np.ndarray, rgb: np.ndarray, specular: float
) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (N,) and colour (N, 3) of pixels at distance d (px) from a tube axis.

    Coverage is the box-filtered strip profile (exact for a straight strip of width w seen by a
    unit pixel): plateau min(w, 1), linear ramp between |1 - w| / 2 and (1 + w) / 2.
    """
    cov = np.clip(np.minimum(0.5 * (width + 1.0) - d, np.minimum(width, 1.0)), 0.0, 1.0)
    t = np.minimum(d / (0.5 * width), 1.0)  # normalised radius across the tube
    shade = _EDGE_SHADE + (1.0 - _EDGE_SHADE) * np.sqrt(1.0 - t * t)
    colour = shade[:, None] * rgb[None, :]
    colour += (255.0 * specular * np.exp(-((t / _HIGHLIGHT_HALF_WIDTH) ** 2)))[:, None]
    return cov, np.minimum(colour, 255.0)


def _render_tube(
    uv: np.ndarray,
    z: np.ndarray,
    cam: StereoCamera,
    diameter: float,
    rgb: np.ndarray,
    specular: float,
    background: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Composite the tube over ``background`` (H, W, 3); return the image and coverage (H, W).

    Each pixel gets the nearest centreline point (branch A) and, where the thread crosses
    itself, the nearest point on another part of the curve (branch B); the nearer branch
    is composited over the farther one.
    """
    h, w = cam.height, cam.width
    width = cam.fx * diameter / z  # projected tube width per sample, px
    reach = 0.5 * float(width.max()) + 1.0  # beyond this a pixel has zero coverage
    band = np.zeros((h, w), np.uint8)
    fixed = np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)  # 4 fractional bits
    cv2.polylines(band, [fixed], False, 1, thickness=2 * int(math.ceil(reach)) + 3, shift=4)
    rows, cols = np.nonzero(band)
    q = np.stack([cols, rows], 1).astype(float)  # pixel centres, (x, y)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(uv, axis=0), axis=1))])
    idx = np.arange(len(uv), dtype=float)
    tree = cKDTree(uv)
    _, ja = tree.query(q, distance_upper_bound=reach + _RENDER_STEP_PX)
    hit = ja < len(uv)
    q, rows, cols, ja = q[hit], rows[hit], cols[hit], ja[hit]
    da, fa = _foot(q, uv, ja)
    za, wa = np.interp(fa, idx, z), np.interp(fa, idx, width)
    cov_a, col_a = _tube(da, wa, rgb, specular)
    bg = background[rows, cols]
    colour = cov_a[:, None] * col_a + (1 - cov_a[:, None]) * bg
    cov = cov_a
    # Branch B: samples within reach whose arc position is far from branch A's.
    pairs = cKDTree(q).sparse_distance_matrix(tree, reach + _RENDER_STEP_PX, output_type="ndarray")
    if pairs.size:
        sa = np.interp(fa, idx, s)
        other = np.abs(s[pairs["j"]] - sa[pairs["i"]]) > math.pi * reach + 2.0
        pairs = pairs[other]
    if pairs.size:
        order = np.lexsort((pairs["v"], pairs["i"]))
        pairs = pairs[order]
        first = np.concatenate([[True], pairs["i"][1:] != pairs["i"][:-1]])
        ib, jb = pairs["i"][first], pairs["j"][first].astype(np.intp)
        db, fb = _foot(q[ib], uv, jb)
        zb, wb = np.interp(fb, idx, z), np.interp(fb, idx, width)
        cov_b, col_b = _tube(db, wb, rgb, specular)
        b_front = zb < za[ib]
        cf = np.where(b_front, cov_b, cov_a[ib])[:, None]
        cb = np.where(b_front, cov_a[ib], cov_b)[:, None]
        colf = np.where(b_front[:, None], col_b, col_a[ib])
        colb = np.where(b_front[:, None], col_a[ib], col_b)
        colour[ib] = cf * colf + (1 - cf) * (cb * colb + (1 - cb) * bg[ib])
        cov = cov.copy()
        cov[ib] = cf[:, 0] + (1 - cf[:, 0]) * cb[:, 0]
    image = background.astype(np.float32, copy=True)
    image[rows, cols] = colour
    coverage = np.zeros((h, w), np.float32)
    coverage[rows, cols] = cov
    return image, coverage


def _smooth_noise(h: int, w: int, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-std smooth random field (h, w) with feature size ~``scale`` px."""
    gh, gw = int(h / scale) + 4, int(w / scale) + 4
    grid = rng.normal(size=(gh, gw)).astype(np.float32)
    field_ = cv2.resize(grid, (int(gw * scale), int(gh * scale)), interpolation=cv2.INTER_CUBIC)
    field_ = field_[:h, :w]
    return (field_ - field_.mean()) / (field_.std() + 1e-6)


def _tissue_texture(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """Procedural pink-red tissue (h, w, 3) float32 RGB with vessels and specular glints."""
    base = np.array([205.0, 120.0, 115.0], np.float32)
    deep = np.array([160.0, 70.0, 75.0], np.float32)
    mix = np.clip(0.5 + 0.25 * _smooth_noise(h, w, 90, rng), 0, 1)[..., None]
    img = (1 - mix) * base + mix * deep
    lum = 1 + 0.08 * _smooth_noise(h, w, 40, rng) + 0.04 * _smooth_noise(h, w, 8, rng)
    img *= lum[..., None]
    vessels = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(4, 9))):
        n = 30
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.25, n))
        pts = rng.uniform([0, 0], [w, h]) + np.cumsum(
            12.0 * np.stack([np.cos(heading), np.sin(heading)], 1), axis=0
        )
        fixed = np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)
        strength = float(rng.uniform(0.25, 0.6))
        thick = int(rng.integers(1, 5))
        cv2.polylines(vessels, [fixed], False, strength, thick, cv2.LINE_AA, shift=4)
    vessels = cv2.GaussianBlur(vessels, (0, 0), 1.2)[..., None]
    img = img * (1 - vessels) + vessels * np.array([110.0, 25.0, 40.0], np.float32)
    glints = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(5, 12))):
        centre = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        axes = (int(rng.integers(2, 7)), int(rng.integers(1, 4)))
        cv2.ellipse(glints, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1.0, -1, cv2.LINE_AA)
    glints = np.clip(cv2.GaussianBlur(glints, (0, 0), 1.5) * 1.5, 0, 1)[..., None]
    img = img * (1 - glints) + 250.0 * glints
    return np.clip(img, 0, 255).astype(np.float32)


def _occlude(
    images: list[np.ndarray],
    coverages: list[np.ndarray],
    views: tuple[np.ndarray, np.ndarray],
    z: np.ndarray,
    cam: StereoCamera,
    rng: np.random.Generator,
) -> None:
    """Draw an instrument shaft (capsule) in front of the thread into both views, in place.

    The shaft is a planar capsule at depth 0.75 * Z of the thread point it covers, so the
    right view sees it shifted by that depth's disparity. Occluded coverage is removed.
    """
    h, w = cam.height, cam.width
    uv = views[0]
    inside = np.flatnonzero(
        (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    )
    lo, hi = inside[0], inside[-1]
    k = int(lo + rng.uniform(0.3, 0.7) * (hi - lo))
    anchor = uv[k]
    radius = float(rng.uniform(14.0, 26.0))  # shaft half-width, px
    d_inst = float(cam.disparity(0.75 * z[k]))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    before = [c.sum() for c in coverages]
    for _ in range(8):
        angle = rng.uniform(0, 2 * math.pi)
        axis = np.array([math.cos(angle), math.sin(angle)])
        tip = anchor + axis * radius * rng.uniform(0.5, 1.5)
        far = tip - axis * 4 * (w + h)  # shaft runs out of the image
        covs = []
        for view in range(2):
            shift = np.array([d_inst if view else 0.0, 0.0])
            covs.append(_capsule(xs, ys, far - shift, tip - shift, radius, axis))
        kept = [
            (c * (1 - co)).sum() / max(b, 1e-9)
            for c, (co, _), b in zip(coverages, covs, before, strict=True)
        ]
        if min(kept) >= 0.5:
            break
    for view in range(2):
        co, colour = covs[view]
        images[view] = co[..., None] * colour + (1 - co[..., None]) * images[view]
        coverages[view] = coverages[view] * (1 - co)


def _capsule(
    xs: np.ndarray, ys: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float, axis: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage (H, W) and metallic shading (H, W, 3) of a capsule a-b."""
    ab = b - a
    t = np.clip(((xs - a[0]) * ab[0] + (ys - a[1]) * ab[1]) / float(ab @ ab), 0, 1)
    dx, dy = xs - (a[0] + t * ab[0]), ys - (a[1] + t * ab[1])
    dist = np.sqrt(dx * dx + dy * dy)
    cov = np.clip(radius - dist + 0.5, 0, 1)
    v = np.clip((dx * -axis[1] + dy * axis[0]) / radius, -1, 1)  # signed, across the shaft
    shade = 0.35 + 0.4 * np.sqrt(1 - v * v) + 0.45 * np.exp(-(((v - 0.4) / 0.15) ** 2))
    along = (xs - b[0]) * axis[0] + (ys - b[1]) * axis[1]  # <= 0 on the shaft, 0 at the tip
    jaw = np.clip(along + 1.2 * radius + 0.5, 0, 1)  # darker jaw over the last 1.2 radii
    shade = shade * (1.0 - 0.45 * jaw)
    colour = np.clip(shade[..., None] * np.array([190.0, 195.0, 200.0], np.float32), 0, 255)
    return cov.astype(np.float32), colour.astype(np.float32)


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """JPEG round trip of an RGB uint8 image (OpenCV's default 4:2:0 chroma subsampling)."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"JPEG encoding failed at quality {quality}")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _light_field(h: int, w: int, strength: float, rng: np.random.Generator) -> np.ndarray:
    """(h, w) float32 gain in [1 - strength, 1]: the endoscope's radial fall-off (vignetting)
    around an off-centre light axis plus a linear gradient (tissue tilted to the light)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    cx, cy = rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h
    r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / float(0.25 * (w * w + h * h))
    angle = rng.uniform(0, 2 * math.pi)
    ramp = (math.cos(angle) * (xs / w - 0.5) + math.sin(angle) * (ys / h - 0.5)) + 0.5
    share = rng.uniform(0.3, 0.7)  # of the fall-off due to vignetting vs the gradient
    loss = share * np.clip(r2, 0, 1) + (1 - share) * np.clip(ramp, 0, 1)
    return (1.0 - strength * loss / max(float(loss.max()), 1e-6)).astype(np.float32)


def _add_distractors(
    tex: np.ndarray,
    w: int,
    d_bg: int,
    count: int,
    cam: StereoCamera,
    diameter: float,
    z: np.ndarray,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``count`` vessels (dark, tissue hue) and fibres (light) as wide as the thread into
    the tissue texture, so they lie on the tissue plane and match in both views; return the
    two views' backgrounds."""
    h, wt = tex.shape[:2]
    w_lo, w_hi = float(cam.fx * diameter / z.max()), float(cam.fx * diameter / z.min())
    if w_hi < 1.0:  # a thread-free frame (sub-pixel thread): distractors of a usual thread width
        w_lo, w_hi = 1.5, 5.0
    for _ in range(count):
        n = 40
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.12, n))
        pts = rng.uniform([0, 0], [wt, h]) + np.cumsum(
            6.0 * np.stack([np.cos(heading), np.sin(heading)], 1), axis=0
        )
        width = rng.uniform(max(1.0, 0.7 * w_lo), w_hi)
        layer = np.zeros((h, wt), np.float32)
        fixed = np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(layer, [fixed], False, 1.0, max(1, round(width)), cv2.LINE_AA, shift=4)
        layer = cv2.GaussianBlur(layer, (0, 0), 0.6)[..., None]
        if rng.uniform() < 0.6:  # a vessel: darker and more saturated than the tissue
            colour = tex * np.array([0.55, 0.3, 0.38], np.float32)
            strength = rng.uniform(0.4, 0.8)
        else:  # a fibre or fascia strand: lighter, slightly yellow
            colour = np.broadcast_to(np.array([240.0, 225.0, 200.0], np.float32), tex.shape)
            strength = rng.uniform(0.35, 0.7)
        tex = tex * (1 - strength * layer) + strength * layer * colour
    return tex[:, :w], tex[:, d_bg : d_bg + w]


def _instrument(
    images: list[np.ndarray],
    coverages: list[np.ndarray],
    z: np.ndarray,
    cam: StereoCamera,
    rng: np.random.Generator,
) -> None:
    """A grasper in front of the thread, in place: a shaft from outside the view ending in two
    open jaws, anywhere in the view, so it may or may not hide the thread (coverage removed)."""
    h, w = cam.height, cam.width
    tip = rng.uniform([0.2 * w, 0.2 * h], [0.8 * w, 0.8 * h])
    angle = rng.uniform(0, 2 * math.pi)
    axis = np.array([math.cos(angle), math.sin(angle)])
    radius = float(rng.uniform(14.0, 24.0))  # shaft half-width, px
    opening = float(rng.uniform(0.2, 0.45))  # half-angle between the jaws, rad
    jaw_len = float(rng.uniform(2.0, 3.5)) * radius
    d_inst = float(cam.disparity(0.7 * float(z.min())))
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    far = tip - axis * 4 * (w + h)
    for view in range(2):
        shift = np.array([d_inst if view else 0.0, 0.0])
        parts = [_capsule(xs, ys, far - shift, tip - shift, radius, axis)]
        for sign in (-1.0, 1.0):
            ca, sa = math.cos(sign * opening), math.sin(sign * opening)
            jaw_axis = np.array([ca * axis[0] - sa * axis[1], sa * axis[0] + ca * axis[1]])
            base = tip - shift + sign * 0.45 * radius * np.array([-axis[1], axis[0]])
            parts.append(_capsule(xs, ys, base, base + jaw_axis * jaw_len, 0.3 * radius, jaw_axis))
        for co, colour in parts:
            images[view] = co[..., None] * colour + (1 - co[..., None]) * images[view]
            coverages[view] = coverages[view] * (1 - co)
