"""The check stage: the final curve held against the evidence it came from.

A curve is never returned silently wrong: after the camera stage (Eq. (9)) the curve is
projected back into both rectified views and compared with the segmented thread pixels P_L,
P_R, its depths with the range the disparity search of Eq. (3) can produce, its length with the
2D path and the depth span of the thread, and the MVS solution (Eq. (8)) with its bounds
(Eq. (7)). Every finding is a reason in words; the status is the worst of them:

- ``failed``: the curve cannot be right (non-finite, behind a camera, outside the depths the
  disparity search allows, or far off the thread pixels);
- ``suspect``: a measurement disagrees with the evidence by more than its threshold;
- ``ok``: every measurement is within its threshold.

The stage also gives a per-point confidence, a grasp point and an automatic quality score on
the paper's 1-5 rating scale (Sec. IV-B: 1 very bad .. 5 very good, below 3 a failure).

Per-point confidence. For each point i of the dense curve an expected 3D error is predicted
from the evidence near it, in mm:

    e_i = (Z_i^2 / (f B)) * sqrt(sigma_d^2 + rbar_i^2) * (1 + exp(-a_i / end_mm))
          + (Z_i / f) * rho_i + bridge_error * g_i,

with Z_i / f and Z_i^2 / (f B) the lateral and depth size of a pixel and of a pixel of
disparity at the point's depth; rbar_i the mean, over one knot span of the spline around the
point (the stretch whose matches the spline averages), of r, the disparity residual of the
curve against the nearest reliable pixel of P_L^R (stretched when that pixel is far away),
counted up to ``support_tol_px`` (beyond it no match agrees and the depth is interpolated);
sigma_d the matching precision (``sigma_disparity_px``); a_i the distance to the nearer end
(an end is fitted from one side); rho_i the larger of the two reprojection distances to the
thread pixels beyond half a pixel's diagonal (quantisation); g_i the distance into a bridge
or from the nearest supported point (an interpolated shape drifts; core/check_score.py). The
confidence is exp(-e_i / ``conf_mm``). The bound half-width h_i of Eq. (7) is left out: where
no match pins the depth it was no sign of a larger error (docs/method.md, the check's fifth
round); it only marks the ambiguous length of the evidence (``ambiguous_mm``).

All image measurements use one distance field per view of the thread masks (``check_field``:
cached with the segmentation, its values computed only where the curve reads them), so the
stage costs a few milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import partial
from typing import Any, ClassVar, Literal

import numpy as np
from scipy.interpolate import BSpline
from scipy.spatial import cKDTree

from threadrecon.core.bounds import Bounds
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.camera import CameraCurve
from threadrecon.core.check_beyond import (
    AHEAD_MEET,
    AHEAD_NEAR_PX,
    AHEAD_STEP_PX,
    END_SAMPLES,
    beyond_ends,
    bridge_stray,
    cut_end,
    end_frames_kept,
    end_occluder,
    extension,
    extension_far,
    hidden_piece,
    left_behind,
    plain_surface,
    surface_ahead,
    surface_past_end,
    thread_line_beyond,
)
from threadrecon.core.check_fast_kernel import flag_runs, ring_level
from threadrecon.core.check_field import MaskField, derived, mask_field
from threadrecon.core.check_fold import Reversal, end_reversal, fold_length, self_contact
from threadrecon.core.check_kernel import (
    coverage_count,
    nearest_residual,
    overlap_length,
    unmeasured_length,
    unsupported_travel,
)
from threadrecon.core.check_mark import moves_with_surface
from threadrecon.core.check_score import (
    GraspPoint,
    bound_halfwidth_px,
    grasp_point,
    point_errors,
    quality_score,
)
from threadrecon.core.check_support import contradicted, reliable_rows, uncontested
from threadrecon.core.continuity import disparity_room
from threadrecon.core.numeric import arc_px, row_norms
from threadrecon.core.ordering import Ordering
from threadrecon.core.params import Params, param
from threadrecon.core.refine import row_runs
from threadrecon.core.reliability import ReliabilityResult
from threadrecon.core.segmentation import LiftedPair
from threadrecon.core.spline import SplineResult
from threadrecon.core.stereo import StereoResult

Status = Literal["ok", "suspect", "failed"]
_RANK = {"ok": 0, "suspect": 1, "failed": 2}
BAND_PX = 8  # band around the curve in which the thread width is measured, px
END_WINDOW_PX = 15.0  # px: the tip's matching window (2 end_window_px + 1, deviation 55)
ROW_DEG = 15.0  # deg: a stretch this close to the image rows (stereo's epipolar_deg default)
CUT_REACH_PX = 35.0  # px searched past cut_end_px (an occluder shifts a cut by 10-25 px)
BEYOND_COVER_PX = 2.0  # px: a thread's half-width, added to cover_px for the pieces beyond
CONTRA_PX = 1  # px: the reliable pixels under a curve point (its pixel and 8 neighbours)
CONTEST_SLACK_PX = 2.0  # px: a right row run holds its own width of left pixels, +-1 px a side


@dataclass(frozen=True)
class CheckParams(Params):
    """Thresholds of the check stage; each one's doc says what exceeding it means."""

    RETIRED: ClassVar[dict[str, str]] = {
        "bridge_turn_deg": "a bridge's turn at its ends is no evidence against it (session 13)",
        "bridge_mm": "the side length of the retired bridge turn test (session 13)",
    }

    reproj_mean_px: float = param(
        2.0, lo=0.0, unit="px", slider=(0.5, 10.0, 0.1), label="max mean reprojection",
        doc="Suspect when the mean distance of the projected curve to the thread pixels "
        "exceeds this in either view.",
    )  # fmt: skip
    reproj_max_px: float = param(
        8.0, lo=0.0, unit="px", slider=(1.0, 50.0, 0.5), label="max reprojection",
        doc="Suspect when a projected curve point lies farther than this from the thread "
        "pixels in either view.",
    )  # fmt: skip
    reproj_fail_px: float = param(
        40.0, lo=0.0, unit="px", slider=(5.0, 200.0, 1.0), label="failed reprojection",
        doc="Failed when a projected curve point lies farther than this from the thread pixels.",
    )  # fmt: skip
    coverage_min: float = param(
        0.85, lo=0.0, hi=1.0, slider=(0.0, 1.0, 0.01), label="min coverage",
        doc="Suspect when a smaller share of the thread pixels lies near the projected curve "
        "(within cover_px plus the thread's half-width) in either view.",
    )  # fmt: skip
    coverage_seen_both: bool = param(
        True, label="coverage of thread both views can see",
        doc="On: a view's thread pixels that the other view cannot see at any depth of the "
        "curve (a strip along the image's side as wide as the curve's smallest disparity: the "
        "right view's right side, the left view's left side) leave that view's coverage: a "
        "thread that leaves the image shows there in one view only, and no curve (nor the "
        "truth scored, the part both views see) covers it. Off: every thread pixel counts. "
        "docs/method.md, prec19.",
    )  # fmt: skip
    cover_px: float = param(
        3.0, lo=0.0, unit="px", slider=(0.0, 10.0, 0.5), label="coverage distance",
        doc="A thread pixel is covered when the projected curve passes within this distance "
        "plus the thread's half-width.",
    )  # fmt: skip
    min_disparity_px: float = param(
        1.0, lo=0.0, unit="px", slider=(0.0, 10.0, 0.5), symbol="d_min",
        label="smallest disparity",
        doc="Smallest disparity a depth may have: the curve must lie between f B / alpha and "
        "f B / d_min (Eq. (3) searches d = 0..alpha). With a working depth range "
        "(stereo.z_far_mm) the search starts at floor(f B / z_far): a larger d_min is that.",
    )  # fmt: skip
    disparity_tol_px: float = param(
        0.5, lo=0.0, unit="px", slider=(0.0, 10.0, 0.5), label="disparity tolerance",
        doc="Failed when the curve's disparity leaves [d_min, alpha] by more than this.",
    )  # fmt: skip
    length_tol: float = param(
        0.25, lo=0.0, slider=(0.0, 2.0, 0.05), label="length tolerance",
        doc="Suspect when the 3D length leaves [(1 - tol) L_min, (1 + tol) L_max], L_min = "
        "s Z_lo / f and L_max = s Z_hi / f + depth_turns (Z_hi - Z_lo), s the 2D path length "
        "in px and [Z_lo, Z_hi] the depth span of the bounds.",
    )  # fmt: skip
    depth_turns: float = param(
        2.0, lo=0.0, slider=(0.0, 10.0, 0.5), label="depth turns",
        doc="How many times the curve may traverse the depth span of the bounds (length test).",
    )  # fmt: skip
    bound_tol: float = param(
        0.25, lo=0.0, slider=(0.0, 5.0, 0.05), label="bound excursion",
        doc="Suspect when the curve leaves its depth bounds (Eq. (7)) by more than this "
        "fraction of the local half-width where no reliable match supports it (a curve that "
        "leaves them along agreeing matches shows the bounds too narrow, not itself wrong).",
    )  # fmt: skip
    solver_suspect: bool = param(
        True, label="solver failure is suspect",
        doc="A rejected MVS solution (the initial spline is shown) makes the curve suspect.",
    )  # fmt: skip
    jump_px: float = param(
        3.0, lo=0.0, unit="px", slider=(0.0, 20.0, 0.5), label="off-thread distance",
        doc="A curve sample farther than this from the left thread pixels is off the thread.",
    )  # fmt: skip
    max_jump_px: float = param(
        60.0, lo=0.0, unit="px", slider=(0.0, 200.0, 1.0), label="longest overshoot",
        doc="Suspect when an end of the curve runs more than this 2D length off the thread "
        "pixels (either view). A run between two thread parts is a bridge (max_unobserved_mm).",
    )  # fmt: skip
    max_unobserved_mm: float = param(
        20.0, lo=0.0, unit="mm", slider=(0.0, 100.0, 1.0), label="longest unobserved stretch",
        doc="Suspect when a stretch of the curve no view observes is longer than this in 3D: a "
        "bridge across unsegmented (e.g. occluded) pixels between two thread parts, or a part "
        "outside the right image. Its shape is interpolated, not measured; the default is the "
        "length error at which a curve counts as wrong (issue 11).",
    )  # fmt: skip
    max_bridge_mm: float = param(
        40.0, lo=0.0, unit="mm", slider=(0.0, 300.0, 1.0), label="longest evidenced bridge",
        doc="Suspect when a bridge the evidence supports (it is no loop and crosses occluder "
        "or unsegmented thread, not bare background) is longer than this in 3D. A thread as "
        "long as the bridge strays at most half its length from it, however it turns at the "
        "bridge's ends: the default is twice the wrong-curve error (issue 11). A bridge without "
        "that evidence is held to max_unobserved_mm.",
    )  # fmt: skip
    bridge_stretch: float = param(
        1.6, lo=1.0, slider=(1.0, 5.0, 0.05), label="bridge stretch",
        doc="A bridge longer than this many times its chord (3D, and 2D in the left image) is "
        "a loop, not a plausible continuation.",
    )  # fmt: skip
    bare_share: float = param(
        0.5, lo=0.0, hi=1.0, slider=(0.0, 1.0, 0.05), label="bare background share",
        doc="A bridge is contradicted when more than this share of its samples lie over pixels "
        "that look like the bare background next to the thread in both views (the thread "
        "would be seen there).",
    )  # fmt: skip
    bare_sigma: float = param(
        2.5, lo=0.0, slider=(0.5, 10.0, 0.1), label="bare background tolerance",
        doc="A pixel looks like bare background when its grey level is within this many robust "
        "standard deviations (at least 4 grey levels) of the ring around the thread near the "
        "bridge's ends (interpolated between them).",
    )  # fmt: skip
    bare_back_px: float = param(
        25.0, lo=0.0, unit="px", slider=(0.0, 100.0, 1.0), label="bare level reach back",
        doc="A bridge end's bare-background level (bare_sigma) is also read on the ring around "
        "the observed thread this far back from the end (2D, along the curve), and the ring "
        "with the smaller spread is taken: where the thread runs under an occluder at the end, "
        "the end's own ring holds the occluder too, and its spread lets the occluder pass for "
        "background. 0: the end's ring only (session 15's check).",
    )  # fmt: skip
    bridge_error: float = param(
        0.05, lo=0.0, slider=(0.0, 1.0, 0.01), label="bridge error rate",
        doc="Expected error added on an evidenced bridge per mm of distance to its nearest "
        "observed end (the interpolated shape drifts away from the observed ends).",
    )  # fmt: skip
    support_tol_px: float = param(
        1.0, lo=0.0, unit="px", slider=(0.0, 10.0, 0.1), label="supported residual",
        doc="A curve point is supported by a reliable match when its disparity residual r_i "
        "(module docstring) is at most this.",
    )  # fmt: skip
    max_unsupported_mm: float = param(
        20.0, lo=0.0, unit="mm", slider=(0.0, 100.0, 1.0), label="unsupported depth travel",
        doc="Suspect when the curve's depth travels back and forth by more than this where no "
        "reliable match supports it (beyond the straight depth change between supported "
        "points): length the evidence does not show. Default: the wrong-length limit.",
    )  # fmt: skip
    max_unmeasured_mm: float = param(
        10.0, lo=0.0, unit="mm", slider=(0.0, 100.0, 1.0), label="unmeasured length",
        doc="With a crossing (of the thread pixels, or of the curve's left projection with "
        "itself), suspect when the curve's depth change adds more than this to its length "
        "where no reliable match supports it (over each such step, the 3D step less the same "
        "2D step at constant depth): the effect of the crossing's ambiguity, a wrong branch "
        "joining two strands at different depths. Default: half the wrong-length limit "
        "(a wrong branch enters and leaves the other strand: two such joins).",
    )  # fmt: skip
    loop_px: float = param(
        1.5, lo=0.0, unit="px", slider=(0.0, 10.0, 0.5), label="loop distance",
        doc="Two curve samples this close in the left image, but far apart along the curve, "
        "overlap.",
    )  # fmt: skip
    crossing_disparity_px: float = param(
        1.0, lo=0.0, unit="px", slider=(0.0, 10.0, 0.25), label="crossing depth gap",
        doc="Two passes of the curve over the same left pixels are two strands crossing, not a "
        "loop, when the thread pixels cross at a keypoint, both passes lie on them, each is "
        "within crossing_support_px along the curve of a point a reliable match supports, and "
        "their disparities differ by at least this (default 1 px, 20 sigma_d: a loop or "
        "doubling back re-uses the same matches, at the same depth). Such a crossing is no overlap.",
    )  # fmt: skip
    crossing_support_px: float = param(
        25.0, lo=0.0, unit="px", slider=(0.0, 100.0, 1.0), label="crossing support reach",
        doc="2D length along the curve within which a crossing strand needs a supported point "
        "(its depth across the crossing is interpolated from there).",
    )  # fmt: skip
    fold_px: float = param(
        3.0, lo=0.0, unit="px", slider=(0.0, 10.0, 0.5), label="fold distance",
        doc="Two passes of the curve's left projection closer than this, far apart along the "
        "curve, along one line and at one disparity (within crossing_disparity_px) run over "
        "one strand: a fold (core/check_fold.py; its length is held to max_overlap_px). "
        "Default: about a thread's half-width (two strands' centres lie a width apart).",
    )  # fmt: skip
    max_overlap_px: float = param(
        25.0, lo=0.0, unit="px", slider=(0.0, 200.0, 1.0), label="longest overlap",
        doc="Suspect when more than this length of the left projection runs over another part "
        "of the curve (a loop or doubling back the pixels do not show; a crossing is short).",
    )  # fmt: skip
    sigma_disparity_px: float = param(
        0.05, lo=0.0, unit="px", slider=(0.0, 2.0, 0.01), symbol="sigma_d",
        label="matching precision",
        doc="Disparity precision of a reliable match, for the per-point expected error (the "
        "generated suites' supported points have a median depth error of 0.02-0.03 px of "
        "disparity).",
    )  # fmt: skip
    support_px: float = param(
        10.0, lo=1.0, unit="px", slider=(1.0, 50.0, 1.0), label="support distance",
        doc="Distance to the nearest reliable pixel at which its disparity counts one pixel "
        "less (adds to the residual r_i).",
    )  # fmt: skip
    end_mm: float = param(
        2.0, lo=1e-6, unit="mm", slider=(0.1, 20.0, 0.1), label="end error reach",
        doc="The expected error doubles at an end of the curve (its depth is fitted from one "
        "side) and falls back over this distance from the end.",
    )  # fmt: skip
    cut_end_px: float = param(
        5.0, lo=0.0, unit="px", slider=(0.0, 50.0, 0.5), label="cut end",
        doc="Suspect when one view sees uncovered thread pixels more than this farther beyond a "
        "free end of the curve than the other view, and the other view shows no bare "
        "background just beyond the end nor (by stereo) a surface at or behind the end's "
        "depth: the end is cut by an occluder in that view (a free end stops at one 3D point, "
        "seen in both views), so the thread may continue hidden. Not when the thread then runs "
        "into an occluder in both views whose measured reach bounds what may hide "
        "(occluded_mm, held to max_unobserved_mm).",
    )  # fmt: skip
    line_level: float = param(
        0.0, lo=0.0, hi=1.0, slider=(0.0, 1.0, 0.05), label="thread line level",
        doc="Where the segmentation gives a thread score (not with given masks): suspect when "
        "a line of at least this score (0.5: the segmentation's decision level) goes on past a "
        "free end that meets no occluder, in both views at the end's disparity, bending "
        "smoothly on from the curve's way, farther than max_unobserved_mm "
        "(core/check_beyond.thread_line_beyond): thread the segmentation dropped (a loop "
        "taken for a vessel). Default 0, off: at 0.5 it flagged a right curve on a held-out "
        "seed (docs/method.md, okwrong14).",
    )  # fmt: skip
    blank_occluder: bool = param(
        True, label="a blank patch beyond an end hides",
        doc="On: at a free end where one view measures a surface in front of the end (an "
        "occluder) and the other cannot tell because it is blank there (its patches just "
        "beyond the end give no disparity, the first is untextured and its grey more than 3 "
        "noise floors from the surface the thread lies on 27 px back: a shaft's dark, uniform "
        "tip), the end runs into that occluder, as when both views measure it, and the "
        "occluder's reach is walked (occluded_mm, core/check_beyond.end_occluder). The lone "
        "measure must stand: the measuring view's next patch shows no surface at or behind "
        "the end, and the blank view's patch where it matched is blank too or returns it. "
        "Off: both views must measure it (session 10b's rule). docs/method.md, okwrong16.",
    )  # fmt: skip
    blank_next_measure: bool = param(
        True, label="a blank view's occluder not contradicted farther on",
        doc="On (with blank_occluder): where one view measures an occluder in front of a free "
        "end whose other view is blank there, the first patch farther along the end's way "
        "that the view seeing farther can measure must not show the surface the thread lies "
        "on (at or behind the end's depth): the lone measure was then a mismatch of faint "
        "texture on a smooth stretch of tissue. Off: only the measuring view's next patch is "
        "looked at (okwrong16's rule). docs/method.md, prec19.",
    )  # fmt: skip
    end_reversal: bool = param(
        True, label="a mark joined where the curve turns back",
        doc="On: suspect when the curve's left projection turns back by more than 120 deg "
        "within 12 px and runs on from there heading back (the 40 px chord either side and "
        "the chord to the end each turn more than 120 deg from the way in) for more than "
        "max_unobserved_mm to an end (core/check_fold.end_reversal), and stereo shows that "
        "branch on the surface beside it while the curve on the other side of the turn floats "
        "in front of its surface: a mark on the surface (a fibre) joined to the thread. A "
        "thread running along the line of sight turns back at a point in its projection too "
        "(a narrow loop): the surface test keeps it. Off: no such test (before session 17). "
        "docs/method.md, okwrong17.",
    )  # fmt: skip
    self_contact: bool = param(
        True, label="the curve passes through itself",
        doc="On: suspect when two points of the curve more than max_unobserved_mm apart along "
        "it lie closer in 3D than half a thread's width (fold_px at their depth) with their "
        "left projections within fold_px (core/check_fold.self_contact): two strands of a "
        "thread lie a width or more apart, so the curve left a strand and came back to the "
        "same point of it (a wrong order of its pieces). Off: no such test (before session "
        "17). docs/method.md, okw17b.",
    )  # fmt: skip
    seen_beyond: bool = param(
        True, label="thread seen past an end",
        doc="On: suspect when the thread pixels of a free end's own piece go on, uncovered by "
        "the curve and within 30 deg of its way, more than max_unobserved_mm (at the end's "
        "depth) past the end in both views (core/check_beyond.extension): the curve stops "
        "short of thread both views show (a walk that ended at a crossing, a tail along the "
        "image rows without a reliable match). Off: the end's own piece is measured only up "
        "to cut_end_px + 35 px, for an end cut in one view (before session 18). "
        "docs/method.md, session 18.",
    )  # fmt: skip
    cut_front_stereo: bool = param(
        True, label="a cut end's occluder measured by stereo",
        doc="On: where one view sees the thread go on past a free end (cut_end_px) and the "
        "other view's pixels just past the end look like bare background by their grey, the "
        "end is still cut when stereo measures the surface there in front of the end "
        "(core/check_beyond.surface_past_end: an instrument's shaded side can have the "
        "tissue's grey); then as any cut end (the occluder's reach bounds what may hide). "
        "Off: the grey alone makes such an end free (before session 20). docs/method.md, okw20.",
    )  # fmt: skip
    bridge_left_behind: bool = param(
        True, label="thread left behind at a bridge",
        doc="On: a bridge (a run of the curve across unsegmented pixels) longer than "
        "max_unobserved_mm where, at one of its ends, the thread pixels the curve leaves "
        "branch on, covered by no part of the curve, over a path longer than half "
        "max_unobserved_mm (at that end's depth) in both views (core/check_beyond.left_behind) "
        "is no continuation of the thread (the thread did not pass out of sight there: the walk "
        "took a branch onto another strand) and is held to max_unobserved_mm, not "
        "max_bridge_mm. Off: before session 20. docs/method.md, okw20.",
    )  # fmt: skip
    bridge_alongside: bool = param(
        True, label="a stretch beside the thread is no bridge",
        doc="On: a run of the curve off the thread pixels (farther than jump_px) between two "
        "thread parts whose every sample lies, in both views, within reproj_max_px of the "
        "thread pixels is no bridge: the thread is segmented all along it (the curve only "
        "runs beside it), so it is judged by the reprojection test like any observed stretch, "
        "not as a stretch no view observes (max_unobserved_mm). Off: before session 21. "
        "docs/method.md, prec21.",
    )  # fmt: skip
    occluder_exit: bool = param(
        True, label="an occluder's far side seen between untold patches",
        doc="On: the walk over an occluder at a free end (occluded_mm, "
        "core/check_beyond.end_occluder) stops where two patches measure one surface at or "
        "behind the end's depth (within 8 px of disparity of each other) with only patches "
        "the pair cannot tell between them, not only two in a row: smooth tissue past a "
        "shaft's edge alternates untextured patches and patches measured behind the end, and "
        "the occluder (measured in front wherever it is textured) does not come back between "
        "them along a straight way. Off: two patches in a row (before session 22). "
        "docs/method.md, prec23 (check rule 67).",
    )  # fmt: skip
    bridge_stray_both: bool = param(
        True, label="a hidden thread strays only where both views hide it",
        doc="On: the occluder's reach across a bridge (how far the hidden thread may stray from "
        "it, core/check_beyond.bridge_stray) is, on each side of each sample, the nearer of "
        "the two views' reaches: a thread off the bridge at the sample's depth lies as far "
        "off it in both views and would be seen where either view shows the surface. Off: "
        "the farther of the two (before session 22). docs/method.md, occ23.",
    )  # fmt: skip
    cut_tip_seen: bool = param(
        True, label="a cut end's far view shows the thread's own tip",
        doc="On: at a cut end (cut_end_px), the view that sees the thread go on shows the "
        "thread's own end also where its thread bends off the end's straight way: the piece "
        "past the end reaches no farther than its farthest pixel within 30 deg of the way "
        "(within 3 px), bare background lies just past that pixel along the chord from the end "
        "to it and the rays 22.5 and 45 deg either side, and stereo measures no surface in "
        "front of the end there (core/check_beyond._own_tip_bare); then nothing is hidden, the curve "
        "misses that extension only (beyond_mm), as when the straight way meets bare "
        "background. Off: the straight way only (before session 22). docs/method.md, cut23 "
        "(check rule 71).",
    )  # fmt: skip
    bridge_outside: bool = param(
        True, label="a bridge outside both images is unobserved",
        doc="On: the samples of the curve outside both images between samples inside them (it "
        "leaves the view and comes back) are part of the bridge across them (with the off-thread "
        "runs either side), and such a bridge is allowed max_unobserved_mm, not "
        "max_bridge_mm: no occluder hides it, nothing bounds where the thread runs there. Off: "
        "they are left out of every run (before session 23), so a bridge out of the image and "
        "back was judged in pieces. docs/method.md, okw27 (check rule 81).",
    )  # fmt: skip
    row_end_tip: bool = param(
        True, label="an end along the rows: the far view's tip on the stop view's end row",
        doc="On: where one view sees the thread go on more than cut_end_px farther past a "
        "free end than the other, and the farthest pixel of that extension lies on the other "
        "view's end row (within cover_px: along the rows), the two could be one tip seen in "
        "both views: along the rows only where the thread ends in each view fixes the "
        "disparity, so which view's end is cut (the curve misses the extension) or which "
        "depth is right the images do not tell. The end's disparity may lie between its own "
        "and that tip's (within the search's range), within one strand's continuity room of "
        "the nearest reliable match past the end's own (or of where the curve leaves the "
        "rows, 15 deg); an end whose matches hold on for 30 px is measured. Suspect when the "
        "depth so allowed lies more than max_unobserved_mm from the end's "
        "(core/check._row_end_tip). Off: no such test (before session 23). docs/method.md, "
        "okw27 (check rule 81).",
    )  # fmt: skip
    beyond_one_view: bool = param(
        True, label="a piece beyond an end borne out by the other view's score",
        doc="On: a piece of thread pixels beyond a free end across an occluder that only one "
        "view's segmentation holds counts as seen in both views when the other view's raw "
        "thread score shows it (core/check_beyond.beyond_ends, _borne_out: at one shift within "
        "16 px of the end's disparity, 80 % of its pixels at score 0.5 or more): the other "
        "view's segmentation dropped the stretch. Raw frames only (given masks carry no "
        "score). Off: a piece must be segmented in both views (before session 22). "
        "docs/method.md, okw24 (check rule 73).",
    )  # fmt: skip
    both_ends_level: float = param(
        0.5, lo=0.0, hi=1.0, slider=(0.0, 1.0, 0.05), label="both ends: thread line level",
        doc="A piece beyond one free end across an occluder (beyond_mm) under "
        "max_unobserved_mm and a thread line (core/check_beyond.thread_line_beyond at this "
        "score level) past the other free end, with no occluder there: suspect when the two "
        "together exceed max_unobserved_mm (the curve misses thread at both ends). Raw frames "
        "only. 0: off (before session 22). docs/method.md, okw24 (check rule 73).",
    )  # fmt: skip
    hidden_piece: bool = param(
        True, label="an occluded end: a piece one view shows and the other hides",
        doc="On: at a free end that runs into an occluder in both views (occluded_mm) "
        "bounded under max_unobserved_mm, a piece of thread pixels beyond it across the "
        "occluder in one view that the other view hides (core/check_beyond.hidden_piece: at "
        "the end's disparity no bare background there, no thread pixels within 16 px of it) "
        "reaching farther than max_unobserved_mm from the end: suspect (the thread runs on "
        "under the occluder past the walked bound, peeking out in one view). Off: before "
        "session 23. docs/method.md, okw26 (check rule 79).",
    )  # fmt: skip
    bridge_rerun: bool = param(
        True, label="a bridge back onto the curve's own thread",
        doc="On: suspect when the curve's stretch past a bridge, toward its nearer end, lies in "
        "both views within rerun_px of the rest of the curve along its whole length: it runs "
        "over thread pixels the curve already follows, so the "
        "bridge joins no thread of its own (a hook's free end bridged back onto the thread's "
        "own stretch, the curve running twice over it). Off: no such test (before session "
        "21). docs/method.md, okw22.",
    )  # fmt: skip
    rerun_px: float = param(
        8.0, lo=0.0, unit="px", slider=(0.0, 30.0, 0.5), label="rerun: distance",
        doc="A sample past a bridge within this of the rest of the curve in both views runs "
        "over thread the curve already follows (reproj_max_px: a curve point this close to "
        "the thread pixels is on them). The stretch must be twice this long (left view) to "
        "run along the rest: a stub that crosses it at 30 deg or more leaves this distance "
        "within twice it.",
    )  # fmt: skip
    surface_mark: bool = param(
        True, label="a curve moving with the tissue is a mark",
        doc="On: suspect when the surface just beside the curve, measured by stereo in both "
        "views (core/check_mark.moves_with_surface), lies at the curve's own disparity (within "
        "mark_disparity_px) on at least mark_share of the first mark_measures patches that "
        "measure it: the curve moves with the tissue, a mark on it (a vessel, a fibre), not a "
        "thread in front of it (the raw segmentation's own test, core/segment_surface, leaves "
        "a piece in fewer than two 64 px blocks open). Not on given masks: the user's mask says "
        "the thread is there, lying on the tissue or not. Off: no such test (before session 21). "
        "docs/method.md, okw21.",
    )  # fmt: skip
    mark_measures: int = param(
        8, lo=1, slider=(1, 32, 1), label="mark: patches measured",
        doc="Patches beside the curve that must measure a surface for surface_mark to judge "
        "(spread along the curve, both views and both sides in turn; fewer: no finding).",
    )  # fmt: skip
    mark_share: float = param(
        0.75, lo=0.0, hi=1.0, slider=(0.5, 1.0, 0.05), label="mark: share moving with it",
        doc="Share of the mark_measures patches at the curve's disparity that makes it a mark "
        "(the raw segmentation's _MARK_SHARE: a block's test errs now and then).",
    )  # fmt: skip
    mark_disparity_px: float = param(
        1.5, lo=0.0, unit="px", slider=(0.5, 4.0, 0.5), label="mark: same disparity",
        doc="A patch beside the curve within this of the curve's disparity moves with it "
        "(segment_surface.SAME_DISPARITY_PX; the generator's threads float >= 3.5 px in front "
        "of the tissue at its far depth).",
    )  # fmt: skip
    conf_mm: float = param(
        2.0, lo=1e-6, unit="mm", slider=(0.1, 10.0, 0.1), label="confidence scale",
        doc="Expected error at which the confidence is exp(-1).",
    )  # fmt: skip
    score_mm: float = param(
        0.25, lo=1e-6, unit="mm", slider=(0.05, 10.0, 0.005), label="score scale",
        doc="Quality score from the typical expected error e (score_average): 5 below "
        "this, 4 below score_step x this, 3 below score_step^2 x, 2 below score_step^3 x, else "
        "1; suspect curves score at most 2, failed ones 1 (core/check_score.py). Default: the "
        "paper's scale, where a rating below 3 is a failure: 3 still means a curve within about "
        "1 mm. A lab fits score_mm and score_step to its own ratings (the page's agreement "
        "table). Classes fitted to equal shares of right generated curves (0.335 mm, step 1.28) "
        "rank e_S better but call 40 % of right curves failures (docs/method.md, session 10).",
    )  # fmt: skip
    score_step: float = param(
        2.0, lo=1.01, slider=(1.05, 4.0, 0.01), label="score step",
        doc="Factor of typical expected error between two neighbouring scores.",
    )  # fmt: skip
    score_average: Literal["confidence", "geometric"] = param(
        "geometric", label="score's typical error",
        doc="How the score reads the curve's typical expected error e from the points' e_i: "
        "'geometric': the geometric mean of e_i; 'confidence': the error whose confidence is "
        "the curve's mean confidence, -conf_mm ln(mean exp(-e_i / conf_mm)) (a point counts by "
        "its confidence: an untrusted stretch weighs by its share of the curve, never more). "
        "'confidence' ranked the tuning seeds better but the lead's held-out check suites "
        "19250 worse (masked 0.864 -> 0.818): docs/method.md, score19.",
    )  # fmt: skip
    grasp_mm: float = param(
        10.0, lo=0.0, unit="mm", slider=(0.0, 100.0, 1.0), label="grasp distance",
        doc="Distance along the curve from the free end around which the grasp point lies.",
    )  # fmt: skip
    grasp_window_mm: float = param(
        5.0, lo=0.0, unit="mm", slider=(0.0, 50.0, 0.5), label="grasp window",
        doc="The grasp point is the most confident point within this distance of grasp_mm.",
    )  # fmt: skip
    free_end: Literal["auto", "start", "end"] = param(
        "auto", label="free end",
        doc="Which end of the curve is free: 'auto' excludes an end at the image border and "
        "takes the more confident one.",
    )  # fmt: skip
    border_px: float = param(
        5.0, lo=0.0, unit="px", slider=(0.0, 50.0, 1.0), label="border",
        doc="An end closer than this to the image border (either view) is not the free end.",
    )  # fmt: skip
    border_suspect: bool = param(
        False, label="any end at border is suspect",
        doc="On: an end at the image border makes the curve suspect (the thread continues "
        "outside the view and its full length is unknown). Off: only a curve without a free "
        "end is suspect for it: both ends at the border (the visible part may be any piece "
        "of the thread), or one end at the border and the curve shorter than grasp_mm + "
        "grasp_window_mm (the grasp window would reach the border end).",
    )  # fmt: skip
    front_excluded: bool = param(
        True, label="bare bridge: nothing matches in front",
        doc="On: a bridge over bare-looking pixels (bare_share) is also known to lie over a "
        "surface at or behind the curve when its best match is there and every shift more "
        "than 2 px of disparity in front of the curve matches worse by the noise floor (4 "
        "grey levels): no occluder in front could hide the thread, although the tissue's "
        "smooth texture leaves its own disparity broad (the median cost of the shifts 6 px "
        "from the best not 4 levels higher). Off: the best shift must be distinct by that "
        "median alone (before session 19). docs/method.md, okw19.",
    )  # fmt: skip
    contested_support: bool = param(
        True, label="contested matches support nothing",
        doc="On: a reliable match whose right position lies on the same strand of the right "
        "view (row run of P_R) as another reliable match of its row, the two farther apart in "
        "the left view than that run is wide plus 2 px, supports no curve point (its residual "
        "r_i is read from the other reliable matches): one right strand cannot show two left "
        "ones side by side, so one of the two matches is no observation (core/check_support.py, "
        "``contested``). Off: every reliable match supports (session 14's check).",
    )  # fmt: skip
    crossing_degree: int = param(
        4, lo=3, slider=(3, 10, 1), label="crossing degree",
        doc="A keypoint adjacent to at least this many keypoints in the graph A is a crossing "
        "of the thread pixels (order and depth there are ambiguous between the strands).",
    )  # fmt: skip
    ambiguous_mm: float = param(
        10.0, lo=0.0, unit="mm", slider=(0.0, 50.0, 0.5), label="ambiguous error",
        doc="A curve point whose expected error e_i exceeds this, its bound half-width h_i "
        "left out where an agreeing reliable match supports it (r_i <= support_tol_px), is "
        "ambiguous (evidence ``ambiguous_mm``: the length of such points; no finding of its "
        "own, its effect on the length is ``max_unmeasured_mm``'s).",
    )  # fmt: skip


