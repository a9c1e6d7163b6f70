"""`quicknav serve`, `quicknav worker`, `quicknav rollout-server`: the job service and its parts.

These commands need the service extra (``pip install 'quicknav[service]'``; ``uv sync`` installs it).
"""

from __future__ import annotations

import os
from typing import Annotated

import typer

from quicknav_cli.common import (
    console,
    enable_compilation_cache,
    expose_cpu_devices,
    fail,
    service_settings,
    warn,
)


def serve(
    host: Annotated[
        str | None, typer.Option(help="Bind address (QUICKNAV_HOST, default 127.0.0.1).")
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="HTTP port (QUICKNAV_PORT, default 8000).")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="In-process workers (QUICKNAV_MAX_CONCURRENT_JOBS).")
    ] = None,
    no_worker: Annotated[
        bool, typer.Option("--no-worker", help="API only; run `quicknav worker` elsewhere.")
    ] = False,
    api_workers: Annotated[
        int,
        typer.Option(
            min=1,
            max=64,
            help="API processes (each with its own in-process workers unless --no-worker).",
        ),
    ] = 1,
    grpc_port: Annotated[
        int | None, typer.Option(help="gRPC Rollout port (QUICKNAV_GRPC_PORT, default 50051).")
    ] = None,
    no_grpc: Annotated[
        bool, typer.Option("--no-grpc", help="Do not start the gRPC Rollout server.")
    ] = False,
) -> None:
    """Start the HTTP API, the gRPC Rollout server and, by default, an in-process worker."""
    # first: exits with a clear message if the service extra is not installed or a value is bad
    settings = service_settings(host=host, port=port, max_concurrent_jobs=workers,
                                embedded_worker=False if no_worker else None,
                                grpc_port=grpc_port, grpc_enabled=False if no_grpc else None)  # fmt: skip
    import uvicorn

    from quicknav_service import redact
    from quicknav_service.api.http import uvicorn_options
    from quicknav_service.api.main import create_app

    if settings.host not in ("127.0.0.1", "localhost", "::1") and not settings.api_token:
        warn(f"binding {settings.host} without QUICKNAV_API_TOKEN: anyone who can reach this port"
             " can submit jobs")  # fmt: skip
    store = (
        "redis " + redact.redact_url(settings.redis_url)
        if settings.redis_url
        else f"sqlite {settings.data_dir / 'jobs.db'}"
    )
    console.print(f"QuickNav API on http{'s' if settings.tls_cert else ''}://{settings.host}:{settings.port} (docs at /docs), store: {store},"
                  f" artifacts: {settings.artifacts_url or settings.artifacts_dir},"
                  f" in-process workers: {settings.max_concurrent_jobs if settings.embedded_worker else 0}",
                  soft_wrap=True)  # fmt: skip
    from quicknav_service.auth import make_limiter
    from quicknav_service.runtime import service_runtime

    # this process's one runtime (room banks, uploaded maps, compiled programs): the API's checks
    # and the Rollout streams share it
    runtime = service_runtime(settings)
    # one count of failed authentications for the API and the gRPC streams of this process
    # (in Redis, shared by every process of the fleet, when the service runs on Redis)
    limiter = make_limiter(settings)
    rollout = announcer = None
    if settings.grpc_enabled:
        import socket

        from quicknav_service.settings import make_store

        # the API process starts JAX only when a rollout stream needs it
        rollout, announcer = start_rollout(settings, make_store(settings), settings.grpc_port,
                                           f"serve-{socket.gethostname()}-{os.getpid()}",
                                           probe_device=False, runtime=runtime,
                                           auth_limiter=limiter)  # fmt: skip
    # HTTPS when QUICKNAV_TLS_CERT/_KEY are set (uvicorn terminates TLS)
    tls = ({"ssl_certfile": str(settings.tls_cert), "ssl_keyfile": str(settings.tls_key)}
           if settings.tls_cert else {})  # fmt: skip
    try:
        if api_workers > 1:
            # several processes: each builds its app from the same QUICKNAV_* settings
            os.environ["QUICKNAV_EMBEDDED_WORKER"] = "false" if not settings.embedded_worker else "true"
            if not os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
                # request metrics of every API process, summed on any one's /metrics
                import tempfile

                os.environ["PROMETHEUS_MULTIPROC_DIR"] = tempfile.mkdtemp(prefix="quicknav-prom-")
            uvicorn.run("quicknav_service.api.main:create_app", factory=True, host=settings.host,
                        port=settings.port, workers=api_workers, log_level="warning",
                        **uvicorn_options(settings, api_workers), **tls)  # fmt: skip
        else:
            uvicorn.run(create_app(settings, runtime=runtime, auth_limiter=limiter), host=settings.host, port=settings.port,
                        log_level="info", **uvicorn_options(settings), **tls)  # fmt: skip
    finally:
        if announcer is not None:
            announcer.stop()
        if rollout is not None:
            rollout.stop()


