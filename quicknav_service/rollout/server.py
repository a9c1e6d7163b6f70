"""Start the gRPC Rollout server: on its own (`quicknav rollout-server`) or beside the HTTP API."""

from __future__ import annotations

import asyncio
import logging
import threading

import grpc
from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc

from quicknav_core.runtime import Runtime
from quicknav_service import auth
from quicknav_service.rollout.policy import PolicyServicer
from quicknav_service.rollout.servicer import RolloutServicer
from quicknav_service.runtime import service_runtime
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.rollout")


ROLLOUT_SERVICE = "quicknav.v1.RolloutService"
POLICY_SERVICE = "quicknav.v1.PolicyService"


def server_credentials(settings: Settings) -> grpc.ServerCredentials | None:
    """TLS for the gRPC port when QUICKNAV_GRPC_TLS_CERT and _KEY name a PEM certificate chain and
    key (None: plaintext)."""
    if not settings.grpc_tls_cert:
        return None
    try:
        chain = settings.grpc_tls_cert.read_bytes()
        key = settings.grpc_tls_key.read_bytes()  # validated as set together
    except OSError as e:
        raise OSError(f"cannot read the gRPC TLS files (QUICKNAV_GRPC_TLS_CERT/_KEY): {e}") from e
    return grpc.ssl_server_credentials([(key, chain)])


async def start_server(
    settings: Settings, host: str | None = None, port: int | None = None,
    runtime: Runtime | None = None,
    auth_limiter: auth.Limiter | None = None,
) -> tuple[grpc.aio.Server, int, RolloutServicer]:
    """A started grpc.aio server bound to host:port (port 0 picks a free one); returns the port.

    Beside Rollout it serves the standard ``grpc.health.v1.Health`` (SERVING for "" and for the
    Rollout service; NOT_SERVING once it stops) and server reflection, so `grpcurl` and load
    balancers' probes work without the proto file."""
    from grpc_health.v1 import health, health_pb2, health_pb2_grpc
    from grpc_reflection.v1alpha import reflection

    limit = settings.grpc_max_message_mb * 2**20
    server = grpc.aio.server(
        options=[
            ("grpc.max_receive_message_length", limit),
            ("grpc.max_send_message_length", limit),
            ("grpc.so_reuseport", 0),
        ]
    )
    # the process's runtime (banks, uploaded maps, compiled programs), shared by both services
    runtime = runtime if runtime is not None else service_runtime(settings)
    # one count of failed authentications for both services (and the API's, when it is given)
    limiter = auth_limiter if auth_limiter is not None else auth.make_limiter(settings)
    servicer = RolloutServicer(settings, runtime=runtime, auth_limiter=limiter)
    pb_grpc.add_RolloutServiceServicer_to_server(servicer, server)
    # trained policies for robots (Load, then Act), on the same port, auth and limits
    servicer.policy_servicer = PolicyServicer(settings, runtime=runtime, auth_limiter=limiter)
    pb_grpc.add_PolicyServiceServicer_to_server(servicer.policy_servicer, server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        (ROLLOUT_SERVICE, POLICY_SERVICE, health.SERVICE_NAME, reflection.SERVICE_NAME), server
    )
    address = f"{host or settings.host}:{settings.grpc_port if port is None else port}"
    creds = server_credentials(settings)
    bound = (server.add_secure_port(address, creds) if creds is not None
             else server.add_insecure_port(address))  # fmt: skip
    if bound == 0:
        raise OSError(f"cannot bind the gRPC Rollout server to {address} (QUICKNAV_GRPC_PORT)")
    await server.start()
    for name in ("", ROLLOUT_SERVICE, POLICY_SERVICE):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    server.quicknav_health = health_servicer  # stop() marks it NOT_SERVING first
    log.info("gRPC Rollout server on %s (%s)", address, "TLS" if creds else "plaintext")
    return server, bound, servicer


def serve_forever(settings: Settings, host: str | None = None, port: int | None = None) -> None:
    """Run the Rollout server in this thread until interrupted."""

    import quicknav_core.env.batch  # noqa: F401  (import JAX now, not on the first Start)

    async def main():
        server, bound, _ = await start_server(settings, host, port)
        print(f"gRPC Rollout server listening on {host or settings.host}:{bound}", flush=True)
        await server.wait_for_termination()

    asyncio.run(main())


class BackgroundServer:
    """The Rollout server on its own event loop in a daemon thread (for `quicknav serve`, tests)."""

    def __init__(self, settings: Settings, host: str | None = None, port: int | None = None,
                 runtime: Runtime | None = None, auth_limiter: auth.Limiter | None = None):  # fmt: skip
        self.settings = settings
        self.runtime = runtime
        self.auth_limiter = auth_limiter
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.port = 0
        self.servicer: RolloutServicer | None = None
        self._server: grpc.aio.Server | None = None
        self._thread = threading.Thread(
            target=self._main, args=(host, port), name="grpc-rollout", daemon=True
        )

    def _main(self, host, port) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._server, self.port, self.servicer = self._loop.run_until_complete(
                start_server(self.settings, host, port, self.runtime, self.auth_limiter)
            )
        except BaseException as e:  # reported to the starting thread
            self._error = e
            self._ready.set()
            return
        self._ready.set()
        self._loop.run_forever()  # until stop(): the loop must outlive server.stop()

    def start(self, timeout: float = 30.0) -> BackgroundServer:
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError("the gRPC Rollout server did not start")
        if self._error is not None:
            raise self._error
        return self

    def stop(self, grace: float = 1.0) -> None:
        """Stop taking streams, give open ones ``grace`` seconds, then end the thread."""
        if self._server is not None and self._loop.is_running():
            health = getattr(self._server, "quicknav_health", None)
            if health is not None:  # probes see NOT_SERVING while open streams finish
                asyncio.run_coroutine_threadsafe(
                    health.enter_graceful_shutdown(), self._loop
                ).result(5)
            asyncio.run_coroutine_threadsafe(self._server.stop(grace), self._loop).result(grace + 5)
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(grace + 5)
