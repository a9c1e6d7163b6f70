"""Secrets never reach logs, errors or answers: URLs are printed without their passwords, and
every service process writes its output through a filter that blanks the secrets it knows.

``redact_url`` is for code that prints a URL on purpose (``quicknav serve`` names its store).
``install(settings)`` wraps the process's stdout and stderr so that whatever reaches them (a log
line, a library's traceback, a print) has every known secret replaced by ``***``: the API token,
the metrics token, passwords and keys in the store's and the artifact store's URLs.
"""

from __future__ import annotations

import io
import sys
from urllib.parse import parse_qsl, urlsplit, urlunsplit

MASK = "***"
# query parameters that carry credentials in connection URLs
SECRET_PARAMS = ("password", "passwd", "secret", "token", "access_key", "secret_key", "key")


def redact_url(url: str | None) -> str | None:
    """``url`` with the password of its user info and credential parameters replaced by ***."""
    if not url:
        return url
    try:
        parts = urlsplit(url)
    except ValueError:
        return MASK
    netloc = parts.netloc
    if "@" in netloc:
        userinfo, host = netloc.rsplit("@", 1)
        user, sep, password = userinfo.partition(":")
        netloc = f"{user}:{MASK}@{host}" if sep or password else f"{MASK}@{host}"
    query = parts.query
    if query:
        query = "&".join(
            f"{k}={MASK}" if k.lower() in SECRET_PARAMS else f"{k}={v}"
            for k, v in parse_qsl(query, keep_blank_values=True)
        )
    return urlunsplit((parts.scheme, netloc, parts.path, query, parts.fragment))


def url_secrets(url: str | None) -> list[str]:
    """The secret parts of a URL: its password (or bare user token) and credential parameters."""
    if not url:
        return []
    try:
        parts = urlsplit(url)
    except ValueError:
        return [url]
    out = []
    if "@" in parts.netloc:
        userinfo = parts.netloc.rsplit("@", 1)[0]
        user, sep, password = userinfo.partition(":")
        out.append(password if sep else user)
    out += [v for k, v in parse_qsl(parts.query) if k.lower() in SECRET_PARAMS]
    return [s for s in out if s]


def settings_secrets(settings) -> list[str]:
    """Every secret a Settings object holds, longest first (so no secret is half-replaced)."""
    found = [getattr(settings, "api_token", None), getattr(settings, "metrics_token", None)]
    for name in ("redis_url", "artifacts_url"):
        found += url_secrets(getattr(settings, name, None))
    return sorted({s for s in found if s and len(s) >= 4}, key=len, reverse=True)


def redact(text: str, secrets: list[str]) -> str:
    for secret in secrets:
        if secret in text:
            text = text.replace(secret, MASK)
    return text


class RedactingStream(io.TextIOBase):
    """A text stream that blanks ``secrets`` in everything written through it."""

    def __init__(self, stream, secrets: list[str]):
        self.stream = stream
        self.secrets = secrets

    def write(self, text: str) -> int:
        self.stream.write(redact(text, self.secrets))
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def isatty(self) -> bool:
        return self.stream.isatty()

    def fileno(self) -> int:
        return self.stream.fileno()

    @property
    def encoding(self):
        return getattr(self.stream, "encoding", "utf-8")


def install(settings) -> None:
    """Blank this process's known secrets in everything it writes to stdout and stderr."""
    secrets = settings_secrets(settings)
    if not secrets:
        return
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if isinstance(stream, RedactingStream):
            stream.secrets = sorted(set(stream.secrets) | set(secrets), key=len, reverse=True)
        else:
            setattr(sys, name, RedactingStream(stream, secrets))
