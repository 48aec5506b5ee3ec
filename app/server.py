"""``threadrecon serve``: the FastAPI app of the debugger, with a viser server in its lifespan.

The page (``static/``) creates a session, embeds the viser client with the session id in its
websocket path (``ws://host:port/session/<id>``) so that the 3D view, the sliders and the page
all belong to the same session, and polls the session's state. The REST API (``/docs``) is what
the page and the tests use.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import threading
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
import viser
from fastapi import Body, FastAPI, HTTPException, Query, Request
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel

from app.controls import controls
from app.dataset import METRIC_COLUMNS, frame_inputs, frame_rectification
from app.evaluation import evaluate_frame
from app.export import LAYERS as EXPORT_LAYERS
from app.export import cloud_ply, json_safe, spline_csv, spline_json
from app.jobs import EvaluationJob, compare
from app.presets import (
    NAME_RE,
    default_configs_dir,
    diff,
    list_presets,
    load_preset,
    params_hash,
    save_preset,
)
from app.ratings import RatingStore, StoreError
from app.scene import SceneView
from app.session import FrameLibrary, Session, SessionManager, merge_params
from app.views import pixel_info, stage_json
from core.pipeline import STAGES, ReconParams

log = logging.getLogger("threadrecon.server")
STATIC = Path(__file__).resolve().parent.parent / "static"
RUN_TIMEOUT_S = 120.0  # a REST run waits this long for its result before answering 504
API_SESSION = "api"  # the session used by REST calls that name none
DB_NAME = "threadrecon.sqlite3"
EXPORTS = {  # export name -> media type
    "spline.json": "application/json",
    "spline.csv": "text/csv",
    **{f"{layer}.ply": "application/octet-stream" for layer in EXPORT_LAYERS},
}


@dataclass
class ServerConfig:
    data_dir: Path
    host: str = "127.0.0.1"
    port: int = 8000
    viser_port: int = 8080
    open_first: bool = True
    """Run the first frame at start-up, so the page shows a reconstruction without a click."""
    db_path: Path | None = None
    """Ratings and evaluations (SQLite); default ``<data_dir>/threadrecon.sqlite3``."""
    configs_dir: Path | None = None
    """Preset folder; default the project's ``configs/``."""

    @property
    def db(self) -> Path:
        return self.db_path or self.data_dir / DB_NAME

    @property
    def configs(self) -> Path:
        return self.configs_dir or default_configs_dir()


