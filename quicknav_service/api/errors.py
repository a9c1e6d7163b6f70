"""Errors of the HTTP API: the bodies they answer with, their documentation, and the handlers that
map the jobs service's and the store's errors to status codes (the one place that does)."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError, StarletteHTTPException
from fastapi.responses import JSONResponse
from fastapi.routing import compile_path, iter_route_contexts
from pydantic import BaseModel

from quicknav_core.config.resolve import explain_unknown_fields
from quicknav_service.artifacts import ArtifactUnavailable
from quicknav_service.jobs.models import StoreUnavailable
from quicknav_service.jobs.service import BadRequest, Conflict, Invalid, NotFound, ServiceError
from quicknav_service.schemas import MIN_ID_PREFIX, HTTPError, ValidationErrorBody

log = logging.getLogger("quicknav.api")

_WHY = {
    400: "the request cannot be understood (the message says which part)",
    401: "missing or wrong bearer token",
    403: "a cross-site request (an Origin that is not this server), or a browser-session request"
    " that changes a job without the X-QuickNav-Web header",
    404: "no such job (or artifact)",
    409: "the request does not fit the state: an ambiguous id prefix, a job still running, a"
    " reused Idempotency-Key",
    413: "the request body exceeds this server's limit (QUICKNAV_MAX_BODY_BYTES)",
    415: "a POST without a JSON body (Content-Type: application/json) or the X-QuickNav-Web header",
    422: "bad fields: every one of them, each with its location and what is allowed",
    429: "too many failed authentications from this address; retry after Retry-After seconds",
    503: "the job store or the artifact store cannot be reached; retry after Retry-After seconds",
    507: "the job store's disk is full; retry after Retry-After seconds (deleting jobs frees space)",
}
_RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before retrying",
                                "schema": {"type": "integer"}}}  # fmt: skip

# what every route that reads the job store may answer
STORE = (503, 507)
# what every route behind the token may answer
AUTH = (401, 429)
# the routes that take a body and change a job: a body that is not JSON text (bytes that are not
# UTF-8) gets 400, a cross-site request or a browser session without the web header 403, a POST
# that is not JSON 415
CHANGE = (400, 401, 403, 413, 415)


def responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI ``responses`` of the given error status codes, with their body's model."""
    out: dict[int | str, dict[str, Any]] = {}
    for code in sorted(set(codes)):
        doc: dict[str, Any] = {"model": ValidationErrorBody if code == 422 else HTTPError,
                               "description": _WHY[code]}  # fmt: skip
        if code in (429, 503, 507):
            doc["headers"] = _RETRY_AFTER
        out[code] = doc
    return out


def _body_model(request: Request) -> type[BaseModel] | None:
    route = request.scope.get("route")
    field = getattr(route, "body_field", None)
    model = getattr(getattr(field, "field_info", None), "annotation", None)
    return model if isinstance(model, type) and issubclass(model, BaseModel) else None


def _field_errors(request: Request, exc: RequestValidationError) -> list[dict[str, Any]]:
    items = []
    for e in exc.errors():
        loc = list(e["loc"])
        item = {"loc": loc, "msg": e["msg"].removeprefix("Value error, "), "type": e["type"]}
        if loc[:2] == ["path", "job_id"] and e["type"] == "string_too_short":
            item["msg"] = (f"job id prefix {e.get('input')!r} is too short: give at least"
                           f" {MIN_ID_PREFIX} characters of the id (the CLI shows 8)")  # fmt: skip
        items.append(item)
    model = _body_model(request)
    body = [i for i in items if i["loc"][:1] == ["body"]]
    if model is None or not body:
        return items
    # unknown body fields: say what was meant (a typo, or a config field beside the request's own)
    explained = explain_unknown_fields(model, [{**i, "loc": [str(p) for p in i["loc"][1:]]}
                                               for i in body])  # fmt: skip
    explained = iter(explained)
    return [{**next(explained), "loc": i["loc"]} if i["loc"][:1] == ["body"] else i for i in items]


class RouteTable:
    """The methods the app serves at each path, for answers the router does not give whole: a
    405's ``Allow`` (Starlette's router names only the first route that matched the path, so a
    path served by two routes, GET and POST /maps, answered ``Allow: POST``) and the cross-site
    guard's "is there a POST here at all" (else the router's 404 or 405 answers). Built on first
    use, when every router has been included."""

    def __init__(self, app: FastAPI):
        self.app = app
        self._table: list[tuple[Any, int, frozenset[str]]] | None = None

    def methods_at(self, path: str, most_literal: bool = True) -> list[str]:
        """The methods of the routes whose path matches, by default the most literal ones only:
        where ``/jobs/eval`` (POST) and ``/jobs/{job_id}`` (GET, DELETE) both match, the document
        (as OpenAPI reads paths: a literal one before a templated one) says POST. With
        ``most_literal=False`` every matching route's (what the router may dispatch to)."""
        if self._table is None:
            self._table = [(compile_path(r.path_format or r.path)[0], (r.path_format or r.path).count("{"),
                            frozenset(r.methods)) for r in iter_route_contexts(self.app.routes)
                           if r.methods and r.path]  # fmt: skip
        matched = [(params, methods) for regex, params, methods in self._table if regex.match(path)]
        fewest = min((params for params, _ in matched), default=0)
        return sorted({m for params, methods in matched if params == fewest or not most_literal
                       for m in methods})  # fmt: skip


def install(app: FastAPI) -> None:
    """The handlers that turn errors into answers."""

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 405:
            allow = request.app.state.route_table.methods_at(request.url.path)
            return JSONResponse({"detail": f"method {request.method} is not allowed here; allowed:"
                                           f" {', '.join(allow)}"},
                                status_code=405, headers={"Allow": ", ".join(allow)})  # fmt: skip
        return await http_exception_handler(request, exc)

    @app.exception_handler(RequestValidationError)
    async def validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": _field_errors(request, exc)}, status_code=422)

    @app.exception_handler(ServiceError)
    async def refused(request: Request, exc: ServiceError) -> JSONResponse:
        if isinstance(exc, Invalid):
            detail = [{"loc": ["body", *i["loc"]], "msg": i["msg"], "type": i["type"]}
                      for i in exc.items]  # fmt: skip
            return JSONResponse({"detail": detail}, status_code=422)
        status = {BadRequest: 400, NotFound: 404, Conflict: 409}[type(exc)]
        return JSONResponse({"detail": exc.detail}, status_code=status)

    @app.exception_handler(ArtifactUnavailable)
    async def artifacts_unavailable(request: Request, exc: ArtifactUnavailable) -> JSONResponse:
        # the client library's words (they name the store's endpoint) go to the log only
        log.warning("artifact store %s unavailable while %s: %s", exc.store, exc.doing, exc.error)
        return JSONResponse(
            {"detail": f"{exc}; retry in a few seconds"}, status_code=503,
            headers={"Retry-After": "5"},
        )

    @app.exception_handler(StoreUnavailable)
    async def store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
        # 507 when the disk is full (the request may succeed once space is freed: DELETE frees
        # it), 503 when the store cannot be reached; both say when to retry
        return JSONResponse(
            {"detail": f"the job store is unavailable: {exc.reason}; retry in a few seconds"},
            status_code=507 if exc.disk_full else 503,
            headers={"Retry-After": str(exc.retry_after_s)},
        )
