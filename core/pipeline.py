"""The reconstruction pipeline: the stages in order, timed, each cached by the parameters it
depends on (its own and those of every stage before it), so that changing a late parameter
re-runs only the stages after it.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields, make_dataclass
from typing import Any

from threadpoolctl import ThreadpoolController

from threadrecon.core.bounds import BoundsParams, depth_bounds
from threadrecon.core.calibration import StereoCalibration
from threadrecon.core.camera import CameraParams, to_camera
from threadrecon.core.check import CheckParams, check_curve
from threadrecon.core.clustering import ClusterParams, cluster_keypoints
from threadrecon.core.corrections import Correction, apply_corrections, unsegmented
from threadrecon.core.ordering import OrderingParams, order_keypoints
from threadrecon.core.params import Params
from threadrecon.core.refine import RefineParams, refine_depth
from threadrecon.core.reliability import ReliabilityParams, prune
from threadrecon.core.segmentation import SegmentationParams, StereoPair, segment
from threadrecon.core.spline import SplineParams, fit_spline
from threadrecon.core.stereo import StereoParams, match_stereo

# One BLAS thread while a stage runs: a multithreaded BLAS sums in another order, and SLSQP's
# path through Eq. (8) amplified that into a different curve ("n_ctrl = 40" on blend3_1 failed
# with one thread and gave 552 km with several). Created once: creation scans loaded libraries.
_BLAS = ThreadpoolController()
_BLAS_LIBS = _BLAS.select(user_api="blas").lib_controllers


def _blas_guard() -> Callable[[], contextlib.AbstractContextManager[Any]]:
    """What to wrap each stage's computation in: nothing when every BLAS already runs one
    thread (the CLI and the server set that once, :meth:`Pipeline.run` once per run; a check
    costs ~15 us), else a one-thread limit (~100 us a stage: it queries and sets every library
    twice)."""
    if all(lib.num_threads == 1 for lib in _BLAS_LIBS):
        return contextlib.nullcontext
    return lambda: _BLAS.limit(limits=1, user_api="blas")


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline, declared once: everything else (parameters, presets, sliders,
    caching, stage JSON, layers, exports) is derived from :data:`STAGE_TABLE`."""

    name: str
    params: type[Params]
    """Its frozen parameter dataclass; the field of :class:`ReconParams` is named ``name``."""
    run: Callable[..., Any]
    """``run(*inputs, params) -> result``."""
    inputs: tuple[str, ...]
    """What ``run`` takes before its params, in order: "pair", "calib" or an earlier stage."""
    title: str


STAGE_TABLE: tuple[Stage, ...] = (
    Stage("segment", SegmentationParams, segment, ("pair",), "Segmentation and lifting, Eq. (1)"),
    Stage("stereo", StereoParams, match_stereo, ("segment", "calib"), "SSD stereo, Eqs. (2)-(5)"),
    Stage("reliability", ReliabilityParams, prune, ("stereo",), "Reliability, Eq. (6)"),
    Stage(
        "clustering",
        ClusterParams,
        cluster_keypoints,
        ("stereo", "reliability"),
        "Keypoint clusters (BFS)",
    ),
    Stage(
        "ordering",
        OrderingParams,
        order_keypoints,
        ("segment", "stereo", "clustering"),
        "Adjacency graph and ordering",
    ),
    Stage(
        "bounds",
        BoundsParams,
        depth_bounds,
        ("stereo", "ordering", "calib"),
        "Depth bounds, Eq. (7)",
    ),
    Stage(
        "spline", SplineParams, fit_spline, ("bounds", "calib"), "Minimum Variation Spline, Eq. (8)"
    ),
    Stage(
        "refine",
        RefineParams,
        refine_depth,
        ("spline", "bounds", "segment", "calib"),
        "Depth from both views",
    ),
    Stage("camera", CameraParams, to_camera, ("refine", "calib"), "Camera frame, Eq. (9)"),
    Stage(
        "check",
        CheckParams,
        check_curve,
        ("segment", "stereo", "reliability", "ordering", "bounds", "refine", "camera", "calib"),
        "Self-check against the evidence",
    ),
)
STAGES: tuple[str, ...] = tuple(s.name for s in STAGE_TABLE)
STAGE_BY_NAME: dict[str, Stage] = {s.name: s for s in STAGE_TABLE}