class AppState:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.library = FrameLibrary(config.data_dir)
        self.store = RatingStore(config.db)  # StoreError now, not at the first rating
        self.job: EvaluationJob | None = None
        self.job_saved: int | None = None
        self._job_lock = threading.Lock()
        self.sessions = SessionManager(self.library)
        self.viser: viser.ViserServer | None = None
        self._views: dict[int, tuple[Session, SceneView]] = {}
        self._lock = threading.Lock()

    # --- viser ------------------------------------------------------------------------------

    def start_viser(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print one URL
            server = viser.ViserServer(
                host=self.config.host, port=self.config.viser_port, verbose=False
            )
        server.scene.set_up_direction("-y")
        server.scene.configure_environment_map(hdri=None)
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self.viser = server

    @property
    def viser_port(self) -> int:
        assert self.viser is not None
        return self.viser.get_port()

    def _session_of(self, client: viser.ClientHandle) -> Session:
        """The session named in the client's websocket path (``/session/<id>``), or a new one
        for a viser client opened on its own."""
        sid = None
        with contextlib.suppress(AttributeError, KeyError):  # viser internals: best effort
            conn = self.viser._websock_server._live_connections[client.client_id]  # type: ignore[union-attr]
            path = conn.request.path.partition("?")[0]
            parts = [p for p in path.split("/") if p]
            if len(parts) == 2 and parts[0] == "session":
                sid = parts[1]
        session = self.sessions.find(sid) if sid else None
        if session is None:
            session = self.sessions.create(sid)
            session.submit()
        return session

    def _on_connect(self, client: viser.ClientHandle) -> None:
        session = self._session_of(client)
        view = SceneView(client, session)
        with self._lock:
            self._views[client.client_id] = (session, view)
        session.attach(client.client_id, view)

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            entry = self._views.pop(client.client_id, None)
        if entry is not None:
            entry[0].detach(client.client_id)

    def stop(self) -> None:
        if self.job is not None:
            self.job.cancel()
        self.sessions.close()
        self.store.close()
        if self.viser is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                self.viser.stop()
            self.viser = None

    # --- helpers ----------------------------------------------------------------------------

    def session(self, sid: str | None) -> Session:
        if sid is None or sid == API_SESSION:
            return self.sessions.find(API_SESSION) or self.sessions.create(API_SESSION)
        try:
            return self.sessions.get(sid)
        except KeyError as exc:
            raise HTTPException(404, str(exc.args[0])) from None

    def start_job(self, params: ReconParams, preset: str) -> EvaluationJob:
        with self._job_lock:
            if self.job is not None and self.job.state in ("pending", "running"):
                raise HTTPException(409, "an evaluation is already running: cancel it first")
            frames = list(self.library.frames.values())
            self.job = EvaluationJob(frames, params, preset, on_done=self._job_done)
            self.job_saved = None
            return self.job.start()

    def _job_done(self, job: EvaluationJob) -> None:
        if job.state == "done":
            self.job_saved = self.store.save_evaluation(
                job.preset, job.params_hash, job.params.to_dict(), job.rows, job.summary
            )

    def frame_or_404(self, frame_id: str) -> None:
        try:
            self.library.get(frame_id)
        except KeyError as exc:
            raise HTTPException(404, str(exc.args[0])) from None


class RunBody(BaseModel):
    params: dict[str, Any] | None = None
    """Partial parameters ``{stage: {name: value}}`` applied over the session's current ones."""
    preset: str | None = None
    """Start from this preset instead of the session's current parameters."""
    until: str | None = None
    """Compute and show the stages up to this one (default: all)."""
    session: str | None = None
    pause_ms: float = 0.0
    wait: bool = True


class RatingBody(BaseModel):
    score: Any = None
    """1..5 (whole number)."""
    note: Any = ""
    session: str | None = None
    """The session whose reconstruction is rated (its preset and parameters are recorded)."""


class SavePresetBody(BaseModel):
    name: str
    session: str | None = None
    overwrite: bool = False


class UsePresetBody(BaseModel):
    name: str
    wait: bool = False


class EvaluateBody(BaseModel):
    session: str | None = None
    preset: str | None = None


class StepBody(BaseModel):
    action: str
    """"run" (all stages, streamed one by one), "next" (reveal one more stage), "all"."""
    pause_ms: float = 350.0


def create_app(config: ServerConfig) -> FastAPI:
    state = AppState(config)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state.start_viser()
        if config.open_first and state.library.frames:
            state.session(None).submit(frame_id=next(iter(state.library.frames)))
        log.info("viser on port %d", state.viser_port)
        try:
            yield
        finally:
            state.stop()

    app = FastAPI(
        title="threadrecon debugger",
        description="Suture-thread reconstruction, stage by stage.",
        lifespan=lifespan,
    )
    app.state.core = state

    # --- page -------------------------------------------------------------------------------

    @app.get("/", include_in_schema=False)
    def index() -> RedirectResponse:
        return RedirectResponse("/static/index.html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/api/info")
    def info() -> dict[str, Any]:
        """Server facts the page needs: the viser port, the stages, the controls."""
        return {
            "viser_port": state.viser_port,
            "data_dir": str(config.data_dir),
            "stages": list(STAGES),
            "controls": [c.to_dict() for c in controls()],
            "defaults": ReconParams().to_dict(),
        }

    # --- frames -----------------------------------------------------------------------------

    @app.get("/api/frames")
    def frames() -> list[dict[str, Any]]:
        """Every frame of the data folder, with the status of its last run."""
        status = state.sessions.frame_status
        ratings = _store(state.store.latest_all)
        return [
            {
                "id": f.id,
                "name": f.name,
                "kind": f.kind,
                "has_ground_truth": f.has_ground_truth,
                "status": status.get(f.id),
                "rating": ratings[f.id].score if f.id in ratings else None,
            }
            for f in state.library.frames.values()
        ]

    @app.get("/api/frames/{frame_id:path}/images/{side}")
    def frame_image(frame_id: str, side: str) -> Response:
        """The rectified left or right image as PNG."""
        state.frame_or_404(frame_id)
        if side not in ("left", "right"):
            raise HTTPException(404, f"no image {side!r}: use left or right")
        try:
            loaded = state.library.load(frame_id)
        except (ValueError, OSError) as exc:
            raise HTTPException(422, f"cannot load frame {frame_id}: {exc}") from None
        img = loaded.pair.left if side == "left" else loaded.pair.right
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR))
        if not ok:
            raise HTTPException(500, "PNG encoding failed")
        return Response(
            png.tobytes(), media_type="image/png", headers={"Cache-Control": "max-age=3600"}
        )

    @app.post("/api/frames/{frame_id:path}/run")
    def run_frame(frame_id: str, body: Annotated[RunBody | None, Body()] = None) -> JSONResponse:
        """Select the frame in a session (default: the API session) and run it with the given
        parameters; answers with the session state when done."""
        state.frame_or_404(frame_id)
        body = body or RunBody()
        session = state.session(body.session)
        base = session.params
        preset = None
        if body.preset is not None:
            base = _load_preset(config.configs, body.preset)
            preset = body.preset
        try:
            params = merge_params(base, body.params or {})
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        if body.until is not None and body.until not in STAGES:
            raise HTTPException(422, f"until: unknown stage {body.until!r}")
        reveal = STAGES.index(body.until) + 1 if body.until else len(STAGES)
        seq = session.submit(
            frame_id=frame_id, params=params, reveal=reveal, pause_s=body.pause_ms / 1000.0,
            preset=preset,
        )  # fmt: skip
        if body.wait and not session.wait(seq, RUN_TIMEOUT_S):
            raise HTTPException(504, "the run did not finish in time")
        return JSONResponse(json_safe(session.state()))

    @app.get("/api/frames/{frame_id:path}/stages/{stage}")
    def frame_stage(frame_id: str, stage: str, session: str | None = None) -> JSONResponse:
        """One stage's result of the frame as the session last computed it (the frame is run
        with the session's parameters first if the session shows another frame)."""
        state.frame_or_404(frame_id)
        if stage not in STAGES:
            raise HTTPException(404, f"unknown stage {stage!r} (stages: {', '.join(STAGES)})")
        s = state.session(session)
        if (
            s.frame_id != frame_id
            or s.rec is None
            or s.loaded is None
            or s.loaded.frame.id != frame_id
        ):
            s.wait(s.submit(frame_id=frame_id), RUN_TIMEOUT_S)
        else:
            s.wait_idle(RUN_TIMEOUT_S)
        rec = s.rec
        if rec is None:
            raise HTTPException(409, s.load_error or "no reconstruction")
        try:
            return JSONResponse(stage_json(rec, stage))
        except LookupError as exc:
            raise HTTPException(409, str(exc.args[0])) from None

    # --- sessions ---------------------------------------------------------------------------

    @app.post("/api/sessions")
    def new_session(frame_id: str | None = None) -> dict[str, Any]:
        """A session for one browser tab; its viser client connects to ``viser_path``."""
        if frame_id is not None:
            state.frame_or_404(frame_id)
        s = state.sessions.create()
        s.submit(frame_id=frame_id)
        return {"session": s.id, "viser_port": state.viser_port, "viser_path": f"/session/{s.id}"}

    @app.get("/api/sessions/{sid}")
    def session_state(
        sid: str, since: int | None = None, timeout: float = Query(0.0, le=25.0)
    ) -> JSONResponse:
        """The session's stepper, metrics and errors; with ``since``, waits up to ``timeout`` s
        for a version newer than ``since`` (long poll)."""
        s = state.session(sid)
        if since is not None and timeout > 0:
            _wait_version(s, since, timeout)
        return JSONResponse(json_safe(s.state()))

    @app.patch("/api/sessions/{sid}/params")
    def patch_params(
        sid: str, patch: Annotated[dict[str, Any], Body()], wait: bool = False
    ) -> JSONResponse:
        """Change parameters (``{stage: {name: value}}``); 422 names a refused parameter."""
        s = state.session(sid)
        try:
            params = merge_params(s.params, patch)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        seq = s.submit(params=params)
        if wait:
            s.wait(seq, RUN_TIMEOUT_S)
        return JSONResponse(json_safe(s.state()))

    @app.post("/api/sessions/{sid}/params/reset")
    def reset_params(sid: str, wait: bool = False) -> JSONResponse:
        s = state.session(sid)
        seq = s.submit(params=ReconParams(), preset="default")
        if wait:
            s.wait(seq, RUN_TIMEOUT_S)
        return JSONResponse(json_safe(s.state()))

    @app.post("/api/sessions/{sid}/step")
    def step(sid: str, body: StepBody, wait: bool = False) -> JSONResponse:
        """The stage stepper: run (streamed), next (reveal one more stage) or all."""
        s = state.session(sid)
        try:
            seq = s.step(body.action, pause_s=body.pause_ms / 1000.0)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        if wait:
            s.wait(seq, RUN_TIMEOUT_S)
        return JSONResponse(json_safe(s.state()))

    @app.get("/api/sessions/{sid}/overlay")
    def session_overlay(sid: str) -> JSONResponse:
        """The 2D overlays of the session's current reconstruction."""
        return JSONResponse(state.session(sid).overlay())

    @app.get("/api/sessions/{sid}/pixel")
    def session_pixel(sid: str, x: int, y: int) -> JSONResponse:
        """Pixel inspector: the energy curve E(d) of a left-image pixel, d_min, d_next, R, depth.
        The pixel becomes the session's inspected pixel (marked in 3D)."""
        s = state.session(sid)
        rec = s.rec
        if rec is None:
            raise HTTPException(409, "no reconstruction yet")
        try:
            info = pixel_info(rec, x, y)
        except LookupError as exc:
            raise HTTPException(409, str(exc.args[0])) from None
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        s.set_inspect(info)
        return JSONResponse(info)

    @app.get("/api/sessions/{sid}/stages/{stage}")
    def session_stage(sid: str, stage: str) -> JSONResponse:
        s = state.session(sid)
        if s.rec is None:
            raise HTTPException(409, s.load_error or "no reconstruction yet")
        try:
            return JSONResponse(stage_json(s.rec, stage))
        except KeyError as exc:
            raise HTTPException(404, str(exc.args[0])) from None
        except LookupError as exc:
            raise HTTPException(409, str(exc.args[0])) from None

    # --- ratings ----------------------------------------------------------------------------

    @app.put("/api/frames/{frame_id:path}/rating")
    def put_rating(frame_id: str, body: RatingBody) -> JSONResponse:
        """Rate the frame's reconstruction 1-5 (the paper's quality score; below 3 is a
        failure) with a note. The rating records the preset and the hash of the parameters of
        the reconstruction the session shows; earlier ratings stay in the history."""
        state.frame_or_404(frame_id)
        s = state.session(body.session)
        shown = s.rec is not None and s.loaded is not None and s.loaded.frame.id == frame_id
        params = s.rec.params if shown else s.params  # type: ignore[union-attr]
        try:
            rating = _store(
                state.store.add_rating, frame_id, body.score, body.note, s.preset,
                params_hash(params),
            )  # fmt: skip
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        history = _store(state.store.history, frame_id)
        return JSONResponse(
            {
                "frame_id": frame_id,
                "latest": rating.to_dict(),
                "history": [r.to_dict() for r in history],
            }
        )

    @app.get("/api/frames/{frame_id:path}/rating")
    def get_rating(frame_id: str) -> JSONResponse:
        """The latest rating of the frame (null if none) and its history, newest first."""
        state.frame_or_404(frame_id)
        history = _store(state.store.history, frame_id)
        return JSONResponse(
            {
                "frame_id": frame_id,
                "latest": history[0].to_dict() if history else None,
                "history": [r.to_dict() for r in history],
            }
        )

    @app.get("/api/ratings.csv")
    def ratings_csv(history: bool = True) -> Response:
        """Every rating (or only the latest per frame) as CSV."""
        text = _store(state.store.ratings_csv, history)
        return Response(
            text, media_type="text/csv",
            headers={"Content-Disposition": 'attachment; filename="ratings.csv"'},
        )  # fmt: skip

    @app.get("/api/ratings/summary")
    def ratings_summary(session: str | None = None) -> JSONResponse:
        """The paper's Table II for the rated frames: reprojection errors and coverage of the
        session's current parameters, the latest score, and the failure rate (score < 3)."""
        s = state.session(session)
        current = params_hash(s.params)
        latest = _store(state.store.latest_all)
        rows = []
        for frame_id, rating in sorted(latest.items()):
            frame = state.library.frames.get(frame_id)
            if frame is None:
                continue
            row, _ = evaluate_frame(frame, s.params)
            rows.append(
                {
                    "frame": frame_id,
                    "kind": frame.kind,
                    "score": rating.score,
                    "note": rating.note,
                    "rated_at": rating.created_at,
                    "preset": rating.preset,
                    "params_hash": rating.params_hash,
                    "same_params": rating.params_hash == current,
                    "status": row["status"],
                    **{c: row[c] for c in METRIC_COLUMNS[5:]},
                }
            )
        n = len(rows)
        summary: dict[str, Any] = {"rated": n, "failures": sum(r["score"] < 3 for r in rows)}
        summary["failure_rate"] = summary["failures"] / n if n else None
        summary["mean_score"] = float(np.mean([r["score"] for r in rows])) if n else None
        for c in METRIC_COLUMNS[5:]:
            v = np.array([r[c] for r in rows], dtype=float)
            v = v[np.isfinite(v)]
            summary[c] = float(v.mean()) if v.size else None
        return JSONResponse(json_safe({"rows": rows, "summary": summary, "params_hash": current}))

    # --- presets ----------------------------------------------------------------------------

    @app.get("/api/presets")
    def presets() -> list[str]:
        """Names of the presets in the configs folder."""
        return list_presets(config.configs)

    @app.get("/api/presets/{name}")
    def preset(name: str) -> JSONResponse:
        """A preset's values and its difference from the defaults; 422 names a bad key."""
        params = _load_preset(config.configs, name)
        return JSONResponse(
            json_safe({"name": name, "params": params.to_dict(), "diff": diff(params)})
        )

    @app.post("/api/presets")
    def save(body: SavePresetBody) -> JSONResponse:
        """Save the session's current parameters as a preset. An existing name is refused
        (409) unless ``overwrite`` is true."""
        s = state.session(body.session)
        try:
            path = save_preset(
                s.params, body.name, config.configs, overwrite=body.overwrite,
                header=f"saved from the debugger; params hash {params_hash(s.params)}",
            )  # fmt: skip
        except FileExistsError as exc:
            raise HTTPException(409, str(exc)) from None
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        except OSError as exc:
            raise HTTPException(507, f"cannot write preset {body.name!r}: {exc}") from None
        s.preset = body.name
        s.version += 1
        return JSONResponse({"name": body.name, "path": str(path)})

    @app.post("/api/sessions/{sid}/preset")
    def use_preset(sid: str, body: UsePresetBody) -> JSONResponse:
        """Load a preset into the session: every slider takes its value, then it runs."""
        s = state.session(sid)
        params = _load_preset(config.configs, body.name)
        seq = s.submit(params=params, preset=body.name)
        if body.wait:
            s.wait(seq, RUN_TIMEOUT_S)
        return JSONResponse(json_safe(s.state()))

    # --- whole-dataset evaluation -----------------------------------------------------------

    @app.post("/api/evaluations")
    def start_evaluation(body: EvaluateBody) -> JSONResponse:
        """Evaluate every frame of the data folder in the background with the session's
        current parameters (or a named preset); poll ``/api/evaluations/current``."""
        if body.preset is not None:
            params, name = _load_preset(config.configs, body.preset), body.preset
        else:
            s = state.session(body.session)
            params, name = s.params, s.preset
        job = state.start_job(params, name)
        return JSONResponse(job.snapshot())

    @app.get("/api/evaluations/current")
    def current_evaluation(since: int = Query(0, ge=0)) -> JSONResponse:
        """Progress and rows (from row ``since`` on) of the running or last evaluation (null
        when none was started since the server started)."""
        job = state.job
        if job is None:
            return JSONResponse(None)  # none since the server started
        snap = job.snapshot(since)
        snap["saved_id"] = state.job_saved
        return JSONResponse(snap)

    @app.post("/api/evaluations/current/cancel")
    def cancel_evaluation() -> JSONResponse:
        job = state.job
        if job is None:
            raise HTTPException(404, "no evaluation to cancel")
        job.cancel()
        job.wait(RUN_TIMEOUT_S)
        return JSONResponse(job.snapshot())

    @app.get("/api/evaluations")
    def evaluations() -> JSONResponse:
        """Saved evaluations, newest first."""
        return JSONResponse(json_safe(_store(state.store.evaluations)))

    @app.get("/api/evaluations/compare")
    def compare_evaluations(a: int, b: int) -> JSONResponse:
        """Two saved evaluations side by side, frame by frame (b - a), with a mean row."""
        ea, eb = (_store(state.store.evaluation, i) for i in (a, b))
        for i, e in ((a, ea), (b, eb)):
            if e is None:
                raise HTTPException(404, f"no saved evaluation {i}")
        return JSONResponse(
            json_safe(
                {
                    "a": {k: ea[k] for k in ("id", "preset", "params_hash", "created_at")},
                    "b": {k: eb[k] for k in ("id", "preset", "params_hash", "created_at")},
                    "rows": compare(ea["rows"], eb["rows"]),
                }
            )
        )

    @app.get("/api/evaluations/{eid}")
    def evaluation(eid: str) -> JSONResponse:
        """One saved evaluation (``last`` for the newest): rows, summary, parameters."""
        if eid == "last":  # the newest, or null when none was saved yet
            return JSONResponse(json_safe(_store(state.store.last_evaluation)))
        if not eid.isdigit():
            raise HTTPException(404, f"no saved evaluation {eid!r}")
        e = _store(state.store.evaluation, int(eid))
        if e is None:
            raise HTTPException(404, f"no saved evaluation {eid!r}")
        return JSONResponse(json_safe(e))

    # --- exports ----------------------------------------------------------------------------

    @app.get("/api/sessions/{sid}/export/{name}")
    def export(sid: str, name: str) -> Response:
        """The current frame's final spline (JSON: control points, knots, degree, dense
        points, keypoint reliability; CSV: dense points) or a point cloud as PLY."""
        if name not in EXPORTS:
            raise HTTPException(404, f"no export {name!r} (exports: {', '.join(EXPORTS)})")
        s = state.session(sid)
        rec, loaded = s.rec, s.loaded
        if rec is None or loaded is None:
            raise HTTPException(409, s.load_error or "no reconstruction yet")
        try:
            if name == "spline.json":
                result = spline_json(  # the CLI's schema, in the left camera frame
                    rec, frame_rectification(loaded.frame), "left", s.preset,
                    frame_inputs(loaded.frame),
                )  # fmt: skip
                data = json.dumps(result, indent=1, allow_nan=False).encode()
            elif name == "spline.csv":
                data = spline_csv(rec).encode()
            else:
                data = cloud_ply(rec, name.removesuffix(".ply"))
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        filename = f"{loaded.frame.name}_{name}"
        return Response(
            data, media_type=EXPORTS[name],
            headers={"Content-Disposition": f'attachment; filename="{filename}"'},
        )  # fmt: skip

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> FileResponse:
        return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml")

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s", request.url.path)
        return JSONResponse({"detail": f"internal error: {type(exc).__name__}: {exc}"}, 500)

    return app


