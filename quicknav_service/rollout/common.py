"""What the Rollout and Policy servicers share: refusals with exact status codes, the token check,
the lookup of a trained job's run folder, and admission problems turned into a status."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import grpc
from google.protobuf.message import DecodeError

from quicknav_core.runtime import Runtime
from quicknav_service import auth
from quicknav_service.settings import Settings

# A status message travels in HTTP/2 trailers (metadata): past a few kB it breaks the call.
MAX_MESSAGE_CHARS = 2000


def bounded(message: str) -> str:
    """A status message cut to MAX_MESSAGE_CHARS (bad input is never echoed at length)."""
    if len(message) <= MAX_MESSAGE_CHARS:
        return message
    return message[: MAX_MESSAGE_CHARS - 40] + f"... ({len(message):,} characters in all)"


class Refused(Exception):
    """A request the server refuses: ends the stream with ``code`` and ``message``."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


class StreamMemory:
    """The memory a server's open Rollout streams hold together, by their admission estimates
    (``quicknav_core.admission.stream_estimate``), added up by ``train.memory.together``: the
    process's runtime once, each stream's room banks and resident envs (or episodes in policy
    mode), and the largest stream's step transients once. A stream that would take the sum past
    ``budget_mb`` is refused RESOURCE_EXHAUSTED; its parts are given back when it ends. Streams on
    the same rooms share their banks in the runtime's cache, so the banks' sum is an upper bound."""

    def __init__(self, budget_mb: int, setting: str):
        self.budget_mb = budget_mb
        self.setting = setting  # the environment variable that sets the budget, for the message
        self._held: dict[str, object] = {}  # stream -> its Estimate
        self._lock = threading.Lock()

    def _total(self, extra=()) -> int:
        from quicknav_core.train.memory import together

        return together([*self._held.values(), *extra]).total

    @property
    def held_mb(self) -> int:
        from quicknav_core.train.memory import megabytes

        with self._lock:
            return megabytes(self._total())

    @property
    def streams(self) -> int:
        with self._lock:
            return len(self._held)

    def take(self, key: str, estimate, where: str) -> None:
        """Hold ``estimate``'s parts for the stream ``key``, or raise Refused naming ``where`` (the
        request field its largest part follows), what the open streams hold and the budget."""
        from quicknav_core.train.memory import megabytes

        with self._lock:
            before, after = self._total(), self._total([estimate])
            if megabytes(after) > self.budget_mb:
                raise Refused(grpc.StatusCode.RESOURCE_EXHAUSTED, (
                    f"{where}: this stream adds about {megabytes(after - before):,} MB (alone it"
                    f" would peak at {megabytes(estimate.total):,} MB: {estimate.describe()}; the"
                    " runtime and one step's transients are counted once) while the"
                    f" {len(self._held)} open stream(s) hold"
                    f" about {megabytes(before):,} MB; together {megabytes(after):,} MB, above the"
                    f" {self.budget_mb:,} MB this server gives its streams ({self.setting}): close a"
                    " stream, ask for fewer envs, or retry later"))  # fmt: skip
            self._held[key] = estimate

    def give_back(self, key: str) -> None:
        with self._lock:
            self._held.pop(key, None)


async def read_next(context: grpc.aio.ServicerContext, idle_s: float, message: str, closed: str):
    """The stream's next message (or ``grpc.aio.EOF``). Bytes that are not a ``message`` in
    protobuf's wire format are the client's mistake (INVALID_ARGUMENT, not INTERNAL); no message for
    ``idle_s`` ends the stream with DEADLINE_EXCEEDED and ``closed`` (what the client does next)."""
    try:
        return await asyncio.wait_for(context.read(), timeout=idle_s)
    except TimeoutError:
        raise Refused(grpc.StatusCode.DEADLINE_EXCEEDED,
                      f"no message for {idle_s:g} s (QUICKNAV_ROLLOUT_IDLE_S): {closed}") from None  # fmt: skip
    except DecodeError:
        raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                      f"the message is not a {message} in protobuf's wire format (corrupt or"
                      " truncated bytes, or another message type): send what the proto"
                      " quicknav/v1/rollout.proto defines") from None  # fmt: skip


def authorization(context: grpc.aio.ServicerContext) -> str | None:
    """The call's ``authorization`` metadata as sent (``Bearer <token>``, as REST takes it)."""
    for key, value in context.invocation_metadata() or ():
        if key.lower() == "authorization" and isinstance(value, str):
            return value
    return None


def peer_host(context) -> str:
    """The client's address without its port (``ipv4:127.0.0.1:5000`` -> ``127.0.0.1``)."""
    peer = context.peer() or "unknown"
    kind, _, rest = peer.partition(":")
    if kind == "ipv6":
        return rest.rsplit(":", 1)[0].strip("[]")
    return rest.rsplit(":", 1)[0] if kind == "ipv4" else peer


async def authenticate(settings: Settings, limiter: auth.Limiter, context) -> None:
    """Abort the call unless it carries ``authorization: Bearer <token>`` (when the server has a
    token); failures count per client address in the limiter REST uses too (off the event loop:
    it may ask Redis)."""
    token = settings.api_token
    if not token:
        return
    client = peer_host(context)
    wait = await asyncio.to_thread(limiter.retry_after, client)
    if wait is not None:
        await context.abort(
            grpc.StatusCode.RESOURCE_EXHAUSTED,
            f"too many failed authentications from this address: retry in {wait} s"
            " (QUICKNAV_AUTH_FAILURES_MAX per QUICKNAV_AUTH_FAILURE_WINDOW_S)",
        )
    if not auth.token_matches(authorization(context), token):
        await asyncio.to_thread(limiter.failed, client)
        await context.abort(
            grpc.StatusCode.UNAUTHENTICATED,
            "this server requires the API token: send call metadata"
            " 'authorization: Bearer <token>' (the QUICKNAV_API_TOKEN of the service)",
        )


def is_plain_id(job_id: str) -> bool:
    return bool(job_id) and all(c.isalnum() or c in "-_" for c in job_id) and len(job_id) <= 64


def run_copy(runtime: Runtime, job_id: str, field: str) -> Path | None:
    """A train job's run folder from the artifact store (a local copy of an object store's);
    UNAVAILABLE naming the store when it cannot be reached."""
    from quicknav_service.artifacts import ArtifactUnavailable

    try:
        return runtime.artifacts.run_copy(job_id)
    except ArtifactUnavailable as e:
        raise Refused(grpc.StatusCode.UNAVAILABLE, f"{field}={job_id!r}: {e}") from None