def rollout_server(
    host: Annotated[
        str | None, typer.Option(help="Bind address (QUICKNAV_HOST, default 127.0.0.1).")
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="gRPC port (QUICKNAV_GRPC_PORT, default 50051).")
    ] = None,
    cpu_devices: Annotated[
        int,
        typer.Option(
            min=1,
            max=64,
            help="CPU devices XLA exposes; batches of at least 256 envs per device are split"
            " across them (on 2 cores one device was faster: gRPC needs the other core)."
            " Several GPUs are always used.",
        ),
    ] = 1,
) -> None:
    """Only the gRPC Rollout server: remote agents step batches of envs over one stream each."""
    if cpu_devices > 1:
        expose_cpu_devices(cpu_devices)
    enable_compilation_cache()
    from quicknav_service.rollout.server import serve_forever

    settings = service_settings(host=host, grpc_port=port)
    if settings.host not in ("127.0.0.1", "localhost", "::1") and not settings.api_token:
        warn(f"binding {settings.host} without QUICKNAV_API_TOKEN")
    try:
        serve_forever(settings)
    except OSError as e:
        fail(str(e))
    except KeyboardInterrupt:
        pass


def worker(
    burst: Annotated[
        bool,
        typer.Option(
            help="Run queued jobs (and jobs orphaned by a dead worker), exit when none is queued or running."
        ),
    ] = False,
    grpc_port: Annotated[
        int | None,
        typer.Option(
            min=0, max=65535,
            help="Also serve gRPC Rollout on this port, on this worker's device, and list it at"
            " GET /rollout/endpoints (QUICKNAV_WORKER_GRPC_PORT; 0 = any free port).",
        ),
    ] = None,
) -> None:
    """A worker process: claims jobs from the store (Redis for several machines), runs them."""
    import signal

    from quicknav_service.settings import make_store
    from quicknav_service.worker import Worker

    settings = service_settings()
    store = make_store(settings)
    w = Worker(store, settings)
    port = grpc_port if grpc_port is not None else settings.worker_grpc_port
    rollout = announcer = None
    if port is not None and not burst:
        rollout, announcer = start_rollout(settings, store, port, f"worker-{w.id}")

    def on_term(signum, frame):
        console.print("stopping at the next chunk boundary (checkpoint kept, job handed back)")
        w.shutdown.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    console.print(f"worker {w.id} on {'redis' if settings.redis_url else settings.data_dir / 'jobs.db'},"
                  f" artifacts: {w.artifacts.url}",
                  soft_wrap=True)  # fmt: skip
    try:
        if burst:
            ran = w.run_burst()
            console.print(f"burst done: {ran} job(s) run, none queued or running")
        else:
            w.run_forever()
    finally:
        if announcer is not None:
            announcer.stop()
        if rollout is not None:
            rollout.stop()


def start_rollout(settings, store, port: int, name: str, probe_device: bool = True, runtime=None,
                  auth_limiter=None):
    """The gRPC Rollout server of this process, announced in the store for the API to list."""
    from quicknav_service.rollout.announce import EndpointAnnouncer, advertised_address
    from quicknav_service.rollout.server import BackgroundServer

    try:
        rollout = BackgroundServer(settings, port=port, runtime=runtime, auth_limiter=auth_limiter).start()
    except OSError as e:
        fail(str(e))
    address = advertised_address(settings.rollout_advertise, rollout.port, settings.host)
    announcer = EndpointAnnouncer(store, name, address, rollout.servicer,
                                  interval_s=settings.heartbeat_s,
                                  max_sessions=settings.rollout_max_sessions,
                                  probe_device=probe_device).start()  # fmt: skip
    console.print(f"gRPC Rollout on {settings.host}:{rollout.port}, announced as {address}",
                  soft_wrap=True)  # fmt: skip
    return rollout, announcer