class _ReconParamsBase:
    def to_dict(self) -> dict[str, dict[str, Any]]:
        """``{stage: {name: value}}`` in table order."""
        return {
            s.name: {g.name: getattr(getattr(self, s.name), g.name) for g in fields(s.params)}
            for s in STAGE_TABLE
        }


ReconParams = make_dataclass(
    "ReconParams",
    [(s.name, s.params, field(default_factory=s.params)) for s in STAGE_TABLE],
    bases=(_ReconParamsBase,),
    frozen=True,
)
ReconParams.__module__ = __name__  # pickled by name (the evaluation job and Dask ship it)
ReconParams.__doc__ = (
    "Every parameter of the core: one frozen Params dataclass per stage, the field named after "
    "the stage (built from :data:`STAGE_TABLE`)."
)


class StageError(ValueError):
    """A stage could not produce its result; ``stage`` names it."""

    def __init__(self, stage: str, message: str) -> None:
        super().__init__(f"{stage}: {message}")
        self.stage = stage
        self.reason = message


def _describe(exc: Exception) -> str:
    """A stage's error in words: the message of a ValueError-like error, else its type too."""
    text = str(exc)
    if isinstance(exc, ValueError | ArithmeticError) and text:
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


@dataclass(frozen=True)
class StageRun:
    stage: str
    result: Any
    ms: float
    """Wall time of the computation, ms (0 when taken from the cache)."""
    cached: bool


class Pipeline:
    """Runs the stages on one stereo pair; results are cached per stage."""

    def __init__(
        self, pair: StereoPair, calib: StereoCalibration, corrections: tuple[Correction, ...] = ()
    ) -> None:
        if pair.shape != calib.image_size:
            raise ValueError(
                f"images are {pair.shape} px but the calibration is for {calib.image_size}"
            )
        self.pair = pair
        self.calib = calib
        self._cache: dict[str, tuple[tuple, Any]] = {}
        self.corrections = tuple(corrections)
        """The user's mask corrections that runs apply unless they name their own."""
        self._segmented: tuple[Any, Any] | None = None  # (segment params, uncorrected result)
        self.last_ms: dict[str, float] = {}

    def _compute(
        self, stage: Stage, results: dict[str, Any], params: Any, corrections: tuple = ()
    ) -> Any:
        sources = {"pair": self.pair, "calib": self.calib, **results}
        p = getattr(params, stage.name)
        if stage.name != "segment" or not corrections:
            return stage.run(*(sources[i] for i in stage.inputs), p)
        # The user's corrections apply right after the segment stage function; its own result
        # is kept, so that a new correction does not segment again.
        if self._segmented is None or self._segmented[0] != p:
            try:
                base = stage.run(*(sources[i] for i in stage.inputs), p)
            except ValueError as exc:  # e.g. no thread found: the user may add it by hand
                base = unsegmented(self.pair, str(exc))
            self._segmented = (p, base)
        return apply_corrections(
            self._segmented[1], corrections, p.lift_dilate_px, (self.pair.left, self.pair.right)
        )

    def stages(
        self,
        params: Any = None,
        until: str | None = None,
        corrections: tuple[Correction, ...] | None = None,
    ) -> Iterator[StageRun]:
        """Yield each stage's run in order up to ``until`` (default: the last stage); any error
        of a stage is raised as :class:`StageError` naming it. ``corrections`` (the user's, in
        order; default :attr:`corrections`) change the masks P_L, P_R right after the segment
        stage (:func:`core.corrections.apply_corrections`)."""
        params = ReconParams() if params is None else params
        corrections = self.corrections if corrections is None else tuple(corrections)
        until = STAGES[-1] if until is None else until
        if until not in STAGES:
            raise ValueError(f"unknown stage {until!r}")
        results: dict[str, Any] = {}
        keys: dict[str, tuple] = {}
        guard = None
        for st in STAGE_TABLE:
            stage = st.name
            # a result depends on its own params and on the results it reads
            key = (getattr(params, stage), *(keys[i] for i in st.inputs if i in keys))
            if stage == "segment":
                key = (*key, corrections)
            keys[stage] = key
            hit = self._cache.get(stage)
            if hit is not None and hit[0] == key:
                results[stage] = hit[1]
                yield StageRun(stage, hit[1], 0.0, True)
            else:
                guard = guard or _blas_guard()
                t0 = time.perf_counter()
                try:
                    with guard():
                        out = self._compute(st, results, params, corrections)
                except StageError:
                    raise
                except Exception as exc:  # a failing stage never takes its caller down
                    self._cache.pop(stage, None)
                    raise StageError(stage, _describe(exc)) from exc
                ms = 1000.0 * (time.perf_counter() - t0)
                self._cache[stage] = (key, out)
                self.last_ms[stage] = ms
                results[stage] = out
                yield StageRun(stage, out, ms, False)
            if stage == until:
                return

    def run(
        self,
        params: Any = None,
        until: str | None = None,
        corrections: tuple[Correction, ...] | None = None,
    ) -> Reconstruction:
        """Run every stage up to ``until``; a failing stage is reported, not raised."""
        params = ReconParams() if params is None else params
        runs: dict[str, StageRun] = {}
        # One BLAS limit for the whole run, when it is not set already: the stages find it
        # set and each skips its own (~100 us a stage; the same one thread either way).
        with _blas_guard()():
            try:
                for run in self.stages(params, until, corrections):
                    runs[run.stage] = run
            except StageError as exc:
                return Reconstruction(runs, exc.stage, exc.reason, params)
        return Reconstruction(runs, None, None, params)


