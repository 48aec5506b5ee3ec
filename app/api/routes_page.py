"""The page, and the server facts it needs (stages, controls, metric labels, exports)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse, RedirectResponse

from threadrecon.app.api import schemas
from threadrecon.app.api.deps import State
from threadrecon.app.api.routes_exports import EXPORTS
from threadrecon.app.controls import controls
from threadrecon.app.dataset import METRIC_COLUMNS
from threadrecon.app.export import LAYERS
from threadrecon.app.resources import static_dir
from threadrecon.app.views import OVERLAY_VIEWS
from threadrecon.core.pipeline import STAGES, ReconParams

STATIC = static_dir()
METRIC_LABELS = {  # key -> (label, unit) shown by the page's metrics and tables
    "e_S_mm": ("e_S", "mm"), "e_S_max_mm": ("e_S max", "mm"),
    "e_length_mm": ("length error", "mm"), "length_mm": ("length", "mm"),
    "length_gt_mm": ("true length", "mm"),
    "left_mean_px": ("reproj. left mean", "px"), "left_max_px": ("reproj. left max", "px"),
    "right_mean_px": ("reproj. right mean", "px"), "right_max_px": ("reproj. right max", "px"),
    "coverage_left": ("coverage left", ""), "coverage_right": ("coverage right", ""),
}  # fmt: skip

router = APIRouter()


@router.get("/", include_in_schema=False)
def index() -> RedirectResponse:
    return RedirectResponse("/static/index.html")


@router.get("/favicon.ico", include_in_schema=False)
def favicon() -> FileResponse:
    return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml")


@router.get("/api/info", tags=["page"])
def info(state: State) -> schemas.Info:
    """Server facts the page needs: the viser port, the stages, the controls, the metric
    labels, the exportable layers and the exports."""
    metrics = [
        {
            "key": k,
            "label": METRIC_LABELS.get(k, (k, ""))[0],
            "unit": METRIC_LABELS.get(k, (k, ""))[1],
        }
        for k in METRIC_COLUMNS
    ]
    return schemas.Info(
        viser_port=state.viser_port,
        data_dir=str(state.config.data_dir),
        stages=list(STAGES),
        controls=[c.to_dict() for c in controls()],
        defaults=ReconParams().to_dict(),
        metrics=metrics,
        layers=list(LAYERS),
        overlays=[v.spec() for v in OVERLAY_VIEWS.values()],
        exports=list(EXPORTS),
    )