@dataclass(frozen=True)
class CheckResult:
    """The check of one curve.

    ``status``: "ok", "suspect" or "failed"; ``reasons``: every finding, in words.
    ``confidence``: (N,) in [0, 1] per point of ``CameraCurve.points``; ``expected_error_mm``:
    (N,) the predicted error e_i behind it (module docstring). ``grasp``: None when the curve
    is not finite. ``score``: 1-5, the paper's rating scale; ``rating``: the continuous value
    in [1, 5] it is rounded from (core/check_score.py), finer for ranking frames.
    Evidence: reprojection distances (px) of the curve to the thread pixels per view,
    ``coverage_*`` the share of thread pixels near the projected curve, ``depth_range`` the
    curve's (min, max) depth and ``depth_allowed`` the range f B / alpha .. f B / d_min,
    ``length`` (calib units) and ``length_range`` the plausible [L_min, L_max],
    ``path_px`` the 2D length of H, ``bound_excursion`` the largest excursion outside the depth
    bounds (fraction of the half-width), ``solver_status`` the spline's, ``longest_jump_px``
    the longest run of the left projection off the thread, ``overlap_px`` the length of the
    left projection running over another part of the curve, ``beyond_mm`` how far (mm, at the
    end's depth) thread pixels beyond a free end reach: a piece across an occluder, or the
    end's own piece seen on in one view or in both (core/check_beyond.py; 0 when there is
    none), ``fold_px`` the length of the left
    projection running twice over one strand (core/check_fold.py), ``end_added_mm`` the
    length the depth change over a free end's last knot span adds (mm), ``occluded_mm`` how
    far (mm, at the end's depth) the thread at a free end may run on hidden under an occluder
    it runs into in both views (its thread beyond the curve's end and the occluder's reach;
    0 when no end meets one), ``untipped_ends`` the ends ("start", "end") whose dead end (an
    endpoint extension longer than the tip's window, ``Ordering.dead_end``) holds no tip
    matched in both views: the dead end carries no measured depth at all, its depth is the
    end keypoint's copied out to the tip (deviation 55; with a tip matched it is interpolated
    to the tip's).
    """

    status: Status
    reasons: tuple[str, ...]
    confidence: np.ndarray
    expected_error_mm: np.ndarray
    grasp: GraspPoint | None
    score: int
    rating: float
    reproj_left_mean: float
    reproj_left_max: float
    reproj_right_mean: float
    reproj_right_max: float
    coverage_left: float
    coverage_right: float
    depth_range: tuple[float, float]
    depth_allowed: tuple[float, float]
    length: float
    length_range: tuple[float, float]
    path_px: float
    bound_excursion: float
    solver_status: str
    longest_jump_px: float
    overlap_px: float
    crossings: int = 0
    unseen_px: float = 0.0
    unseen_mm: float = 0.0
    longest_bridge_mm: float = 0.0
    unsupported_mm: float = 0.0
    unmeasured_mm: float = 0.0
    contradicted_mm: float = 0.0
    ambiguous_mm: float = 0.0
    ends_at_border: tuple[str, ...] = ()
    beyond_mm: float = 0.0
    fold_px: float = 0.0
    end_added_mm: float = 0.0
    occluded_mm: float = 0.0
    untipped_ends: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def message(self) -> str | None:
        return "; ".join(self.reasons) if self.reasons else None

    def evidence(self) -> dict[str, Any]:
        """The measured evidence as plain values (for JSON, tables and exports)."""
        return {
            "reproj_left_mean_px": self.reproj_left_mean,
            "reproj_left_max_px": self.reproj_left_max,
            "reproj_right_mean_px": self.reproj_right_mean,
            "reproj_right_max_px": self.reproj_right_max,
            "coverage_left": self.coverage_left,
            "coverage_right": self.coverage_right,
            "depth_range": list(self.depth_range),
            "depth_allowed": list(self.depth_allowed),
            "length": self.length,
            "length_range": list(self.length_range),
            "path_px": self.path_px,
            "bound_excursion": self.bound_excursion,
            "solver_status": self.solver_status,
            "longest_jump_px": self.longest_jump_px,
            "overlap_px": self.overlap_px,
            "crossings": self.crossings,
            "unseen_px": self.unseen_px,
            "unseen_mm": self.unseen_mm,
            "longest_bridge_mm": self.longest_bridge_mm,
            "unsupported_mm": self.unsupported_mm,
            "unmeasured_mm": self.unmeasured_mm,
            "contradicted_mm": self.contradicted_mm,
            "ambiguous_mm": self.ambiguous_mm,
            "ends_at_border": list(self.ends_at_border),
            "beyond_mm": self.beyond_mm,
            "fold_px": self.fold_px,
            "end_added_mm": self.end_added_mm,
            "occluded_mm": self.occluded_mm,
            "untipped_ends": list(self.untipped_ends),
        }


