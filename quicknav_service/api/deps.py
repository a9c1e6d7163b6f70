"""The dependencies every route takes: the job store (typed by its protocol), settings, the jobs
service, the token (a bearer security scheme, or the browser view's session cookie), a job id."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from quicknav_service import auth
from quicknav_service.jobs.models import JobStore
from quicknav_service.jobs.service import JobsService
from quicknav_service.schemas import ID_DESCRIPTION, MIN_ID_PREFIX
from quicknav_service.settings import Settings


async def _store(request: Request) -> JobStore:
    return request.app.state.store


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


StoreDep = Annotated[JobStore, Depends(_store)]
SettingsDep = Annotated[Settings, Depends(_settings)]


async def _jobs(request: Request, store: StoreDep, settings: SettingsDep) -> JobsService:
    return JobsService(store, settings, request.app.state.runtime)


JobsDep = Annotated[JobsService, Depends(_jobs)]
JobId = Annotated[str, Path(min_length=MIN_ID_PREFIX, max_length=200, description=ID_DESCRIPTION)]


# The browser view's session: a cookie holding a random session id, kept server-side in the job
# store (``quicknav_service.auth``), set by POST /auth/session. Images, GIFs and the event stream
# are fetched by the browser itself, which cannot add an Authorization header to them; a cookie it
# sends on its own.
SESSION_COOKIE = "quicknav_session"
# A cookie-authenticated request that changes something must carry this header: a page on another
# site cannot set it without a CORS preflight, which this API never grants (SameSite=Strict on the
# cookie and the Origin check of the cross-site guard come first).
WEB_HEADER = "X-QuickNav-Web"
SAFE_METHODS = ("GET", "HEAD", "OPTIONS")


def session_valid(settings: Settings, store: JobStore, cookie: str | None) -> bool:
    """Whether ``cookie`` names an open session opened with the server's current token."""
    token = settings.api_token
    if token is None or not cookie or len(cookie) > 200:
        return False
    proof = store.session_proof(auth.session_key(cookie))
    return proof is not None and hmac.compare_digest(
        proof.encode(), auth.session_proof(cookie, token).encode()
    )


def client_address(request: Request) -> str:
    return request.client.host if request.client else "unknown"


def check_rate(request: Request) -> None:
    """429 (with Retry-After) for a client address that failed to authenticate too often."""
    wait = request.app.state.auth_limiter.retry_after(client_address(request))
    if wait is not None:
        raise HTTPException(429, f"too many failed authentications from this address: retry in"
                                 f" {wait} s (QUICKNAV_AUTH_FAILURES_MAX per"
                                 " QUICKNAV_AUTH_FAILURE_WINDOW_S)",
                            headers={"Retry-After": str(wait)})  # fmt: skip


def auth_failed(request: Request, message: str) -> HTTPException:
    request.app.state.auth_limiter.failed(client_address(request))
    return HTTPException(401, message, headers={"WWW-Authenticate": "Bearer"})


# auto_error=False: a missing token is not an error here when the browser's cookie stands in for
# it (and with no QUICKNAV_API_TOKEN nothing is needed); the scheme puts "Authorize" in /docs
bearer = HTTPBearer(auto_error=False, description="QUICKNAV_API_TOKEN, when the server sets one")


def require_token(
    request: Request,
    settings: SettingsDep,
    store: StoreDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> None:
    """With QUICKNAV_API_TOKEN set, every job route needs ``Authorization: Bearer <token>`` (or
    the browser view's session cookie); failed attempts are limited per client address."""
    token = settings.api_token
    if token is None:
        return
    check_rate(request)
    if credentials is not None:
        if auth.token_matches(f"Bearer {credentials.credentials}", token):
            return
        raise auth_failed(request, "wrong bearer token (Authorization: Bearer <QUICKNAV_API_TOKEN>)")
    if session_valid(settings, store, request.cookies.get(SESSION_COOKIE)):
        if request.method not in SAFE_METHODS and request.headers.get(WEB_HEADER) != "1":
            raise HTTPException(403, f"a request from the browser session that changes a job must"
                                     f" send the header {WEB_HEADER}: 1")  # fmt: skip
        return
    raise HTTPException(401, "missing bearer token (Authorization: Bearer <QUICKNAV_API_TOKEN>) or"
                             " browser session", headers={"WWW-Authenticate": "Bearer"})  # fmt: skip


def require_metrics_token(
    request: Request,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> None:
    """/metrics: the metrics token or the API token as a bearer token, when either is set."""
    tokens = [t for t in (settings.metrics_token, settings.api_token) if t]
    if not tokens:
        return
    check_rate(request)
    sent = f"Bearer {credentials.credentials}" if credentials is not None else None
    if any(auth.token_matches(sent, t) for t in tokens):
        return
    if credentials is None:
        raise HTTPException(401, "/metrics needs Authorization: Bearer <QUICKNAV_METRICS_TOKEN or"
                                 " QUICKNAV_API_TOKEN>", headers={"WWW-Authenticate": "Bearer"})  # fmt: skip
    raise auth_failed(request, "wrong bearer token for /metrics")
