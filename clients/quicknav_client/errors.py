"""Typed errors of the REST client; each carries the server's own message."""

from __future__ import annotations

from typing import Any


class QuickNavError(Exception):
    """A request to the QuickNav service failed; ``message`` is the server's text."""

    def __init__(
        self,
        message: str,
        status_code: int | None = None,
        body: Any = None,
        method: str | None = None,
        url: str | None = None,
    ):
        self.message = message
        self.status_code = status_code
        self.body = body
        self.method = method
        self.url = url
        super().__init__(message)

    @property
    def detail(self) -> Any:
        """The ``detail`` of the server's JSON error body (a string, or a list of field errors)."""
        return self.body.get("detail") if isinstance(self.body, dict) else self.body

    def __str__(self) -> str:
        if self.status_code is None:
            return self.message
        where = f" from {self.method} {self.url}" if self.method and self.url else ""
        return f"HTTP {self.status_code}{where}: {self.message}"


class BadRequest(QuickNavError):
    """400 or 422: the request was refused; the message names the bad field and why."""


class Unauthorized(QuickNavError):
    """401 or 403: missing or wrong ``Authorization: Bearer <token>``."""


class NotFound(QuickNavError):
    """404: no such job or artifact."""


class Conflict(QuickNavError):
    """409: an Idempotency-Key reused with another body, or an operation the job's state forbids."""


class PayloadTooLarge(QuickNavError):
    """413: the request body exceeds the server's limit."""


class ServerError(QuickNavError):
    """5xx: the service failed (after retries where the status is transient)."""


class ConnectionFailed(QuickNavError):
    """The service could not be reached (connection refused, timeouts) after all retries."""


class WaitTimeout(QuickNavError, TimeoutError):
    """``Job.wait(timeout=...)`` ran out before the job finished."""


_BY_STATUS: dict[int, type[QuickNavError]] = {
    400: BadRequest,
    422: BadRequest,
    401: Unauthorized,
    403: Unauthorized,
    404: NotFound,
    409: Conflict,
    413: PayloadTooLarge,
}


def error_class(status_code: int) -> type[QuickNavError]:
    """The error type for an HTTP status (the base class for statuses without their own)."""
    if status_code >= 500:
        return ServerError
    return _BY_STATUS.get(status_code, QuickNavError)


def format_detail(detail: Any) -> str:
    """The server's ``detail`` as one line: a string as is, field errors as ``path: msg; ...``."""
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list):
        parts = []
        for item in detail:
            if isinstance(item, dict) and "msg" in item:
                loc = [str(p) for p in item.get("loc", [])]
                if loc and loc[0] == "body":  # every body error starts with it: noise to a reader
                    loc = loc[1:]
                parts.append(f"{'.'.join(loc)}: {item['msg']}" if loc else str(item["msg"]))
            else:
                parts.append(str(item))
        return "; ".join(parts)
    return str(detail)
