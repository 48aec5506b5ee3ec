"""The reconstruction pipeline: the stages in order, timed, each cached by the parameters it
depends on (its own and those of every stage before it), so that changing a late parameter
re-runs only the stages after it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from typing import Any

from threadpoolctl import ThreadpoolController

from core.bounds import BoundsParams, depth_bounds
from core.calibration import StereoCalibration
from core.camera import CameraParams, to_camera
from core.check import CheckParams, check_curve
from core.clustering import ClusterParams, cluster_keypoints
from core.ordering import OrderingParams, order_keypoints
from core.reliability import ReliabilityParams, prune
from core.segmentation import SegmentationParams, StereoPair, segment
from core.spline import SplineParams, fit_spline
from core.stereo import StereoParams, match_stereo

# One BLAS thread while a stage runs: a multithreaded BLAS sums in another order, and SLSQP's
# path through Eq. (8) amplified that into a different curve ("n_ctrl = 40" on blend3_1 failed
# with one thread and gave 552 km with several). Created once: creation scans loaded libraries.
_BLAS = ThreadpoolController()

STAGES = (
    "segment",
    "stereo",
    "reliability",
    "clustering",
    "ordering",
    "bounds",
    "spline",
    "camera",
    "check",
)


@dataclass(frozen=True)
class ReconParams:
    """Every parameter of the core, one frozen dataclass per stage (field name = stage name)."""

    segment: SegmentationParams = field(default_factory=SegmentationParams)
    stereo: StereoParams = field(default_factory=StereoParams)
    reliability: ReliabilityParams = field(default_factory=ReliabilityParams)
    clustering: ClusterParams = field(default_factory=ClusterParams)
    ordering: OrderingParams = field(default_factory=OrderingParams)
    bounds: BoundsParams = field(default_factory=BoundsParams)
    spline: SplineParams = field(default_factory=SplineParams)
    camera: CameraParams = field(default_factory=CameraParams)
    check: CheckParams = field(default_factory=CheckParams)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {
            f.name: {
                g.name: getattr(getattr(self, f.name), g.name)
                for g in fields(getattr(self, f.name))
            }
            for f in fields(self)
        }


class StageError(ValueError):
    """A stage could not produce its result; ``stage`` names it."""

    def __init__(self, stage: str, message: str) -> None:
        super().__init__(f"{stage}: {message}")
        self.stage = stage
        self.reason = message


@dataclass(frozen=True)
class StageRun:
    stage: str
    result: Any
    ms: float
    """Wall time of the computation, ms (0 when taken from the cache)."""
    cached: bool


class Pipeline:
    """Runs the stages on one stereo pair; results are cached per stage."""

    def __init__(self, pair: StereoPair, calib: StereoCalibration) -> None:
        if pair.shape != calib.image_size:
            raise ValueError(
                f"images are {pair.shape} px but the calibration is for {calib.image_size}"
            )
        self.pair = pair
        self.calib = calib
        self._cache: dict[str, tuple[tuple, Any]] = {}
        self.last_ms: dict[str, float] = {}

    def _compute(self, stage: str, r: dict[str, Any], p: ReconParams) -> Any:
        c = self.calib
        fns: dict[str, Callable[[], Any]] = {
            "segment": lambda: segment(self.pair, p.segment),
            "stereo": lambda: match_stereo(r["segment"], c, p.stereo),
            "reliability": lambda: prune(r["stereo"], p.reliability),
            "clustering": lambda: cluster_keypoints(r["stereo"], r["reliability"], p.clustering),
            "ordering": lambda: order_keypoints(
                r["segment"], r["stereo"], r["clustering"], p.ordering
            ),
            "bounds": lambda: depth_bounds(r["stereo"], r["ordering"], c, p.bounds),
            "spline": lambda: fit_spline(r["bounds"], c, p.spline),
            "camera": lambda: to_camera(r["spline"], c, p.camera),
            "check": lambda: check_curve(
                *(r[s] for s in ("segment", "stereo", "reliability", "ordering", "bounds")),
                r["spline"],
                r["camera"],
                c,
                p.check,
            ),  # fmt: skip
        }
        return fns[stage]()

    def stages(
        self, params: ReconParams = ReconParams(), until: str = STAGES[-1]
    ) -> Iterator[StageRun]:
        """Yield each stage's run in order up to ``until``; raises :class:`StageError`."""
        if until not in STAGES:
            raise ValueError(f"unknown stage {until!r}")
        results: dict[str, Any] = {}
        key: tuple = ()
        for stage in STAGES:
            key = (*key, getattr(params, stage))
            hit = self._cache.get(stage)
            if hit is not None and hit[0] == key:
                results[stage] = hit[1]
                yield StageRun(stage, hit[1], 0.0, True)
            else:
                t0 = time.perf_counter()
                try:
                    with _BLAS.limit(limits=1, user_api="blas"):
                        out = self._compute(stage, results, params)
                except StageError:
                    raise
                except (ValueError, ArithmeticError, IndexError) as exc:
                    self._cache.pop(stage, None)
                    raise StageError(stage, str(exc)) from exc
                ms = 1000.0 * (time.perf_counter() - t0)
                self._cache[stage] = (key, out)
                self.last_ms[stage] = ms
                results[stage] = out
                yield StageRun(stage, out, ms, False)
            if stage == until:
                return

    def run(self, params: ReconParams = ReconParams(), until: str = STAGES[-1]) -> Reconstruction:
        """Run every stage up to ``until``; a failing stage is reported, not raised."""
        runs: dict[str, StageRun] = {}
        try:
            for run in self.stages(params, until):
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
    pair: StereoPair, calib: StereoCalibration, params: ReconParams = ReconParams()
) -> Reconstruction:
    """One-shot run of the whole pipeline."""
    return Pipeline(pair, calib).run(params)
