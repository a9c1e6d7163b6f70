"""The dependencies every route takes: the job store (typed by its protocol), settings, the token."""

from __future__ import annotations

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


async def require_token(
    settings: SettingsDep, authorization: Annotated[str | None, Header()] = None
) -> None:
    """With QUICKNAV_API_TOKEN set, every job route needs ``Authorization: Bearer <token>``."""
    token = settings.api_token
    if token is None:
        return
    sent = (authorization or "").encode()
    if not hmac.compare_digest(sent, f"Bearer {token}".encode()):
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