def _store(fn: Any, *args: Any) -> Any:
    """Call the rating store; a database that fails now answers 503 with the reason."""
    try:
        return fn(*args)
    except StoreError as exc:
        raise HTTPException(503, str(exc)) from None


def _load_preset(folder: Path, name: str) -> ReconParams:
    if not NAME_RE.match(name):
        raise HTTPException(422, f"invalid preset name {name!r}")
    path = folder / f"{name}.toml"
    if not path.exists():
        raise HTTPException(404, f"no preset {name!r} in {folder}")
    try:
        return load_preset(path)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


def _wait_version(s: Session, since: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while s.version <= since and time.monotonic() < deadline:
        time.sleep(0.02)


def serve(config: ServerConfig) -> None:
    import uvicorn

    app = create_app(config)
    state: AppState = app.state.core
    uv = uvicorn.Server(
        uvicorn.Config(app, host=config.host, port=config.port, log_level="warning")
    )

    original = uv.startup

    async def startup(sockets: Any = None) -> None:
        await original(sockets)
        if uv.started:
            print(
                f"threadrecon debugger: open http://{config.host}:{config.port}/  "
                f"({len(state.library.frames)} frames of {config.data_dir}; "
                f"3D view on port {state.viser_port})",
                flush=True,
            )

    uv.startup = startup  # type: ignore[method-assign]
    uv.run()
