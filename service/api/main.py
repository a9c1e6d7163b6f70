"""The HTTP API's factory: settings, store, middleware, routers, in-process workers."""

from __future__ import annotations

from contextlib import asynccontextmanager
from pathlib import Path

import anyio
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from service.api.metrics import RequestMetrics
from service.api.middleware import BodyLimit
from service.api.routes import artifacts, events, jobs, ops
from service.jobs.models import JobStore, StoreUnavailable
from service.settings import Settings, get_settings, make_store
from service.web import routes as web

STATIC_DIR = Path(__file__).resolve().parent / "static"


def create_app(
    settings: Settings | None = None, store: JobStore | None = None, start_workers: bool | None = None
) -> FastAPI:
    """The API; with ``start_workers`` (default: settings.embedded_worker) in-process workers run too."""
    settings = settings or get_settings()
    store = store if store is not None else make_store(settings)
    settings.artifacts_dir.mkdir(parents=True, exist_ok=True)
    run_workers = settings.embedded_worker if start_workers is None else start_workers

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.workers = []
        if run_workers:
            # jobs run in supervised child processes: one that dies (out of memory) fails its
            # job and is replaced, and the API lives on
            from service.supervisor import WorkerSupervisor

            app.state.workers = WorkerSupervisor(settings, store, settings.max_concurrent_jobs).start()
        yield
        if app.state.workers:
            await anyio.to_thread.run_sync(app.state.workers.stop)

    # /docs is served from files inside the package (Swagger UI's own distribution, Apache-2.0):
    # FastAPI's default page loads it from a CDN and is blank without internet
    app = FastAPI(title="QuickNav", version="0.1.0", lifespan=lifespan, docs_url=None,
                  redoc_url=None,
                  description="Submit train, sweep and eval jobs; follow their progress; fetch results.")  # fmt: skip
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.mount("/web/static", StaticFiles(directory=web.STATIC_DIR), name="web-static")

    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url, title="QuickNav API",
            swagger_js_url="/static/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url="/static/swagger-ui/swagger-ui.css",
            swagger_favicon_url="/static/swagger-ui/favicon-32x32.png",
        )  # fmt: skip
    app.state.settings = settings
    app.state.store = store
    app.state.workers = []

    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(RequestMetrics)  # outermost: it sees every answer, 413s included

    @app.exception_handler(StoreUnavailable)
    async def store_unavailable(request: Request, exc: StoreUnavailable):
        # 507 when the disk is full (the request may succeed once space is freed: DELETE frees
        # it), 503 when the store cannot be reached; both say when to retry
        status = 507 if exc.disk_full else 503
        return JSONResponse(
            {"detail": f"the job store is unavailable: {exc.reason}; retry in a few seconds"},
            status_code=status, headers={"Retry-After": str(exc.retry_after_s)},
        )  # fmt: skip

    @app.exception_handler(RequestValidationError)
    async def validation_handler(request: Request, exc: RequestValidationError):
        detail = [{"loc": list(e["loc"]), "msg": e["msg"], "type": e["type"]} for e in exc.errors()]
        return JSONResponse({"detail": detail}, status_code=422)

    app.include_router(jobs.router)
    app.include_router(events.router)
    app.include_router(artifacts.router)
    app.include_router(ops.router)
    app.include_router(web.auth)
    app.include_router(web.router)
    return app