def check_curve(
    lifted: LiftedPair,
    stereo: StereoResult,
    rel: ReliabilityResult,
    ordering: Ordering,
    bounds: Bounds,
    spline: SplineResult,
    curve: CameraCurve,
    calib: StereoCalibration,
    p: CheckParams = CheckParams(),
) -> CheckResult:
    """Check the camera-frame curve against the images, the depth range and the bounds."""
    # a diverged curve overflows: it is reported, not warned; each free end's frame is taken
    # once a run (check_beyond.end_frames_kept)
    with np.errstate(all="ignore"), end_frames_kept():
        return _check(lifted, stereo, rel, ordering, bounds, spline, curve, calib, p)


def _check(
    lifted: LiftedPair,
    stereo: StereoResult,
    rel: ReliabilityResult,
    ordering: Ordering,
    bounds: Bounds,
    spline: SplineResult,
    curve: CameraCurve,
    calib: StereoCalibration,
    p: CheckParams,
) -> CheckResult:
    pts = np.asarray(curve.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise ValueError(f"curve points must be (N >= 2, 3), got {pts.shape}")
    n = len(pts)
    f, B = calib.focal, calib.baseline
    alpha = stereo.d_range[1]
    # the search's own far end (stereo.z_far_mm): a depth beyond it was never searched, so a
    # curve there is no measurement (a bridge's depth run away), whatever d_min allows
    d_lo = max(p.min_disparity_px, float(stereo.d_range[0]))
    z_allowed = (f * B / alpha, f * B / d_lo if d_lo > 0 else np.inf)
    findings: list[tuple[Status, str]] = []
    unit = calib.unit

    if not np.isfinite(pts).all():
        bad = int(np.sum(~np.all(np.isfinite(pts), axis=1)))
        return _failed_early(
            f"the curve is not finite ({bad} of {n} points are NaN or infinite)",
            n, z_allowed, spline, bounds,
        )  # fmt: skip

    # Depths: in front of both cameras and inside the range of the disparity search.
    z = pts[:, 2]
    depth_range = (float(z.min()), float(z.max()))
    hom = np.column_stack([pts, np.ones(n)])
    h_r = hom @ calib.P2.T  # the right view's projection; its third row: the right depths
    z_right = h_r[:, 2]
    if (z <= 0).any() or (z_right <= 0).any():
        findings.append(
            ("failed", f"{int(np.sum((z <= 0) | (z_right <= 0)))} of {n} points lie behind a "
             f"camera (depth {depth_range[0]:.4g} to {depth_range[1]:.4g} {unit})")
        )  # fmt: skip
    else:
        disp = f * B / z
        tol = p.disparity_tol_px
        if disp.max() > alpha + tol or disp.min() < d_lo - tol:
            findings.append(
                ("failed", f"depth {depth_range[0]:.4g} to {depth_range[1]:.4g} {unit} leaves "
                 f"the range the disparity search allows ({z_allowed[0]:.4g} to "
                 f"{z_allowed[1]:.4g} {unit}, disparity {d_lo:g}..{alpha} px)")
            )  # fmt: skip

    # Reprojection onto the thread pixels of both views (one distance transform per view);
    # a point projecting outside a view cannot be seen there and is left out of its figures.
    H, W = lifted.P_L.shape
    uv_l, uv_r = _dehomogenise(hom @ calib.P1.T), _dehomogenise(h_r)
    in_l, in_r = _in_image(uv_l, (H, W)), _in_image(uv_r, (H, W))
    margin = p.reproj_fail_px + 2.0
    field_l, field_r = mask_field(lifted.P_L, margin), mask_field(lifted.P_R, margin)
    view_l, view_r = _view(lifted.P_L, field_l), _view(lifted.P_R, field_r)
    rho_l, rho_r = field_l.at(uv_l), field_r.at(uv_r)
    # Ordering anomalies (1): runs of the left projection across unsegmented pixels. A short
    # run between two thread parts is a bridge (an occluded or unsegmented stretch) and is
    # left out of the reprojection figures; a long one is a jump.
    # The distances of a bridge's points measure the occluder's width, not an error: a bridge
    # is left out of the reprojection figures and judged by its unobserved 3D length instead.
    mm = calib.mm_per_unit
    # (np.diff's own subtraction, without its layers)
    d3 = row_norms(pts[1:] - pts[:-1])  # 3D steps, calib units (the grasp point's too)
    step3 = d3 * mm
    step = row_norms(uv_l[1:] - uv_l[:-1])
    step_r = row_norms(uv_r[1:] - uv_r[:-1])
    off_l, off_r = in_l & (rho_l > p.jump_px), in_r & (rho_r > p.jump_px)
    # samples outside both images between seen ones: a stretch no view observes (rule 81)
    outside = _outside_between(in_l, in_r) if p.bridge_outside else np.zeros(n, dtype=bool)
    if outside.any():
        off_l, off_r = off_l | outside, off_r | outside
    run_l, run3_l, bridge_l = _off_thread_runs(off_l, step, step3)
    run_r, run3_r, bridge_r = _off_thread_runs(off_r, step_r, step3)
    if p.bridge_alongside and (bridge_l | bridge_r).any():
        # a run beside the thread (within the reprojection limit in both views all along) is
        # observed: the reprojection test judges it, not the bridge test
        near = in_l & in_r & (rho_l <= p.reproj_max_px) & (rho_r <= p.reproj_max_px)
        for i0, i1 in _runs(bridge_l) + _runs(bridge_r):
            if near[i0:i1].all():
                for off, run, run3, bridge in ((off_l, run_l, run3_l, bridge_l),
                                               (off_r, run_r, run3_r, bridge_r)):  # fmt: skip
                    keep = ~bridge[i0:i1]  # an end run of the view is left as it is
                    off[i0:i1] &= keep
                    run[i0:i1] *= keep
                    run3[i0:i1] *= keep
                    bridge[i0:i1] = False
    longest_jump = float(max(run_l.max(), run_r.max()))
    ends = (off_l & ~bridge_l) | (off_r & ~bridge_r)
    bare = (
        _BareBackground(lifted, (field_l, field_r), p)
        if (bridge_l | bridge_r | ends).any()
        else None
    )
    # An end of the curve off the thread in one view only, over pixels that are not bare
    # background there (an occluder), while the other view sees the thread: hidden in that
    # view, like a part outside the right image (not observed there, not an error).
    hidden_l = _hidden_end(off_l & ~bridge_l, ~off_l & in_l, off_r, uv_l, 0, bare, p)
    hidden_r = _hidden_end(off_r & ~bridge_r, ~off_r & in_r, off_l, uv_r, 1, bare, p)
    overshoot = float(
        max((run_l * ~(bridge_l | hidden_l)).max(), (run_r * ~(bridge_r | hidden_r)).max())
    )
    longest_bridge = float(max((run3_l * bridge_l).max(), (run3_r * bridge_r).max()))
    if overshoot > p.max_jump_px:
        findings.append(
            ("suspect", f"an end of the curve runs {overshoot:.0f} px off the thread pixels "
             f"(limit {p.max_jump_px:g} px)")
        )  # fmt: skip
    # Each bridge is judged by what can be checked (no loop, not over bare background); an
    # evidenced one is allowed up to max_bridge_mm, any other one up to
    # max_unobserved_mm. Its points get a growing expected error (below) instead.
    s3 = np.concatenate([[0.0], step3.cumsum()])
    bridge_gap = np.zeros(n)  # mm along the curve to the nearest observed end of a bridge
    worst: tuple[float, str] | None = None
    rerun: tuple[float, float, float] | None = None
    for i0, i1 in _runs(bridge_l) + _runs(bridge_r):
        a, b = i0 - 1, i1  # the observed samples on either side
        len3 = float(s3[b] - s3[a])
        bridge_gap[i0:i1] = np.maximum(
            bridge_gap[i0:i1], np.minimum(s3[i0:i1] - s3[a], s3[b] - s3[i0:i1])
        )
        if p.bridge_rerun and rerun is None:
            far, end_px = _rerun_px(uv_l, uv_r, a, b)
            # within rerun_px over twice that length (left view): it runs along the rest, no
            # stub crossing it (a stretch at 30 deg or more to a line leaves rerun_px of it
            # within 2 rerun_px)
            if far <= p.rerun_px and end_px >= 2.0 * p.rerun_px:
                rerun = (len3, end_px, far)
        if not len3 > min(p.max_bridge_mm, p.max_unobserved_mm):
            continue  # within either limit: the evidence (its costly part) cannot matter
        why = _bridge_evidence(pts, uv_l, uv_r, s3, step, a, b, mm, bare, p)
        if why is None and outside[i0:i1].any():
            out_mm = float(step3[a:b][outside[a:b] | outside[a + 1 : b + 1]].sum())
            why = (f"{out_mm:.1f} mm of it lie "
                   "outside both images: no occluder hides it, no view observes it")  # fmt: skip
        if why is None and p.bridge_left_behind and len3 > p.max_unobserved_mm:
            why = _left_behind(uv_l, uv_r, lifted, z, a, b, f, mm, p)
        limit = p.max_bridge_mm if why is None else p.max_unobserved_mm
        # an evidenced bridge is judged by how far its occluder lets the hidden thread stray,
        # where that can be measured
        if len3 > limit and why is None and _bridge_confined(lifted, uv_l, uv_r, z, a, b, f, B,
                                                              mm, limit, bare, p):  # fmt: skip
            continue  # the occluder holds the hidden thread within half the limit of it
        if len3 > limit and (worst is None or len3 > worst[0]):
            worst = (len3, why or "")
    if rerun is not None:
        findings.append(
            ("suspect", f"past a {rerun[0]:.1f} mm bridge the curve's end ({rerun[1]:.0f} px) runs "
             f"over thread pixels the curve already follows (within {rerun[2]:.1f} px in both "
             f"views, limit {p.rerun_px:g} px): the bridge leads to no thread of its own")
        )  # fmt: skip
    if worst is not None:
        len3, why = worst
        findings.append(
            ("suspect", f"the curve bridges {len3:.1f} mm across unsegmented pixels in one "
             f"stretch: its shape there is interpolated, not observed (limit "
             f"{p.max_unobserved_mm if why else p.max_bridge_mm:g} mm"
             + (f"; {why})" if why else ")"))
        )  # fmt: skip
    rep = []
    views = (
        ("left", rho_l, in_l & ~bridge_l & ~hidden_l),
        ("right", rho_r, in_r & ~bridge_r & ~hidden_r),
    )
    for side, rho, inside in views:
        count = int(inside.sum())
        if count < 2:
            findings.append(("failed", f"the curve lies outside the {side} image"))
            rep += [float("nan"), float("nan")]
            continue
        seen = rho[inside]  # the mean as np.mean takes it: numpy's sum over the count
        mean, mx = float(seen.sum() / count), float(seen.max())
        rep += [mean, mx]
        if mx > p.reproj_fail_px:
            findings.append(
                ("failed", f"the curve's {side} projection lies {_px(mx, margin)} from the "
                 f"thread pixels (limit {p.reproj_fail_px:g} px)")
            )  # fmt: skip
        elif mean > p.reproj_mean_px or mx > p.reproj_max_px:
            findings.append(
                ("suspect", f"the curve's {side} projection lies {mean:.2f} px (mean) and up to "
                 f"{mx:.1f} px from the thread pixels (limits {p.reproj_mean_px:g} / "
                 f"{p.reproj_max_px:g} px)")
            )  # fmt: skip

    if p.coverage_seen_both:
        # a thread pixel the other view cannot see at any depth of the curve (a strip along
        # the image's side as wide as the curve's smallest disparity) no curve can cover
        disp = uv_l[:, 0] - uv_r[:, 0]
        disp = disp[in_l & in_r & np.isfinite(disp)]
        if disp.size:
            d_lo = float(disp.min())
            view_l = _columns_within(view_l, d_lo, float(W))  # the right view sees x - d
            view_r = _columns_within(view_r, float("-inf"), W - 1 - d_lo + 1e-9)
    cov_l = _coverage(view_l, uv_l, in_l, p.cover_px)
    cov_r = _coverage(view_r, uv_r, in_r, p.cover_px)
    for side, cov in (("left", cov_l), ("right", cov_r)):
        if cov < p.coverage_min:
            findings.append(
                ("suspect", f"the curve covers {100 * cov:.0f} % of the {side} thread pixels "
                 f"(at least {100 * p.coverage_min:.0f} % expected)")
            )  # fmt: skip
    one_view = (in_l & ~in_r) | hidden_l | hidden_r
    unseen_px = unseen_mm = 0.0  # (a sum of zeros: no point seen in one view only)
    if one_view.any():
        unseen_px = float(np.where(one_view, np.concatenate((step, [0.0])), 0.0).sum())
        unseen_mm = float(np.where(one_view, np.concatenate((step3, [0.0])), 0.0).sum())
    if unseen_mm > p.max_unobserved_mm:
        findings.append(
            ("suspect", f"{unseen_mm:.1f} mm ({unseen_px:.0f} px) of the curve lie outside the "
             f"right image or hidden in one view: their depth is not observed (limit {p.max_unobserved_mm:g} mm)")
        )  # fmt: skip
    at_border = tuple(
        end for end, i in (("start", 0), ("end", -1))
        if _border_distance(uv_l[i], uv_r[i], (H, W)) < p.border_px
    )  # fmt: skip
    if p.border_suspect:
        for end in at_border:
            findings.append(
                ("suspect", f"the curve's {end} is at the image border: the thread may "
                 "continue outside the view, its full length is unknown")
            )  # fmt: skip
    elif len(at_border) == 2:
        findings.append(
            ("suspect", "both ends of the curve are at the image border: no free end is seen, "
             "the visible part may be any piece of the thread")
        )  # fmt: skip
    elif at_border and curve.length * mm < p.grasp_mm + p.grasp_window_mm:
        findings.append(
            ("suspect", f"the curve's {at_border[0]} is at the image border and the curve is "
             f"{curve.length * mm:.1f} mm long, shorter than the grasp reach "
             f"({p.grasp_mm + p.grasp_window_mm:g} mm): no free end to grasp from")
        )  # fmt: skip

    # A curve that stops short at an occluder: uncovered thread beyond a free end, across
    # pixels that are neither thread nor bare background, in both views (core/check_beyond).
    free = tuple(e for e in ("start", "end") if e not in at_border)
    missing = 0.0
    end_added = 0.0
    occluded = 0.0
    unoccluded: list[str] = []  # the free ends with no occluder in front of them
    knowns = {}  # per free end, extension_far's reading (rule 81)
    if free and bare is None:
        bare = _BareBackground(lifted, (field_l, field_r), p)
    for end in free:  # a free end ends at one 3D point: both views see the thread stop there
        z_end = z[0] if end == "start" else z[-1]
        unobserved_px = p.max_unobserved_mm / mm * f / z_end  # the limit's length at the end
        reach = min(unobserved_px, p.cut_end_px + CUT_REACH_PX)
        known = extension_far((uv_l, uv_r), (lifted.P_L, lifted.P_R), end, reach,
                              p.cover_px + BEYOND_COVER_PX, p.cut_end_px)  # fmt: skip
        knowns[end] = known
        if p.seen_beyond and min(known[0]) + 2.0 >= reach:  # both views see on to the reach
            seen = extension((uv_l, uv_r), (lifted.P_L, lifted.P_R), end,
                             unobserved_px + AHEAD_STEP_PX, p.cover_px + BEYOND_COVER_PX,
                             p.cut_end_px)  # fmt: skip
            seen_px = min(seen)
            missing = max(missing, seen_px * z_end / f * mm)
            if seen_px > unobserved_px:
                findings.append(
                    ("suspect", f"the thread goes on {seen_px:.0f} px "
                     f"({seen_px * z_end / f * mm:.1f} mm) past the curve's {end} in both "
                     "views, not covered by the curve: the curve stops short of thread both "
                     f"views show (limit {p.max_unobserved_mm:g} mm)")
                )  # fmt: skip
        # the stopping view's patches past the end measured in front of it: an occluder there,
        # whatever its grey (core/check_beyond.surface_past_end)
        front_past = (
            partial(_measured_in_front, (uv_l, uv_r), lifted, end, f * B / z_end)
            if p.cut_front_stereo
            else None
        )
        cut = cut_end((uv_l, uv_r), (lifted.P_L, lifted.P_R), end, reach, p.cut_end_px,
                      p.cover_px + BEYOND_COVER_PX, bare, p.bare_share, see_px=unobserved_px,
                      known=known[0], front_past=front_past,
                      tip_seen=p.cut_tip_seen, tip_front=partial(_front_at_tip, lifted, f * B / z_end))  # fmt: skip
        # seen: the far view's thread stops inside see_px = unobserved_px (core/check_beyond)
        hidden = cut is not None and not cut.seen
        if hidden and max(cut.ext) + 2.0 <= unobserved_px:
            # An occluder that cuts the thread in one view lies in front of the end there; a
            # surface at or behind the end's depth just past it (stereo) is none: that view's
            # thread goes on unsegmented, as far as the other view sees it (within the limit).
            stop = 1 if cut.view == "left" else 0
            uv_stop, grey_stop = (uv_l, uv_r)[stop], (lifted.grey_L, lifted.grey_R)[stop]
            tip = uv_stop[0] if end == "start" else uv_stop[-1]
            mask_stop = (lifted.P_L, lifted.P_R)[stop]
            plain = plain_surface(grey_stop, mask_stop, tip, _end_way(uv_stop, end), p.bare_sigma)
            front = surface_past_end(
                uv_stop, (lifted.grey_L, lifted.grey_R), (lifted.P_L, lifted.P_R), stop, end,
                f * B / z_end, plain,
            )  # fmt: skip
            hidden = front is None or front > AHEAD_NEAR_PX
        # A free end is followed, in both views, by the surface the thread lies on (at or
        # behind its depth, measured by stereo: grey levels cannot tell an instrument from the
        # tissue); a thread that runs into an occluder in both views may go on hidden under
        # it, as far as the occluder reaches (core/check_beyond.end_occluder).
        occ = end_occluder(
            (uv_l, uv_r), (lifted.P_L, lifted.P_R), (lifted.grey_L, lifted.grey_R), end,
            f * B / z_end, known, reach, p.cover_px + BEYOND_COVER_PX, unobserved_px,
            unobserved_px + AHEAD_STEP_PX, plain_sigma=p.bare_sigma, untextured=p.blank_occluder,
            next_measure=p.blank_next_measure, past_untold=p.occluder_exit,
        )  # fmt: skip
        # the occluder's reach, walked in both views, bounds what a cut end may hide
        bounded = occ is not None and not occ.walked_out and occ.reach_px <= unobserved_px
        if hidden and not bounded:
            findings.append(
                ("suspect", f"the {cut.view} view sees the thread {max(cut.ext):.0f} px beyond "
                 f"the curve's {end}, the other {min(cut.ext):.0f} px, over no bare background "
                 "or a surface in front of the end: the end is cut by an occluder (a free end "
                 "stops at one point in both views), the thread may go on hidden under it")
            )  # fmt: skip
        elif cut is not None:  # the thread's end is seen in one view: the curve misses that much
            missing = max(missing, max(cut.ext) * z_end / f * mm)
        if occ is None:
            unoccluded.append(end)
            # No occluder in front of the end: a thread line the segmentation dropped that goes
            # on past it, in both views at its depth, makes it no end (core/check_beyond).
            if p.line_level > 0.0 and lifted.score_L is not None and lifted.score_R is not None:
                line_px = thread_line_beyond(
                    (lifted.score_L, lifted.score_R), (uv_l, uv_r), end, f * B / z_end,
                    unobserved_px + AHEAD_STEP_PX, p.line_level,
                )  # fmt: skip
                if line_px > unobserved_px:
                    findings.append(
                        ("suspect", f"a thread line goes on {line_px:.0f} px "
                         f"({line_px * z_end / f * mm:.1f} mm) past the curve's {end}, in "
                         "both views at the end's depth, bending on from the curve's way "
                         "(thread score): the thread goes on past the end, not reconstructed "
                         f"(limit {p.max_unobserved_mm:g} mm)")
                    )  # fmt: skip
            continue
        reach_mm = occ.reach_px * z_end / f * mm
        occluded = max(occluded, reach_mm)
        if p.hidden_piece and occ.reach_px <= unobserved_px:
            # the walk bounds the occluder along the end's way; a piece one view shows past it
            # where the other view's occluder hides the thread bounds it from below
            shown = hidden_piece(
                (uv_l, uv_r), (lifted.P_L, lifted.P_R), end, f * B / z_end,
                p.cover_px + BEYOND_COVER_PX, p.max_bridge_mm / mm * f / z_end,
                (lifted.grey_L, lifted.grey_R), bare,
            )  # fmt: skip
            if shown is not None:
                missing = max(missing, shown[1] * z_end / f * mm)
                if shown[1] > unobserved_px:
                    findings.append(
                        ("suspect", f"the thread at the curve's {end} runs into an occluder "
                         f"in both views, and the {shown[0]} view shows a piece of thread "
                         f"past it that the other view's occluder hides, reaching "
                         f"{shown[1]:.0f} px ({shown[1] * z_end / f * mm:.1f} mm) from the "
                         "end: the thread runs on under the occluder (limit "
                         f"{p.max_unobserved_mm:g} mm)")
                    )  # fmt: skip
        if occ.reach_px > unobserved_px:
            findings.append(
                ("suspect", f"the thread at the curve's {end} runs into an occluder "
                 + ("in both views " if occ.blank is None else
                    f"(the {occ.blank} view blank there: untextured, unlike the surface "
                    "beside the end) ")
                 + f"({occ.front_px:.0f} px of disparity in front of it; the {occ.view} "
                 f"view sees {occ.ext_px:.0f} px of thread beyond the end): it may go on "
                 f"hidden for {'at least ' if occ.walked_out else ''}{reach_mm:.1f} mm, as far "
                 "as the occluder reaches (limit "
                 f"{p.max_unobserved_mm:g} mm)")
            )  # fmt: skip
    # A free end is matched from one side, with the matching window over the thread's end and
    # what lies beyond it (an occluder's edge pulls the depth towards its own): a depth change
    # over the end's last knot span is length the matches there cannot vouch for.
    n_spans = max(len(spline.ctrl) - int(spline.degree), 1)
    s2 = arc_px(step)  # the left projection's arc length: ends, strands, folds, errors
    for end in free:
        added = _end_added_length(step3, step, z, f / mm, n_spans, end, s2)
        end_added = max(end_added, added)
        if added > p.max_unmeasured_mm:
            findings.append(
                ("suspect", f"the curve's depth change over the last knot span at its {end} "
                 f"adds {added:.1f} mm to its length (limit {p.max_unmeasured_mm:g} mm): an "
                 "end is matched from one side, over the thread's end and what lies beyond "
                 "it (an occluder's edge pulls the depth towards its own)")
            )  # fmt: skip
    if free and cov_l < 1.0 and cov_r < 1.0:
        found = beyond_ends(
            (uv_l, uv_r), (lifted.P_L, lifted.P_R), free, {"start": z[0], "end": z[-1]}, f,
            p.cover_px + BEYOND_COVER_PX, p.max_bridge_mm / mm, bare, p.bare_share,
            scores=(lambda: (lifted.score_L, lifted.score_R)) if p.beyond_one_view else None,
            disparity={"start": f * B / z[0], "end": f * B / z[-1]},
        )  # fmt: skip
        for b in found:
            missing = max(missing, b.missing * mm)
            if b.missing * mm > p.max_unobserved_mm:
                findings.append(
                    ("suspect", f"a piece of thread pixels lies beyond the curve's {b.end} "
                     f"across an occluder in both views ({b.gap_px:.0f} px away, reaching "
                     f"{b.reach_px:.0f} px): the curve probably stops short by at least "
                     f"{b.missing * mm:.1f} mm (limit {p.max_unobserved_mm:g} mm)")
                )  # fmt: skip
                continue
            other = "start" if b.end == "end" else "end"
            if (
                p.both_ends_level > 0.0
                and other in unoccluded
                and lifted.score_L is not None
                and lifted.score_R is not None
            ):
                # the piece beyond this end and a thread line past the other: the curve misses
                # thread at both ends, and the length error is their sum
                z_o = z[0] if other == "start" else z[-1]
                line_px = thread_line_beyond(
                    (lifted.score_L, lifted.score_R), (uv_l, uv_r), other, f * B / z_o,
                    p.max_unobserved_mm / mm * f / z_o + AHEAD_STEP_PX, p.both_ends_level,
                )  # fmt: skip
                line_mm = line_px * z_o / f * mm
                if b.missing * mm + line_mm > p.max_unobserved_mm:
                    findings.append(
                        ("suspect", f"a piece of thread pixels lies beyond the curve's {b.end} "
                         f"across an occluder ({b.missing * mm:.1f} mm) and a thread line goes "
                         f"on {line_px:.0f} px ({line_mm:.1f} mm) past its {other} in both "
                         "views: the curve stops short at both ends by "
                         f"{b.missing * mm + line_mm:.1f} mm together (limit "
                         f"{p.max_unobserved_mm:g} mm)")
                    )  # fmt: skip

    # Length against the 2D path length and the depth span of the bounds.
    path_px = float(bounds.s[-1])
    z_lo = float(max(bounds.lower.min(), z_allowed[0]))
    z_hi = float(min(bounds.upper.max(), z_allowed[1]))
    L_min = path_px * z_lo / f
    L_max = path_px * z_hi / f + p.depth_turns * max(z_hi - z_lo, 0.0)
    length = float(curve.length)
    if not (1 - p.length_tol) * L_min <= length <= (1 + p.length_tol) * L_max:
        findings.append(
            ("suspect", f"length {length:.4g} {unit} is implausible for a {path_px:.0f} px path "
             f"at depths {z_lo:.4g} to {z_hi:.4g} {unit} (expected {L_min:.4g} to "
             f"{L_max:.4g} {unit})")
        )  # fmt: skip

    # Bound excursions of the returned spline and the solver's status.
    zs = _spline_z(spline)
    excursions = _excursions(spline, bounds, zs)
    excursion = _excursion(spline, excursions)
    if not spline.ok and p.solver_suspect:
        findings.append(
            ("suspect", f"the MVS solver's result was rejected ({spline.status}: "
             f"{spline.message}); the curve shown is the initial spline (fallback)")
        )  # fmt: skip

    # Ordering anomalies (2): crossings of the thread pixels, overlaps the pixels do not show.
    K = ordering.n_clusters
    degree = np.bincount(ordering.edges.ravel(), minlength=K) if ordering.edges.size else []
    crossings = int((np.asarray(degree) >= p.crossing_degree).sum())
    z_pos = np.maximum(z, 1e-12)
    # a reliable match sharing its right strand with one of its row too far away in the left
    # view to be that strand is no observation of the depth (one of the two is not seen)
    rel_s = rel
    if p.contested_support and lifted.P_R is not None:
        kept = uncontested(stereo, rel, lifted.P_R, CONTEST_SLACK_PX)  # cached: one array
        if kept is not None:
            rel_s = replace(rel, reliable=kept)
    r = _disparity_residual(stereo, rel_s, uv_l, f * B / z_pos, p.support_px)
    supported = r <= p.support_tol_px
    strand = _strand_samples(crossings, in_l & (rho_l <= p.jump_px), supported, step, p, s2)
    overlap = _overlap(uv_l, step, p.loop_px, f * B / z_pos, strand, p.crossing_disparity_px)
    if overlap > p.max_overlap_px:
        findings.append(
            ("suspect", f"{overlap:.0f} px of the curve run over another part of it (a loop or "
             f"doubling back the thread pixels do not show; limit {p.max_overlap_px:g} px)")
        )  # fmt: skip
    fold = fold_length(
        uv_l, step, in_l & (rho_l <= p.jump_px), f * B / z_pos, p.fold_px,
        p.crossing_disparity_px, s2,
    )  # fmt: skip
    if fold > p.max_overlap_px:
        findings.append(
            ("suspect", f"the curve runs twice over {fold:.0f} px of one strand (a fold: back and "
             "forth along the same thread pixels at the same depth, longer than the thread; "
             f"limit {p.max_overlap_px:g} px)")
        )  # fmt: skip

    # Two points far apart along the curve at one place in 3D (core/check_fold.self_contact):
    # the thread cannot pass through itself, the curve came back to a strand it left.
    touch = (
        self_contact(uv_l, pts * mm, s3, p.fold_px, f, p.max_unobserved_mm)
        if p.self_contact
        else None
    )
    if touch is not None:
        findings.append(
            ("suspect", f"the curve passes through itself: two of its points {touch.apart:.0f} "
             f"mm apart along it lie {touch.distance:.2f} mm apart (less than half a thread's "
             f"width, {touch.limit:.2f} mm) at a point of the left view ({touch.at[0]:.0f}, "
             f"{touch.at[1]:.0f} px): a thread's strands lie a width apart, so its pieces may "
             f"be joined in a wrong order (limit {p.max_unobserved_mm:g} mm apart)")
        )  # fmt: skip
    # A point where the projection turns back, with the curve heading back from it to an end
    # (core/check_fold.end_reversal), the branch on the surface and the rest in front of it:
    # a mark on the surface joined to the thread there.
    rev = end_reversal(uv_l, s3, step) if p.end_reversal else None
    if (
        rev is not None
        and rev.length > p.max_unobserved_mm
        and _mark_joined(lifted, uv_l, f * B / np.maximum(z, 1e-12), rev)
    ):
        findings.append(
            ("suspect", f"the curve turns back by {rev.turn_deg:.0f} deg at a point of the left "
             f"view ({rev.at[0]:.0f}, {rev.at[1]:.0f} px) and runs "
             f"back from it {rev.length:.1f} mm to its {rev.end}, on the surface beside it "
             "while the curve before the turn floats in front of it: that branch may be a mark "
             f"on the surface joined to the thread there (limit {p.max_unobserved_mm:g} mm)")
        )  # fmt: skip
    # The surface beside the curve at the curve's own depth in both views: a mark on the tissue
    # (a vessel, a fibre the segmentation could not judge), not a thread in front of it. A mask
    # the user gave says what the thread is: a thread lying on the tissue stays a thread.
    if p.surface_mark and lifted.method != "mask":
        mark = moves_with_surface(
            (uv_l, uv_r), (lifted.grey_L, lifted.grey_R), (lifted.P_L, lifted.P_R),
            f * B / z_pos, p.mark_disparity_px, p.mark_measures, p.mark_share,
        )  # fmt: skip
        if mark.measured >= p.mark_measures and mark.along >= p.mark_share * mark.measured:
            findings.append(
                ("suspect", f"the surface beside the curve lies at the curve's own depth "
                 f"(within {p.mark_disparity_px:g} px of disparity) at {mark.along} of the "
                 f"{mark.measured} places stereo measures it in the two views: the curve moves "
                 "with the tissue, a mark on it (a vessel, a fibre), not a thread in front of "
                 f"it (limit {p.mark_share:.0%})")
            )  # fmt: skip
    # An end along the rows whose far view sees the thread go on: which view's end is cut
    # the images do not tell, and the end's disparity lies between the two readings, within
    # one strand's room from the nearest supported point past the end's window (rule 81).
    for end in knowns if p.row_end_tip else ():
        z_end = z[0] if end == "start" else z[-1]
        alt = _row_end_tip((uv_l, uv_r), knowns[end], end, f * B / z_end, p.cut_end_px,
                           p.cover_px, (d_lo, alpha), supported)  # fmt: skip
        if alt is not None and abs(f * B / alt[1] - z_end) * mm > p.max_unobserved_mm:
            findings.append(
                ("suspect", f"the {alt[0]} view sees the thread {alt[2]:.0f} px past the "
                 f"curve's {end} along the rows, its tip on the other view's end row, and no "
                 f"reliable match for {alt[3]:.0f} px: the end's depth may lie anywhere from "
                 f"{z_end * mm:.1f} to {f * B / alt[1] * mm:.1f} mm (disparity {alt[1]:.1f} "
                 "px): along the rows only the thread's ends fix the depth, and which view's "
                 f"end is cut the images do not tell (limit {p.max_unobserved_mm:g} mm)")
            )  # fmt: skip
    # Per-point expected error and confidence.
    unsupported = _unsupported_travel(z, supported) * mm
    if unsupported > p.max_unsupported_mm:
        findings.append(
            ("suspect", f"the curve's depth travels {unsupported:.1f} mm back and forth where "
             f"no reliable match supports it (limit {p.max_unsupported_mm:g} mm): length the "
             "images do not show")
        )  # fmt: skip
    # A crossing (a keypoint of high degree in A, or the curve's own left projection running
    # over itself: the segmentation may merge the strands so that no keypoint shows it) makes
    # order and depth ambiguous between the strands. The ambiguity's effect on the curve is the
    # length its depth change adds where no reliable match measures it: a wrong branch joins
    # two strands at different depths through such a stretch. Without a crossing, unsupported
    # depth change is a tilted thread (the paper's frames: up to 29 mm on right curves).
    unmeasured = _unmeasured_length(step3, step, z_pos, supported, f / mm)
    if (crossings or overlap > 0) and unmeasured > p.max_unmeasured_mm:
        where = (
            f"the thread pixels cross or branch at {crossings} keypoint(s)" if crossings
            else f"the curve crosses itself in the left image ({overlap:.0f} px overlap)"
        )  # fmt: skip
        findings.append(
            ("suspect", f"{where} and the curve's depth change adds {unmeasured:.1f} mm to its "
             f"length where no reliable match supports it (limit {p.max_unmeasured_mm:g} mm): "
             "the strands' order or depth may be mixed up")
        )  # fmt: skip
    # Depth change where the reliable matches under the curve all give another depth (by
    # crossing_disparity_px or more): the curve runs at one strand's depth over another's
    # pixels, or between two strands (a wrong branch at a crossing no keypoint shows).
    # (a point a reliable match supports has an agreeing match near it: tested on the others)
    free_pts = np.flatnonzero(~supported)
    against_pts = np.zeros(n, dtype=bool)
    against_pts[free_pts] = contradicted(
        stereo, rel, uv_l[free_pts], f * B / z_pos[free_pts], CONTRA_PX, p.crossing_disparity_px
    )
    against = _unmeasured_length(step3, step, z_pos, ~against_pts, f / mm)
    if against > p.max_unmeasured_mm:
        findings.append(
            ("suspect", f"the curve's depth change adds {against:.1f} mm to its length over "
             "thread pixels whose reliable matches all give another depth (limit "
             f"{p.max_unmeasured_mm:g} mm): it may join two strands at different depths")
        )  # fmt: skip
    unsupported_exc = _excursion(spline, excursions, ~supported)
    if unsupported_exc > p.bound_tol:
        findings.append(
            ("suspect", f"the curve leaves its depth bounds by {unsupported_exc:.2f} of the "
             f"bound half-width where no reliable match supports it (limit {p.bound_tol:g})")
        )  # fmt: skip
    h = bound_halfwidth_px(spline, bounds, n, f * B)
    rho = np.maximum(
        np.where(bridge_l | hidden_l, 0.0, rho_l),
        np.where(in_r & ~bridge_r & ~hidden_r, rho_r, 0.0),
    )
    pe = point_errors(
        z_pos, (z <= 0) | (z_right <= 0), r, rho, bridge_gap, step, s3, spline, f, f * B, mm, p,
        s2=s2, supported=supported,
    )  # fmt: skip
    e_mm, lateral, conf = pe.e_mm, pe.lateral_mm, pe.confidence

    # Ambiguous depth (evidence only): a wide bound where no agreeing reliable match pins the
    # depth (where one does, the strands' depths are measured there, however wide the bounds).
    # Whether an ambiguity matters is its effect on the curve: the unmeasured length above.
    h_free = np.where(supported, 0.0, h)
    e_free = (z_pos**2 / (f * B)) * np.sqrt(p.sigma_disparity_px**2 + r**2 + h_free**2) * mm
    e_free = np.where(np.isfinite(e_mm), e_free + lateral, np.inf)
    amb = e_free > p.ambiguous_mm
    ambiguous = float((step3 * (amb[1:] | amb[:-1])).sum())
    status: Status = max((s for s, _ in findings), key=_RANK.__getitem__, default="ok")
    score, rating = quality_score(e_mm, status, p)
    grasp = grasp_point(pts, conf, uv_l, uv_r, (H, W), mm, p, d3)
    return CheckResult(
        status=status,
        reasons=tuple(msg for _, msg in sorted(findings, key=lambda x: -_RANK[x[0]])),
        confidence=conf,
        expected_error_mm=e_mm,
        grasp=grasp,
        score=score,
        rating=rating,
        reproj_left_mean=rep[0],
        reproj_left_max=rep[1],
        reproj_right_mean=rep[2],
        reproj_right_max=rep[3],
        coverage_left=cov_l,
        coverage_right=cov_r,
        depth_range=depth_range,
        depth_allowed=z_allowed,
        length=length,
        length_range=(L_min, L_max),
        path_px=path_px,
        bound_excursion=excursion,
        solver_status=spline.status,
        longest_jump_px=longest_jump,
        overlap_px=overlap,
        crossings=crossings,
        unseen_px=unseen_px,
        unseen_mm=unseen_mm,
        longest_bridge_mm=longest_bridge,
        unsupported_mm=unsupported,
        unmeasured_mm=unmeasured,
        contradicted_mm=against,
        ambiguous_mm=ambiguous,
        ends_at_border=at_border,
        beyond_mm=missing,
        fold_px=fold,
        end_added_mm=end_added,
        occluded_mm=occluded,
        untipped_ends=untipped_ends(ordering),
    )


def untipped_ends(ordering: Ordering) -> tuple[str, ...]:
    """The ends of the ordered path ("start", "end") that are a dead end's tip
    (``Ordering.dead_end``: an endpoint extension longer than the tip's window) not matched
    in both views (``Ordering.end_disparity`` NaN): the dead end's depth is the end
    keypoint's, copied."""
    return tuple(
        end
        for row, end in enumerate(("start", "end"))
        if ordering.dead_end[row] and not np.isfinite(ordering.end_disparity[row, 0])
    )


BESIDE_STEP_PX = 10.0  # px along the curve between the surface's measures beside it
BESIDE_SAMPLES = 12  # measures a side of the turn, each on both sides of the curve
FLOAT_PX = 2.0 * AHEAD_NEAR_PX  # the surface this far behind the curve: the thread floats


def _mark_joined(lifted: LiftedPair, uv: np.ndarray, disp: np.ndarray, rev: Reversal) -> bool:
    """Whether the branch beyond a turn back lies on the surface beside it while the curve on
    the other side of the turn floats in front of its surface: a mark on the surface (a fibre,
    a vessel) joined to the thread. The surface is matched by stereo beside the curve's left
    projection (core/check_beyond.surface_ahead, the patch just off the thread on either side,
    every BESIDE_STEP_PX along it from the turn, BESIDE_SAMPLES a side); a side is judged by
    its median measure, with at least two. Where the pair cannot tell (an untextured
    background), nothing is found: a thread can turn back at a point in its projection where
    it runs along the line of sight (a narrow loop: the development split's blend6_4)."""
    s = np.concatenate([[0.0], np.cumsum(row_norms(np.diff(uv, axis=0)))])
    greys, masks = (lifted.grey_L, lifted.grey_R), (lifted.P_L, lifted.P_R)
    fronts = []
    for sign in (-1.0, 1.0):  # towards the start, towards the end
        at = rev.at_px + sign * BESIDE_STEP_PX * np.arange(1, BESIDE_SAMPLES + 1)
        at = at[(at > 0.0) & (at < s[-1])]
        got = []
        for v in at:
            i = int(np.clip(np.searchsorted(s, v), 1, len(uv) - 2))
            t = uv[i + 1] - uv[i - 1]
            nt = float(np.hypot(*t))
            if nt <= 0.0 or not np.isfinite(disp[i]):
                continue
            normal = np.array([-t[1], t[0]]) / nt
            for way in (normal, -normal):
                front, _ = surface_ahead(greys, masks, 0, uv[i], way, float(disp[i]))
                if front is not None:
                    got.append(front)
        fronts.append(float(np.median(got)) if len(got) >= 2 else None)
    branch, rest = fronts if rev.end == "start" else fronts[::-1]
    return (
        branch is not None and rest is not None
        and abs(branch) <= AHEAD_NEAR_PX and rest < -FLOAT_PX
    )  # fmt: skip


def _failed_early(
    reason: str, n: int, z_allowed: tuple[float, float], spline: SplineResult, bounds: Bounds
) -> CheckResult:
    nan = float("nan")
    return CheckResult(
        status="failed",
        reasons=(reason,),
        confidence=np.zeros(n),
        expected_error_mm=np.full(n, np.inf),
        grasp=None,
        score=1,
        rating=1.0,
        reproj_left_mean=nan,
        reproj_left_max=nan,
        reproj_right_mean=nan,
        reproj_right_max=nan,
        coverage_left=0.0,
        coverage_right=0.0,
        depth_range=(nan, nan),
        depth_allowed=z_allowed,
        length=nan,
        length_range=(nan, nan),
        path_px=float(bounds.s[-1]),
        bound_excursion=_excursion(spline, _excursions(spline, bounds, _spline_z(spline))),
        solver_status=spline.status,
        longest_jump_px=nan,
        overlap_px=nan,
    )


def _px(v: float, margin: float) -> str:
    return f"more than {margin:g} px" if v >= margin else f"up to {v:.1f} px"


def _dehomogenise(h: np.ndarray) -> np.ndarray:
    """(N, 2) pixels (x, y) of (N, 3) homogeneous image points (P @ [X, 1] per point); a point
    at depth 0 gives inf or NaN (check_curve ignores the floating-point warnings)."""
    return h[:, :2] / h[:, 2:3]


def _in_image(uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    H, W = shape  # a NaN point compares False: outside
    return (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)


def _border_distance(a: np.ndarray, b: np.ndarray, shape: tuple[int, int]) -> float:
    """Smallest distance (px) of two image points to the image border (negative outside)."""
    H, W = shape
    ax, ay, bx, by = float(a[0]), float(a[1]), float(b[0]), float(b[1])
    if math.isnan(ax + ay + bx + by):
        return -np.inf
    d = min(min(ax, bx), min(ay, by), W - 1 - max(ax, bx), H - 1 - max(ay, by))
    return d if math.isfinite(d) else -np.inf


@dataclass(frozen=True)
class _View:
    """One view's thread pixels for the coverage, by rows (CSR) on their bounding box
    [bx, bx + w) x [by, by + h) of the image (the curve's band outside it holds no thread
    pixel); ``x0``, ``y0`` the origin of the field's box the curve is measured from (the band
    is drawn from the same fixed-point coordinates as on that box)."""

    x0: int
    y0: int
    bx: int
    by: int
    total: int
    shape: tuple[int, int]
    cols: np.ndarray  # the thread pixels' columns of the box, row by row (ascending)
    row_ptr: np.ndarray  # row i's columns: cols[row_ptr[i]:row_ptr[i + 1]]


def _view(mask: np.ndarray, field: MaskField) -> _View:
    """The thread pixels on their bounding box (per segmentation, cached with it)."""
    return derived((mask,), f"view{field.x0},{field.y0}", lambda: _crop(mask, field))


def _crop(mask: np.ndarray, field: MaskField) -> _View:
    bx, by, _, bh = field.bbox
    cols, row_ptr = _rows_of_runs(row_runs(mask), bx, by, bh)  # np.nonzero's order
    if row_ptr[-1] != field.total:
        raise ValueError(f"the thread mask changed: {row_ptr[-1]} pixels, {field.total} counted")
    return _View(field.x0, field.y0, bx, by, field.total, mask.shape, cols, row_ptr)


def _rows_of_runs(
    runs: tuple[np.ndarray, np.ndarray, np.ndarray], bx: int, by: int, bh: int
) -> tuple[np.ndarray, np.ndarray]:
    """The set pixels of a mask by rows on their bounding box (rows by..by + bh - 1, columns
    from bx), from the mask's row runs (``refine.row_runs``: row, first and last column,
    row-major, cached with the mask): row i's columns ``cols[row_ptr[i]:row_ptr[i + 1]]`` (box
    px, ascending), as ``np.nonzero`` of the box lists them, without a scan of the mask."""
    row, first, last = runs
    n = last - first + 1
    ends = np.cumsum(n)
    total = int(ends[-1]) if n.size else 0
    # pixel j of run r: column first[r] + (j - start of run r), shifted to the crop
    cols = np.arange(total, dtype=np.int64) + np.repeat(first - bx - (ends - n), n)
    run_ptr = np.searchsorted(row, np.arange(by, by + bh + 1, dtype=np.int64))
    row_ptr = np.concatenate([[0], ends])[run_ptr].astype(np.int64)
    return cols, row_ptr


def _columns_within(v: _View, lo: float, hi: float) -> _View:
    """``v`` with only its thread pixels whose column x (image px) lies in [lo, hi]."""
    cols = v.cols
    if cols.size == 0 or (v.bx + int(cols.min()) >= lo and v.bx + int(cols.max()) <= hi):
        return v
    x = cols + v.bx
    keep = (x >= lo) & (x <= hi)
    kept = np.concatenate([[0], np.cumsum(keep, dtype=np.int64)])
    return replace(v, total=int(kept[-1]), cols=cols[keep], row_ptr=kept[v.row_ptr])


def _coverage(v: _View, uv: np.ndarray, inside: np.ndarray, cover_px: float) -> float:
    """Share of thread pixels within ``cover_px`` + the thread's half-width of the curve.

    The half-width is the thread area in a band around the curve divided by twice the curve's
    2D length (a wrong curve over background gets a thin band: stricter, never looser).
    A band ``2 r + 1`` px wide holds the thread pixels whose centre lies within ``r + 1.5`` of
    the polyline through the curve's points at 1/4 px: the rectangles' half-width and the
    discs' radius of OpenCV's thick polyline of that width (``r + 1``, the drawn band this
    replaces) and the half pixel by which its filling rounds the edges outwards. The distances
    are measured once, out to the widest band."""
    if inside.sum() < 2 or v.total == 0:
        return 0.0
    # counted below two bands, both at least this one: values under it need not be least
    done = (min(int(np.ceil(cover_px)), BAND_PX) + 1.5) ** 2  # reach >= ceil(cover_px)
    n = coverage_count(
        np.ascontiguousarray(uv, dtype=np.float64),
        np.ascontiguousarray(inside),
        float(v.x0),
        float(v.y0),
        v.cols,
        v.row_ptr,
        float(v.bx - v.x0),
        float(v.by - v.y0),
        float(cover_px),
        float(BAND_PX),
        float(done),
    )  # fmt: skip  (compiled: the band's distances and both counts in one call)
    return float(n) / v.total


def _spline_z(spline: SplineResult) -> np.ndarray:
    """S_z at the points of H (the returned spline)."""
    c = np.ascontiguousarray(spline.ctrl[:, 2], dtype=np.float64)  # as BSpline() keeps it
    t = np.ascontiguousarray(spline.knots, dtype=np.float64)
    return BSpline.construct_fast(t, c, int(spline.degree))(spline.u_H)


def _excursions(spline: SplineResult, bounds: Bounds, zs: np.ndarray) -> np.ndarray:
    """Excursion of S_z outside [lower, upper] at each point of H, in half-widths (<= 0
    inside); 0 where the refine stage dropped the bounds (``spline.bounds_dropped``: stereo
    matched a strand to its neighbour there, so they bound the wrong strand: no evidence)."""
    half = np.maximum(0.5 * (bounds.upper - bounds.lower), 1e-12)
    out = np.maximum(bounds.lower - zs, zs - bounds.upper) / half
    dropped = spline.bounds_dropped
    if dropped is not None and len(dropped) == len(out):
        out = np.where(dropped, 0.0, out)
    return out


def _excursion(
    spline: SplineResult, excursions: np.ndarray, where: np.ndarray | None = None
) -> float:
    """Largest of the ``excursions`` (``_excursions``) and 0; with ``where`` (one flag per
    dense curve point, evenly spaced in the spline's parameter), only at the points of H whose
    nearest curve point is flagged."""
    out = excursions
    if where is not None:
        n = len(where)
        u = spline.u_H / spline.length if spline.length > 0 else np.zeros(len(out))
        if not np.isfinite(u).all():  # (nan_to_num leaves a finite array as it is)
            u = np.nan_to_num(u)
        # np.clip's values on a finite u (an overflow to inf clips to n - 1), without its layers
        i = np.minimum(np.maximum(np.rint(u * (n - 1)), 0), n - 1).astype(np.intp)
        out = out[where[i]]
    if out.size == 0:
        return 0.0
    if not np.isfinite(out).all():
        return float("inf")
    return float(max(0.0, out.max()))


def _off_thread_runs(
    off: np.ndarray, step: np.ndarray, step3: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of consecutive off-thread samples: per sample its run's 2D length (px, including
    the steps onto and off the thread; 0 on the thread), its 3D length (the same steps of
    ``step3``) and whether the run is a bridge (both of its ends on the thread, i.e. not at an
    end of the curve)."""
    n = len(off)
    if not off.any():
        return np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)
    start = off & ~np.concatenate([[False], off[:-1]])
    run = np.where(off, np.cumsum(start) - 1, -1)
    # a step belongs to a run when either of its samples does (entering, inside, leaving)
    step_run = np.maximum(run[1:], run[:-1])
    k = int(run.max()) + 1
    sel = step_run >= 0
    length = np.bincount(step_run[sel], weights=step[sel], minlength=k)
    length3 = np.bincount(step_run[sel], weights=step3[sel], minlength=k)
    at_end = np.zeros(k, dtype=bool)
    at_end[run[[0, -1]][run[[0, -1]] >= 0]] = True
    return np.where(off, length[run], 0.0), np.where(off, length3[run], 0.0), off & ~at_end[run]


def _unsupported_travel(z: np.ndarray, supported: np.ndarray) -> float:
    """Depth travel no reliable match shows: over each stretch of unsupported points between
    two supported ones, the total variation of z minus the net depth change across it (the
    net change is measured at both ends); over an unsupported end, the whole total variation
    (its depth is extrapolated from one side: none of its change is measured). The whole total
    variation when no point is supported."""
    # compiled: stretch k runs over the steps between the supported samples k - 1 and k, the
    # ends before the first and from the last (empty when the curve's end is supported)
    return unsupported_travel(
        np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(supported, dtype=bool)
    )


def _unmeasured_length(
    step3: np.ndarray, step: np.ndarray, z: np.ndarray, supported: np.ndarray, f_mm: float
) -> float:
    """Length (mm) the curve's depth change adds where no reliable match supports it: over
    each step with an unsupported sample, the 3D step ``step3`` (mm) less the same 2D step
    ``step`` (px) at constant depth (px * z / f, ``f_mm`` = f per mm of depth). A step between
    two supported samples is measured at both ends and left out."""
    return unmeasured_length(  # compiled: the same sums (numpy's, with where)
        np.ascontiguousarray(step3, dtype=np.float64), np.ascontiguousarray(step, dtype=np.float64),
        np.ascontiguousarray(z, dtype=np.float64), np.ascontiguousarray(supported, dtype=bool),
        0.5 / f_mm,
    )  # fmt: skip


def _end_added_length(
    step3: np.ndarray,
    step: np.ndarray,
    z: np.ndarray,
    f_mm: float,
    n_spans: int,
    end: str,
    s: np.ndarray | None = None,
) -> float:
    """Length (mm) the depth change adds over the curve's last knot span at ``end`` (2D length
    of the left projection / ``n_spans``): each step's 3D length less the same 2D step at
    constant depth (``_unmeasured_length`` with no step measured). ``s``: ``arc_px(step)``
    when the caller has it."""
    s = arc_px(step) if s is None else s
    span = s[-1] / n_spans
    k = int(np.searchsorted(s, span)) if end == "start" else int(np.searchsorted(s, s[-1] - span))
    sl = slice(0, max(k, 1)) if end == "start" else slice(min(k, len(step) - 1), len(step))
    zs = z[sl.start : sl.stop + 1]
    return _unmeasured_length(step3[sl], step[sl], zs, np.zeros(len(zs), dtype=bool), f_mm)


def _strand_samples(
    crossings: int,
    on_l: np.ndarray,
    supported: np.ndarray,
    step: np.ndarray,
    p: CheckParams,
    s: np.ndarray | None = None,
) -> np.ndarray:
    """Samples that may belong to a strand crossing another (``crossing_disparity_px``): the
    thread pixels cross at a keypoint, the sample lies on the left thread pixels and a
    supported sample lies within ``crossing_support_px`` of it along the curve (2D). ``s``:
    ``arc_px(step)`` when the caller has it."""
    n = len(on_l)
    if crossings == 0 or not supported.any():
        return np.zeros(n, dtype=bool)
    s = arc_px(step) if s is None else s
    ss = s[supported]
    k = np.searchsorted(ss, s)
    before = np.abs(s - ss[np.maximum(k - 1, 0)])
    after = np.abs(ss[np.minimum(k, len(ss) - 1)] - s)
    return on_l & (np.minimum(before, after) <= p.crossing_support_px)


def _overlap(
    uv: np.ndarray,
    step: np.ndarray,
    loop_px: float,
    disp: np.ndarray,
    strand: np.ndarray,
    dtol: float,
) -> float:
    """2D length (px) of the curve lying within ``loop_px`` of a part of the curve more than
    ``pi * loop_px`` + 3 px away along it (a crossing contributes a few px); two ``strand``
    samples whose disparities differ by ``dtol`` or more cross, they do not overlap."""
    if loop_px <= 0:
        return 0.0
    # compiled: the finite samples' pairs (sorted by x), the arc length and numpy's sum
    return overlap_length(
        np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(step, dtype=np.float64),
        loop_px**2, np.pi * loop_px + 3.0, np.ascontiguousarray(disp, dtype=np.float64),
        np.ascontiguousarray(strand, dtype=bool), float(dtol),
    )  # fmt: skip


def _rerun_px(uv_l: np.ndarray, uv_r: np.ndarray, a: int, b: int) -> tuple[float, float]:
    """The curve's stretch past a bridge (observed samples ``a`` and ``b``) toward its nearer
    end (the shorter side: ``0..a`` or ``b..n-1``) held against the rest of the curve (the
    other side): the largest distance of one of its samples to the nearest sample of the rest,
    px (the larger of the two views), and its 2D length in the left view, px."""
    n = len(uv_l)
    end, rest = (slice(0, a + 1), slice(b, n)) if a + 1 <= n - b else (slice(b, n), slice(0, a + 1))
    far = max(float(cKDTree(uv[rest]).query(uv[end])[0].max()) for uv in (uv_l, uv_r))
    return far, float(row_norms(np.diff(uv_l[end], axis=0)).sum())


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index ranges of the runs of True in ``flag``."""
    return [(a, b) for a, b in flag_runs(np.ascontiguousarray(flag, dtype=bool)).tolist()]


class _BareBackground:
    """Per view, whether a bridge's pixels look like the bare background next to the thread
    at the bridge's two ends: the ring 3..9 px around the thread pixels (read off the view's
    distance field) within ``REACH_PX`` of each end gives a local grey level (median) and
    spread (1.4826 MAD, at least 4 levels); a pixel off the thread is bare when its grey level
    is within ``bare_sigma`` spreads of the level interpolated between the two ends along the
    bridge."""

    REACH_PX = 25
    RING_PX = (3.0, 9.0)  # the ring's inner and outer distance to the thread pixels

    def __init__(self, lifted: LiftedPair, fields: tuple[MaskField, MaskField], p: CheckParams):
        self.p = p
        self.views = [
            (np.asarray(lifted.grey_L), lifted.P_L, fields[0]),
            (np.asarray(lifted.grey_R), lifted.P_R, fields[1]),
        ]
        # the levels depend on the segmentation only: kept with it for the next slider move
        self._cache: dict[tuple[int, int, int], tuple[float, float] | None] = derived(
            (lifted.grey_L, lifted.grey_R, lifted.P_L, lifted.P_R),
            f"bare{fields[0].reach:g},{fields[1].reach:g}",
            dict,
        )

    def _level(self, side: int, xy: np.ndarray) -> tuple[float, float] | None:
        """Median and spread of the ring around the thread within REACH_PX of ``xy``."""
        if not np.isfinite(xy).all():
            return None
        x, y = int(round(xy[0])), int(round(xy[1]))
        if (side, x, y) not in self._cache:
            g, _, field = self.views[side]
            d, rows, cols = field.window(x, y, self.REACH_PX, self.RING_PX[1])
            # compiled: the ring's grey levels, their median and deviation (np.median's values)
            grey = np.asarray(g[rows, cols], dtype=np.float64, order="C")
            n, med, mad = ring_level(d, grey, *self.RING_PX, 10)
            level = None if n < 10 else (float(med), max(1.4826 * float(mad), 4.0))
            self._cache[side, x, y] = level
        return self._cache[side, x, y]

    def grey(self, side: int, uv: np.ndarray) -> np.ndarray:
        """Grey level at each (x, y) of view ``side``; NaN off the image."""
        return _sample(self.views[side][0], uv)

    def quieter(self, side: int, at: np.ndarray, back: np.ndarray) -> np.ndarray:
        """``back`` when its ring's spread is smaller than ``at``'s (or ``at`` has none), else
        ``at``: where an end's ring holds another surface (an occluder) besides the
        background, its spread is the larger."""
        la, lb = self._level(side, at), self._level(side, back)
        if lb is not None and (la is None or lb[1] < la[1]):
            return back
        return at

    def spread(self, side: int, *ends: np.ndarray) -> float:
        """Largest local spread of the background next to the thread at ``ends``."""
        levels = [self._level(side, e) for e in ends]
        return max((lv[1] for lv in levels if lv is not None), default=4.0)

    def behind(self, uv_l: np.ndarray, uv_r: np.ndarray) -> bool:
        """Whether the stereo pair shows the surface under a run of curve samples at or
        behind the curve's depth, or cannot tell (``_surface_behind``)."""
        return _surface_behind(
            self.views[0][0], self.views[1][0], uv_l, uv_r, self.p.front_excluded
        )

    def __call__(self, side: int, uv: np.ndarray, end_a: np.ndarray, end_b: np.ndarray):
        """(len(uv),) bool: sample k of the bridge (uv in order from end a to end b) is bare."""
        out = np.zeros(len(uv), dtype=bool)
        la, lb = self._level(side, end_a), self._level(side, end_b)
        ok = np.isfinite(uv).all(axis=1)
        if la is None or lb is None or not ok.any():
            return out  # no background next to the thread to compare with: not known bare
        g, mask, _ = self.views[side]
        h, w = g.shape
        t = np.linspace(0.0, 1.0, len(uv) + 2)[1:-1][ok]
        level = (1 - t) * la[0] + t * lb[0]
        tol = self.p.bare_sigma * max(la[1], lb[1])
        q = np.rint(uv[ok]).astype(np.intp)
        inside = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
        res = np.zeros(len(q), dtype=bool)
        qi = q[inside]
        grey = g[qi[:, 1], qi[:, 0]]
        res[inside] = ~mask[qi[:, 1], qi[:, 0]] & (np.abs(grey - level[inside]) <= tol)
        out[ok] = res
        return out


FRONT_PX = 12  # px of disparity searched in front of the curve by _surface_behind
BEHIND_PX = 48  # px of disparity searched behind it (a background well behind the thread)
NEAR_PX = 2  # a best match within this of the curve's disparity: a surface at its depth
FAR_PX = 6  # shifts this far from the best match tell whether it is distinct
TEXTURE_LEVELS = 4.0  # grey levels: the spread floor of the ring (sensor noise and JPEG)


def _surface_behind(
    grey_l: np.ndarray,
    grey_r: np.ndarray,
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    front_excluded: bool = False,
) -> bool:
    """Whether the stereo pair shows the surface under a run of curve samples at or behind
    the curve's depth (so that a thread there would be seen in front of it), or cannot tell.

    The mean |left - right grey| along the run is taken with the right view shifted along
    the epipolar line, from FRONT_PX px of disparity more than the curve's (in front) to
    BEHIND_PX less (behind). Where the run's grey varies (texture beyond TEXTURE_LEVELS,
    robust spread) and the best shift is distinct (the median cost FAR_PX or more away from
    it is TEXTURE_LEVELS higher), the surface's disparity is measured: behind or at the
    curve's (within NEAR_PX) is True; in front (an occluder) is False. A match that says
    nothing about depth (a uniform or row-aligned occluder such as a shaft along the rows)
    is False: nothing shows the thread would be seen. An untextured run (a flat background)
    cannot be told by stereo and is True: left to the grey levels. ``front_excluded``: a best
    shift at or behind the curve also counts when every shift more than NEAR_PX in front of
    the curve costs TEXTURE_LEVELS more than it (smooth tissue matches over a broad valley
    behind the thread, but no occluder in front matches at all)."""
    gl = _sample(grey_l, uv_l)
    ok = np.isfinite(gl)
    if ok.sum() < 3:
        return True
    spread = 1.4826 * float(np.median(np.abs(gl[ok] - np.median(gl[ok]))))
    if spread <= TEXTURE_LEVELS:
        return True
    # a surface delta px of disparity in front of the curve is seen delta px left of uv_r
    delta = np.arange(-BEHIND_PX, FRONT_PX + 1)
    shifted = uv_r[None, :, :] - np.stack([delta, np.zeros_like(delta)], axis=1)[:, None, :]
    gr = _sample(grey_r, shifted.reshape(-1, 2)).reshape(len(delta), len(uv_r))
    d = np.abs(gl[None, :] - gr)
    seen = np.isfinite(d).sum(axis=1)
    with np.errstate(invalid="ignore"):
        cost = np.where(seen >= max(3, ok.sum() // 2), np.nansum(d, axis=1) / seen, np.inf)
    if not np.isfinite(cost).any():
        return True
    k = int(np.argmin(cost))
    far = cost[(np.abs(delta - delta[k]) >= FAR_PX) & np.isfinite(cost)]
    distinct = far.size > 0 and float(np.median(far)) >= cost[k] + TEXTURE_LEVELS
    if not distinct and front_excluded and delta[k] <= NEAR_PX:
        front = cost[delta > NEAR_PX]
        distinct = bool(np.all(np.isfinite(front))) and float(front.min()) >= (
            cost[k] + TEXTURE_LEVELS
        )
    return distinct and delta[k] <= NEAR_PX


def _sample(grey: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Grey level of an (H, W) image at each (x, y) (nearest pixel); NaN off the image."""
    h, w = grey.shape
    out = np.full(len(uv), np.nan)
    ok = np.all(np.isfinite(uv), axis=1)
    q = np.rint(np.where(ok[:, None], uv, -1.0)).astype(np.intp)
    ok &= (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
    out[ok] = grey[q[ok, 1], q[ok, 0]]
    return out


def _hidden_end(
    end_off: np.ndarray,
    on: np.ndarray,
    other_off: np.ndarray,
    uv: np.ndarray,
    side: int,
    bare: _BareBackground | None,
    p: CheckParams,
) -> np.ndarray:
    """Samples of an end run off the thread in view ``side`` (``end_off``) that the other
    view sees on its thread (at least half of the run) and that do not lie over bare
    background in this view (compared with the tissue next to the thread where the run
    leaves it): hidden by an occluder in this view."""
    out = np.zeros(len(uv), dtype=bool)
    if bare is None:
        return out
    for i0, i1 in _runs(end_off):
        obs = i1 if i0 == 0 else i0 - 1  # the observed sample the run leaves from
        if obs >= len(uv) or not on[obs] or np.mean(other_off[i0:i1]) > 0.5:
            continue
        share = float(bare(side, uv[i0:i1], uv[obs], uv[obs]).mean())
        if share <= p.bare_share:
            out[i0:i1] = True
    return out


def _bridge_evidence(
    pts: np.ndarray,
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    s3: np.ndarray,
    step: np.ndarray,
    a: int,
    b: int,
    mm: float,
    bare: _BareBackground | None,
    p: CheckParams,
) -> str | None:
    """None when the bridge from observed sample ``a`` to ``b`` is supported by the evidence,
    else why not: it is a loop, or it crosses bare background in both views. How it turns at
    its ends is no evidence: the hidden thread bends somewhere between them either way, and a
    thread as long as the bridge strays at most half its length from it (max_bridge_mm)."""
    chord = pts[b] - pts[a]
    chord_mm = float(np.linalg.norm(chord)) * mm
    len3 = float(s3[b] - s3[a])
    chord_px = float(np.linalg.norm(uv_l[b] - uv_l[a]))
    path_px = float(np.sum(step[a:b]))
    if not (len3 <= p.bridge_stretch * chord_mm and path_px <= p.bridge_stretch * chord_px):
        return (f"{len3:.0f} mm / {path_px:.0f} px for a chord of {chord_mm:.0f} mm / "
                f"{chord_px:.0f} px: a loop, not a continuation")  # fmt: skip
    if bare is not None and b - a > 1:
        hidden = slice(a + 1, b)
        # each end's background level: its own ring, or the ring farther back along the
        # observed thread when that one is quieter (an occluder the thread runs under at the
        # end lies in the end's own ring and would pass for background)
        ends = [
            tuple(
                bare.quieter(side, uv[i], _back_along(uv, i, sign, p.bare_back_px))
                for i, sign in ((a, -1), (b, 1))
            )
            for side, uv in ((0, uv_l), (1, uv_r))
        ]
        both = bare(0, uv_l[hidden], *ends[0]) & bare(1, uv_r[hidden], *ends[1])
        # bare tissue lies at about the thread's depth: both views see the same grey there at
        # the curve's disparity (an occluder in front of the thread is seen shifted)
        spread = max(bare.spread(0, *ends[0]), bare.spread(1, *ends[1]))
        with np.errstate(invalid="ignore"):
            same = np.abs(bare.grey(0, uv_l[hidden]) - bare.grey(1, uv_r[hidden]))
            both &= same <= p.bare_sigma * spread
        share = float(both.mean())
        if share > p.bare_share and bare.behind(uv_l[hidden], uv_r[hidden]):
            return (f"{100 * share:.0f} % of it lies over bare background in both views (the "
                    "grey of the tissue next to the thread, the same in both), where the thread "
                    "would be seen")  # fmt: skip
    return None


def _back_along(uv: np.ndarray, i: int, sign: int, px: float) -> np.ndarray:
    """The sample ``px`` of 2D length from sample ``i`` of the projected curve ``uv``,
    walking its samples in direction ``sign`` (-1: towards the start), or the curve's end
    on that side; sample ``i`` itself for ``px`` <= 0 (or a non-finite step)."""
    if px <= 0.0:
        return uv[i]
    idx = np.arange(i, -1, -1) if sign < 0 else np.arange(i, len(uv))
    run = uv[idx]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(run, axis=0).T))])
    k = int(np.searchsorted(s, px))
    return run[min(k, len(run) - 1)] if np.isfinite(s[-1]) else uv[i]


def _outside_between(in_l: np.ndarray, in_r: np.ndarray) -> np.ndarray:
    """Samples outside both images that lie between samples inside one of them: the curve
    leaves the view and comes back (the parts past its first and last seen samples are ends
    at the border, not stretches between)."""
    seen = np.flatnonzero(in_l | in_r)
    out = np.zeros(len(in_l), dtype=bool)
    if len(seen) >= 2:
        out[seen[0] : seen[-1]] = ~(in_l | in_r)[seen[0] : seen[-1]]
    return out


def _row_end_tip(
    uv: tuple[np.ndarray, np.ndarray],
    known: tuple[tuple[float, float], tuple[np.ndarray | None, np.ndarray | None]],
    end: str,
    disparity: float,
    cut_px: float,
    row_px: float,
    d_range: tuple[float, float],
    supported: np.ndarray,
) -> tuple[str, float, float, float] | None:
    """At a free ``end`` that one view sees the thread go on past by more than ``cut_px``
    farther than the other (``known``: ``extension_far``), the other reading of the two
    views' ends: the far view's farthest extension pixel and the stopping view's end tip as
    one tip, when they lie on one row (within ``row_px``) and their disparity lies in
    ``d_range``. The end's disparity may then lie anywhere between its own (``disparity``)
    and that one, within one strand's room (``continuity.disparity_room``) of the nearest
    depth the images fix: the first ``supported`` sample past the end's own supported run
    (the end's match, the reading in question), or where the left projection leaves the rows
    (ROW_DEG from the end, plus ``row_px``). An end whose supported run holds on past two tip
    windows (2 END_WINDOW_PX) is measured: None. Returns (far view, the farthest disparity
    so allowed, the extension px, the stretch's length px) or None."""
    ext, far_px = known
    if abs(ext[0] - ext[1]) <= cut_px or not math.isfinite(disparity):
        return None
    far = 0 if ext[0] > ext[1] else 1
    px = far_px[far]
    stop = uv[1 - far]
    tip = stop[0] if end == "start" else stop[-1]
    if px is None or not np.isfinite(tip).all():
        return None
    if abs(float(px[1]) - float(tip[1])) > row_px:
        return None
    d_alt = float(px[0] - tip[0]) if far == 0 else float(tip[0] - px[0])
    if not d_range[0] <= d_alt <= d_range[1]:
        return None
    # the stretch along the rows from the end: past it the thread's slant fixes the disparity,
    # and one strand's disparity changes at most disparity_room over the stretch's length
    seq, sup = (uv[0], supported) if end == "start" else (uv[0][::-1], supported[::-1])
    fin = np.isfinite(seq).all(axis=1)
    seq, sup = seq[fin], sup[fin]
    rel = seq - seq[0]
    off = np.abs(rel[:, 1]) > row_px + np.abs(rel[:, 0]) * math.tan(math.radians(ROW_DEG))
    arc = np.concatenate([[0.0], row_norms(np.diff(seq, axis=0)).cumsum()])
    # the end's own run of supported samples is the reading in question unless it holds on
    # past two tip windows (a slant the matches measure: the end is fixed there); else the
    # first supported sample past that run (or where the curve leaves the rows) is the
    # nearest depth the images fix
    first = int(np.argmax(~sup)) if (~sup).any() else len(sup)
    if arc[min(first, len(arc) - 1)] >= 2 * END_WINDOW_PX:
        return None
    fixed = (sup & (np.arange(len(sup)) >= first)) | off
    along = float(arc[int(np.argmax(fixed))]) if fixed.any() else float(arc[-1])
    room = float(disparity_room(along))
    d_end = disparity + float(np.clip(d_alt - disparity, -room, room))
    return ("left" if far == 0 else "right", d_end, float(ext[far]), along)


def _end_way(uv: np.ndarray, end: str) -> np.ndarray:
    """The outward unit direction (x, y) of a projected curve's ``end`` over its last (up to)
    END_SAMPLES samples (zero when they coincide)."""
    k = min(END_SAMPLES, len(uv) - 1)
    tip, back = (uv[0], uv[k]) if end == "start" else (uv[-1], uv[-1 - k])
    way = tip - back
    norm = float(np.hypot(way[0], way[1]))
    return way / norm if norm > 0.0 else np.zeros(2)


def _measured_in_front(
    uv: tuple[np.ndarray, np.ndarray], lifted: LiftedPair, end: str, disparity: float, side: int
) -> bool:
    """Whether stereo measures the surface just past the curve's ``end`` in view ``side`` in
    front of the end (more than AHEAD_NEAR_PX of ``disparity``, the end's): an occluder."""
    front = surface_past_end(
        uv[side], (lifted.grey_L, lifted.grey_R), (lifted.P_L, lifted.P_R), side, end, disparity
    )
    return front is not None and front > AHEAD_NEAR_PX


def _front_at_tip(
    lifted: LiftedPair, disparity: float, side: int, at: np.ndarray, way: np.ndarray
) -> bool:
    """Whether stereo measures the surface just past ``at`` (a thread's tip in view ``side``)
    along ``way`` in front of an end of ``disparity`` (more than AHEAD_NEAR_PX): an occluder
    (``surface_ahead``, its first two patches)."""
    greys, masks = (lifted.grey_L, lifted.grey_R), (lifted.P_L, lifted.P_R)
    for k in range(AHEAD_MEET):
        d, _ = surface_ahead(greys, masks, side, at, way, disparity, k * AHEAD_STEP_PX)
        if d is not None and d > AHEAD_NEAR_PX:
            return True
    return False


def _left_behind(
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    lifted: LiftedPair,
    z: np.ndarray,
    a: int,
    b: int,
    f: float,
    mm: float,
    p: CheckParams,
) -> str | None:
    """Why the bridge from observed sample ``a`` to ``b`` is no continuation of the thread:
    at one of its ends the thread pixels branch on, uncovered by the curve, for more than half
    of max_unobserved_mm (at that end's depth) in both views (core/check_beyond.left_behind),
    the bound of how far the thread under a bridge of that length strays from it; else None."""
    for at, where in ((a, "before"), (b, "after")):
        if not 0 <= at < len(z):
            continue
        half_px = 0.5 * p.max_unobserved_mm / mm * f / z[at]  # half the limit, at that end
        ext = left_behind((uv_l, uv_r), (lifted.P_L, lifted.P_R), at, 2.0 * half_px,
                          p.cover_px + BEYOND_COVER_PX, p.jump_px + 0.5)  # fmt: skip
        seen = min(ext)
        if seen > half_px:
            return (
                f"the thread goes on {seen:.0f} px ({seen * z[at] / f * mm:.1f} mm) in "
                f"both views where the curve leaves it (the observed part {where} the "
                "bridge), not covered by the curve: the curve left the thread it followed"
            )
    return None


def _bridge_confined(
    lifted: LiftedPair,
    uv_l: np.ndarray,
    uv_r: np.ndarray,
    z: np.ndarray,
    a: int,
    b: int,
    f: float,
    B: float,
    mm: float,
    limit_mm: float,
    bare: _BareBackground | None,
    p: CheckParams,
) -> bool:
    """Whether the thread hidden under the bridge from observed sample ``a`` to ``b`` is held
    by its occluder within ``limit_mm`` / 2 of the bridge in both views (at each sample's
    depth): the bound the bridge's limit stands for (a thread as long as the bridge strays at
    most half its length from it), measured instead of assumed from the bridge's length
    (core/check_beyond.bridge_stray: the occluder walked across the bridge on both sides)."""
    if bare is None:
        return False
    seg = slice(a, b + 1)
    limit_px = 0.5 * limit_mm / mm * f / z[seg]
    plain: list[tuple[float, float] | None] = [None, None]
    for side, (g, m, uv) in enumerate(
        ((lifted.grey_L, lifted.P_L, uv_l), (lifted.grey_R, lifted.P_R, uv_r))
    ):
        run = uv[a : b + 1]
        for i, way in ((a, -_end_way(run, "start")), (b, -_end_way(run, "end"))):
            # at an end of the bridge where this view sees the thread (way: into the bridge)
            plain[side] = plain_surface(g, m, uv[i], way, p.bare_sigma)
            if plain[side] is not None:
                break
    # the thread hidden at both ends in one view: the plain surface is the one the other sees
    plain = [plain[0] if plain[0] is not None else plain[1], plain[1] or plain[0]]
    stray = bridge_stray(
        (uv_l[seg], uv_r[seg]), (lifted.P_L, lifted.P_R), (lifted.grey_L, lifted.grey_R),
        f * B / z[seg], (plain[0], plain[1]), limit_px, p.bridge_stray_both,
    )  # fmt: skip
    return stray < 1.0


def _disparity_residual(
    stereo: StereoResult,
    rel: ReliabilityResult,
    uv_l: np.ndarray,
    disp_curve: np.ndarray,
    support_px: float,
) -> np.ndarray:
    """|curve disparity - disparity of the nearest reliable pixel| + distance / support_px."""
    xs, row_ptr, y0, disp_rel = reliable_rows(stereo, rel)  # shared with contradicted
    uv = np.ascontiguousarray(uv_l, dtype=np.float64)
    r = nearest_residual(
        xs, row_ptr, y0, disp_rel, uv[:, 0].copy(), uv[:, 1].copy(),
        np.ascontiguousarray(disp_curve, dtype=np.float64), float(support_px),
    )  # fmt: skip
    return np.where(np.isfinite(r), r, 1e3)
