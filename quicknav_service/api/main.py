"""The HTTP API's factory: it assembles the app (settings, store, middleware, error handlers,
docs, routers) and starts in-process workers when asked; the rules live in the jobs service."""

from __future__ import annotations

import gc
from contextlib import asynccontextmanager

import anyio
from fastapi import APIRouter, FastAPI
from fastapi.routing import APIRoute

from quicknav_core.runtime import Runtime
from quicknav_service.api import docs, errors, openapi
from quicknav_service.api.event_hub import EventHub
from quicknav_service.api.metrics import RequestMetrics
from quicknav_service.api.middleware import BodyLimit, CrossSiteGuard, SecurityHeaders, TrustedHosts
from quicknav_service.api.routes import artifacts, events, jobs, maps, ops
from quicknav_service.api.routes.events import StreamSlots
from quicknav_service.auth import Limiter, make_limiter
from quicknav_service.jobs.models import JobStore
from quicknav_service.maps import DecodeBudget
from quicknav_service.runtime import service_runtime
from quicknav_service.settings import Settings, get_settings, make_store
from quicknav_service.web import routes as web

DESCRIPTION = "Submit train, sweep and eval jobs; follow their progress; fetch results."


def operation_id(route: APIRoute) -> str:
    """The operationId of a route: its handler's name (``submit_train_job``, ``list_jobs``)."""
    return route.name


def api_version() -> str:
    """The package's version (one source: the installed distribution's metadata)."""
    import quicknav_core

    version = getattr(quicknav_core, "__version__", None)
    if version:
        return version
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("quicknav")
    except PackageNotFoundError:
        return "0+unknown"


def create_app(
    settings: Settings | None = None, store: JobStore | None = None, start_workers: bool | None = None,
    runtime: Runtime | None = None, auth_limiter: Limiter | None = None,
) -> FastAPI:
    """The API; with ``start_workers`` (default: settings.embedded_worker) in-process workers run too."""
    settings = settings or get_settings()
    store = store if store is not None else make_store(settings)
    # the data folder (its disk is a readiness check) and, without an object store, the artifacts
    (settings.data_dir if settings.artifacts_url else settings.artifacts_dir).mkdir(parents=True,
                                                                                   exist_ok=True)
    run_workers = settings.embedded_worker if start_workers is None else start_workers

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        # what start-up made (modules, the app, schemas) lives as long as the process: out of the
        # garbage collector's reach, a full collection walks only what requests make, and stops
        # the event loop for a millisecond instead of tens
        gc.collect()
        gc.freeze()
        app.state.workers = []
        if run_workers:
            # jobs run in supervised child processes: one that dies (out of memory) fails its
            # job and is replaced, and the API lives on
            from quicknav_service.supervisor import WorkerSupervisor

            app.state.workers = WorkerSupervisor(settings, store, settings.max_concurrent_jobs).start()
        yield
        await app.state.event_hub.close()
        if app.state.workers:
            await anyio.to_thread.run_sync(app.state.workers.stop)

    app = FastAPI(title="QuickNav", version=api_version(), description=DESCRIPTION,
                  lifespan=lifespan, docs_url=None, redoc_url=None,
                  generate_unique_id_function=operation_id)  # fmt: skip
    app.state.settings = settings
    app.state.store = store
    # this process's room banks, uploaded maps and artifact store, for every request's checks
    app.state.runtime = runtime if runtime is not None else service_runtime(settings)
    # failed authentications per client address: one count for this process's doors (REST and,
    # under `quicknav serve`, gRPC), shared by the fleet through Redis when the store is Redis
    app.state.auth_limiter = auth_limiter if auth_limiter is not None else make_limiter(settings)
    # uploaded maps are decoded within one memory budget per process (concurrent uploads wait)
    app.state.map_decode_budget = DecodeBudget(settings.map_decode_mb * 2**20)
    app.state.streams = StreamSlots(settings.sse_max_per_client, settings.sse_max_total)
    app.state.event_hub = EventHub(store)
    app.state.workers = []
    app.state.route_table = errors.RouteTable(app)
    docs.install(app)
    errors.install(app)
    openapi.install(app, api_token=settings.api_token is not None,
                    metrics_token=settings.metrics_token is not None,
                    max_eval_episodes=settings.max_eval_episodes)  # fmt: skip
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes,
                       uploads={"/maps": settings.max_map_upload_bytes})  # fmt: skip
    app.add_middleware(CrossSiteGuard, origins=settings.trusted_origins, routes=app.state.route_table)
    app.add_middleware(TrustedHosts, hosts=settings.trusted_hosts)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RequestMetrics)  # outermost: it sees every answer, refusals included

    app.include_router(jobs.router)
    app.include_router(events.router)
    app.include_router(artifacts.router)
    app.include_router(maps.router)
    app.include_router(ops.router)
    app.include_router(_documented(web.auth, {"POST": errors.responses(400, 401, 403, 413, 415, 422, 429)}))
    app.include_router(web.router)
    return app


def _documented(router: APIRouter, extra: dict[str, dict]) -> APIRouter:
    """``router`` with error responses added to its routes by method (the browser view's session
    routes: signing in checks a body and the token)."""
    out = APIRouter()
    for r in router.routes:
        more = {code: doc for m in r.methods for code, doc in extra.get(m, {}).items()}
        out.add_api_route(r.path, r.endpoint, methods=list(r.methods), name=r.name, tags=r.tags,
                          response_model=r.response_model, status_code=r.status_code,
                          description=r.description, responses={**r.responses, **more},
                          response_class=r.response_class)  # fmt: skip
    return out
