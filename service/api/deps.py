"""The dependencies every route takes: the job store (typed by its protocol), settings, the token."""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Request

from service.jobs.models import AmbiguousId, Job, JobNotFound, JobStore
from service.settings import Settings


async def _store(request: Request) -> JobStore:
    return request.app.state.store


async def _settings(request: Request) -> Settings:
    return request.app.state.settings


StoreDep = Annotated[JobStore, Depends(_store)]
SettingsDep = Annotated[Settings, Depends(_settings)]


# The browser view's session: a cookie holding a digest of the token (not the token itself), set
# by POST /auth/session. Images, GIFs and the event stream are fetched by the browser itself, which
# cannot add an Authorization header to them; a cookie it sends on its own.
SESSION_COOKIE = "quicknav_session"
# A cookie-authenticated request that changes something must carry this header: a page on another
# site cannot set it without a CORS preflight, which this API never grants (SameSite=Strict on the
# cookie is the first line; this is the second).
WEB_HEADER = "X-QuickNav-Web"
SAFE_METHODS = ("GET", "HEAD", "OPTIONS")


def session_digest(token: str) -> str:
    """The session cookie's value for ``token``."""
    return hmac.new(token.encode(), b"quicknav-web-session-v1", hashlib.sha256).hexdigest()


def session_valid(settings: Settings, cookie: str | None) -> bool:
    token = settings.api_token
    return token is not None and cookie is not None and hmac.compare_digest(
        cookie.encode(), session_digest(token).encode()
    )


async def require_token(
    request: Request, settings: SettingsDep, authorization: Annotated[str | None, Header()] = None
) -> None:
    """With QUICKNAV_API_TOKEN set, every job route needs ``Authorization: Bearer <token>`` (or
    the browser view's session cookie)."""
    token = settings.api_token
    if token is None:
        return
    sent = (authorization or "").encode()
    if hmac.compare_digest(sent, f"Bearer {token}".encode()):
        return
    if session_valid(settings, request.cookies.get(SESSION_COOKIE)):
        if request.method not in SAFE_METHODS and request.headers.get(WEB_HEADER) != "1":
            raise HTTPException(403, f"a request from the browser session that changes a job must"
                                     f" send the header {WEB_HEADER}: 1")  # fmt: skip
        return
    raise HTTPException(401, "missing or wrong bearer token (Authorization: Bearer <QUICKNAV_API_TOKEN>)",
                        headers={"WWW-Authenticate": "Bearer"})  # fmt: skip


def get_job(store: JobStore, job_id: str) -> Job:
    """The job, by its id or a unique prefix of it (at least 4 characters, as the CLI shows
    them); 404 naming the id if none, 409 listing them if the prefix is not unique."""
    try:
        return store.get(job_id)
    except JobNotFound:
        pass
    try:
        return store.get(store.resolve_id(job_id))
    except JobNotFound:
        raise HTTPException(404, f"no job {job_id!r}") from None
    except AmbiguousId as e:
        raise HTTPException(
            409, f"job id prefix {job_id!r} matches several jobs ({', '.join(e.matches)}):"
            " give more characters"
        ) from None
