"""ASGI middleware of the API: body size, trusted hosts, cross-site requests. Pure ASGI (a
BaseHTTPMiddleware costs a task per request)."""

from __future__ import annotations

from urllib.parse import urlsplit

from fastapi import HTTPException
from fastapi.responses import JSONResponse

# what a page of another site can send without a CORS preflight (which this API never grants)
SIMPLE_METHODS = ("GET", "HEAD", "POST")
SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
WEB_HEADER = b"x-quicknav-web"


def _header(scope, name: bytes) -> bytes | None:
    for key, value in scope["headers"]:
        if key == name:
            return value
    return None


def host_name(host: str) -> str:
    """The name part of a Host header or netloc: no port, IPv6 brackets removed, lower case."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:].split("]", 1)[0]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


class TrustedHosts:
    """Answer only requests whose Host header names this server (DNS rebinding: a page on
    another site that resolves its own name to 127.0.0.1 reaches the API under that name)."""

    def __init__(self, app, hosts: list[str]):
        self.app = app
        self.hosts = set(hosts)
        self.any = "*" in self.hosts

    def allowed(self, host: str) -> bool:
        name = host_name(host)
        return self.any or name in self.hosts or any(
            h.startswith("*.") and name.endswith(h[1:]) for h in self.hosts)  # fmt: skip

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        host = (_header(scope, b"host") or b"").decode("latin-1")
        if not self.allowed(host):
            # the names it answers to are the operator's to know, not a stranger's
            name = host_name(host)
            shown = name if len(name) <= 80 else name[:77] + "..."
            response = JSONResponse({"detail": (
                f"Host {shown!r} is not a name this server answers to (the operator lists them in"
                " QUICKNAV_ALLOWED_HOSTS)")}, status_code=400)  # fmt: skip
            return await response(scope, receive, send)
        return await self.app(scope, receive, send)


# every answer: no other site may frame the pages (clickjacking), no content-type sniffing
SECURITY_HEADERS = (
    (b"x-frame-options", b"DENY"),
    (b"content-security-policy", b"frame-ancestors 'none'"),
    (b"x-content-type-options", b"nosniff"),
)


class SecurityHeaders:
    """Adds SECURITY_HEADERS to every HTTP answer (refusals included) that does not set them."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def sending(message):
            if message["type"] == "http.response.start":
                have = {k.lower() for k, _ in message.get("headers", [])}
                extra = [(k, v) for k, v in SECURITY_HEADERS if k not in have]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        return await self.app(scope, receive, sending)


UPLOAD_PATHS = ("/maps",)  # POST routes that take multipart/form-data


class CrossSiteGuard:
    """Requests that change state must come from this server's own pages or a client that is not
    a browser: where a browser says where a request comes from (``Origin``), it must be this
    server (or QUICKNAV_ALLOWED_ORIGINS), and a POST must carry a JSON body or the web view's
    header, which a form on another site cannot send without a preflight this API never grants
    (methods other than GET, HEAD and POST always need one). A POST to a path with no POST
    route passes on to the router's 404 or 405 (with ``Allow``): nothing runs there."""

    def __init__(self, app, origins: list[str], routes=None):
        self.app = app
        self.origins = set(origins)
        self.routes = routes  # the app's RouteTable (api.errors)

    def _posted_to_a_route(self, scope) -> bool:
        # any route the router could dispatch this POST to, templated ones included
        return self.routes is None or "POST" in self.routes.methods_at(scope["path"], most_literal=False)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in SAFE_METHODS:
            return await self.app(scope, receive, send)
        origin = _header(scope, b"origin")
        if origin is not None:
            value = origin.decode("latin-1").strip().rstrip("/").lower()
            own = (_header(scope, b"host") or b"").decode("latin-1").strip().lower()
            if value not in self.origins and (value == "null" or urlsplit(value).netloc != own):
                response = JSONResponse({"detail": (
                    f"cross-site request refused: Origin {value} is not this server ({own});"
                    " allowed: the server's own pages and QUICKNAV_ALLOWED_ORIGINS")},
                    status_code=403)  # fmt: skip
                return await response(scope, receive, send)
        if scope["method"] == "POST" and self._posted_to_a_route(scope):
            kind = (_header(scope, b"content-type") or b"").split(b";")[0].strip().lower()
            # a map upload is a file form: safe as any POST here, because a browser session
            # needs the web header anyway (require_token) and a token never rides cross-site
            upload = kind == b"multipart/form-data" and scope["path"] in UPLOAD_PATHS
            if kind != b"application/json" and not upload and _header(scope, WEB_HEADER) is None:
                response = JSONResponse({"detail": (
                    "a POST must send a JSON body (Content-Type: application/json; '{}' where"
                    " the route takes no fields) or the header X-QuickNav-Web: 1; got"
                    f" Content-Type {kind.decode('latin-1') or 'none'}")}, status_code=415)  # fmt: skip
                return await response(scope, receive, send)
        return await self.app(scope, receive, send)


class BodyLimit:
    """Refuse request bodies over ``max_bytes`` with 413: by Content-Length up front, and by
    counting for chunked bodies. Pure ASGI (a BaseHTTPMiddleware costs a task per request)."""

    def __init__(self, app, max_bytes: int, uploads: dict[str, int] | None = None):
        self.app = app
        self.max_bytes = max_bytes
        self.uploads = uploads or {}  # POST path -> its own limit (file uploads)

    @staticmethod
    def _too_large(size: int | str, limit: int, setting: str) -> str:
        return f"request body of {size} bytes exceeds the limit of {limit} bytes ({setting})"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        limit, setting = self.max_bytes, "QUICKNAV_MAX_BODY_BYTES"
        if scope["method"] == "POST" and scope["path"] in self.uploads:
            limit, setting = self.uploads[scope["path"]], "QUICKNAV_MAX_MAP_UPLOAD_BYTES"
        for name, value in scope["headers"]:
            if name == b"content-length" and value.isdigit() and int(value) > limit:
                response = JSONResponse(
                    {"detail": self._too_large(value.decode(), limit, setting)}, status_code=413
                )
                return await response(scope, receive, send)
        received = 0

        async def counted():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise HTTPException(413, self._too_large(f"more than {received}", limit, setting))
            return message

        return await self.app(scope, counted, send)
