"""The browser view: one page (``/`` and ``/ui/...``) that reads the REST API from the browser, its
static files, and the session that lets a browser carry the API token."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from quicknav_service import auth as tokens
from quicknav_service.api.deps import (
    SESSION_COOKIE,
    SettingsDep,
    StoreDep,
    auth_failed,
    check_rate,
    session_valid,
)

STATIC_DIR = Path(__file__).resolve().parent / "static"
SESSION_MAX_AGE_S = 7 * 24 * 3600

router = APIRouter(include_in_schema=False)
auth = APIRouter(prefix="/auth", tags=["auth"])


def _page() -> FileResponse:
    # the shell holds no data (every number on it comes from the token-checked API), so it is
    # served to anyone; no-cache so an upgraded server's page is picked up on reload
    return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})


@router.get("/")
async def index() -> FileResponse:
    return _page()


@router.get("/ui/{path:path}")
async def ui(path: str) -> FileResponse:
    return _page()


class SessionCreate(BaseModel):
    token: str = Field(min_length=1, max_length=4096, description="the server's QUICKNAV_API_TOKEN")


class SessionPublic(BaseModel):
    token_required: bool = Field(description="whether the server has QUICKNAV_API_TOKEN set")
    authenticated: bool = Field(description="whether this request may read jobs")


@auth.get("/session", response_model=SessionPublic)
def read_session(request: Request, settings: SettingsDep, store: StoreDep) -> SessionPublic:
    """Whether a token is needed and whether this browser's session cookie carries it."""
    required = settings.api_token is not None
    ok = not required or session_valid(settings, store, request.cookies.get(SESSION_COOKIE))
    return SessionPublic(token_required=required, authenticated=ok)


@auth.post("/session", response_model=SessionPublic)
def create_session(body: SessionCreate, request: Request, response: Response,
                         settings: SettingsDep, store: StoreDep) -> SessionPublic:  # fmt: skip
    """Check the token and open a session: a random id in the browser's cookie (HttpOnly,
    SameSite=Strict), kept server-side until it expires, the browser signs out or the token
    changes. Failed attempts count towards the same per-address limit as bearer tokens."""
    token = settings.api_token
    if token is None:
        return SessionPublic(token_required=False, authenticated=True)
    check_rate(request)
    if not tokens.token_matches(f"Bearer {body.token}", token):
        raise auth_failed(request, "wrong token: give the server's QUICKNAV_API_TOKEN")
    session = tokens.new_session_id()
    store.create_session(tokens.session_key(session), tokens.session_proof(session, token),
                         SESSION_MAX_AGE_S)  # fmt: skip
    response.set_cookie(SESSION_COOKIE, session, max_age=SESSION_MAX_AGE_S, httponly=True,
                        samesite="strict", path="/", secure=request.url.scheme == "https")  # fmt: skip
    return SessionPublic(token_required=True, authenticated=True)


@auth.delete("/session", status_code=204)
def delete_session(request: Request, store: StoreDep) -> Response:
    """Sign out: the session ends on the server too (its cookie no longer opens anything)."""
    cookie = request.cookies.get(SESSION_COOKIE)
    if cookie and len(cookie) <= 200:
        store.delete_session(tokens.session_key(cookie))
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response
