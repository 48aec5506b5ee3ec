"""The debugger's web server: a FastAPI app with one router per resource.

``create_app`` wires the state (:mod:`app.api.state`), the guard (Host/Origin, body limit:
:mod:`app.api.guard`), the error mapping (:mod:`app.api.errors`), the routers and the API docs
served from local files (``fastapi_offline``: no request leaves the machine).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from threadrecon.app.api import errors
from threadrecon.app.api.config import ServerConfig
from threadrecon.app.api.guard import Guard
from threadrecon.app.api.isolation import OriginIsolation
from threadrecon.app.api.routes_corrections import router as corrections
from threadrecon.app.api.routes_evaluations import router as evaluations
from threadrecon.app.api.routes_exports import router as exports
from threadrecon.app.api.routes_frames import router as frames
from threadrecon.app.api.routes_page import STATIC
from threadrecon.app.api.routes_page import router as page
from threadrecon.app.api.routes_presets import router as presets
from threadrecon.app.api.routes_ratings import router as ratings
from threadrecon.app.api.routes_sequences import router as sequences
from threadrecon.app.api.routes_sessions import router as sessions
from threadrecon.app.api.routes_tune import router as tune
from threadrecon.app.api.state import AppState
from threadrecon.app.timeline import Timelines
from threadrecon.app.tune.job import Tuner

__all__ = ["AppState", "ServerConfig", "create_app"]
log = logging.getLogger("threadrecon.server")


def create_app(config: ServerConfig) -> FastAPI:
    state = AppState(config)
    timelines = Timelines(state.library)
    # tunes from the page: their stores next to the ratings database (the user's, never the package)
    tuner = Tuner(config.data_dir, config.db.parent / "tunes", config.configs)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        state.start_viser()
        first = state.library.first_id()
        if config.open_first and first is not None:
            state.session(None).submit(frame_id=first)
        log.info("viser on port %d", state.viser_port)
        reaper = asyncio.create_task(state.expire_sessions())
        try:
            yield
        finally:
            reaper.cancel()
            timelines.close()
            tuner.stop()
            state.stop()

    app = FastAPIOffline(
        title="threadrecon debugger",
        description="Suture-thread reconstruction, stage by stage.",
        lifespan=lifespan,
        favicon_url="/static/favicon.svg",
        swagger_ui_parameters={"validatorUrl": None},  # no badge fetched from swagger.io
    )
    app.state.core = state
    app.state.timelines = timelines
    app.state.tuner = tuner
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    for router in (
        page,
        frames,
        sequences,
        sessions,
        ratings,
        corrections,
        presets,
        evaluations,
        exports,
        tune,
    ):
        app.include_router(router)
    errors.install(app)
    app.add_middleware(OriginIsolation)  # the page renders apart from the 3D viewer
    app.add_middleware(Guard, policy=state.policy, max_body=config.max_body_bytes)
    return app