@dataclass(frozen=True)
class Reconstruction:
    """Stage runs of one pipeline call; ``failed_stage``/``error`` are set when a stage failed.

    ``status`` is the check stage's: "ok", "suspect" or "failed" (with its reasons in
    ``message``); "failed" when a stage raised. Without a check run (``until`` before it),
    "failed" when the MVS solver's result was rejected, else "ok".
    """

    runs: dict[str, StageRun]
    failed_stage: str | None
    error: str | None
    params: ReconParams

    def __getitem__(self, stage: str) -> Any:
        return self.runs[stage].result

    @property
    def status(self) -> str:
        if self.failed_stage is not None:
            return "failed"
        if "check" in self.runs:
            return self.runs["check"].result.status
        spline = self.runs.get("spline")
        if spline is not None and not spline.result.ok:
            return "failed"
        return "ok"

    @property
    def reasons(self) -> tuple[str, ...]:
        """Every reason for a status other than "ok", in words."""
        if self.error is not None:
            return (f"{self.failed_stage}: {self.error}",)
        if "check" in self.runs:
            return self.runs["check"].result.reasons
        spline = self.runs.get("spline")
        if spline is not None and not spline.result.ok:
            s = spline.result
            return (f"spline: MVS {s.status}: {s.message}; the curve shown is the initial spline",)
        return ()

    @property
    def message(self) -> str | None:
        return "; ".join(self.reasons) or None

    @property
    def timings_ms(self) -> dict[str, float]:
        return {name: run.ms for name, run in self.runs.items()}


def reconstruct(
    pair: StereoPair,
    calib: StereoCalibration,
    params: Any = None,
    corrections: tuple[Correction, ...] = (),
) -> Reconstruction:
    """One-shot run of the whole pipeline (with the user's mask corrections, if any)."""
    return Pipeline(pair, calib, corrections).run(params)
