"""How uvicorn serves the API: a time limit on request headers, which uvicorn lacks.

uvicorn closes idle keep-alive connections (``timeout_keep_alive``) but waits forever for the rest
of a request's headers: a client that opens connections and sends a header a byte at a time holds
them all (slowloris). ``HeaderTimeoutProtocol`` is uvicorn's httptools protocol with a timer armed
when a connection opens and when each request on it begins, disarmed when its headers are
complete; when it fires, the connection is closed.
"""

from __future__ import annotations

import os
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol


class HeaderTimeoutProtocol(HttpToolsProtocol):
    header_timeout_s = 10.0

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_too_slow)

    def _disarm(self) -> None:
        timer = getattr(self, "_header_timer", None)
        if timer is not None:
            timer.cancel()
        self._header_timer = None

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if self.transport is not None and not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def connection_lost(self, exc) -> None:
        self._disarm()
        super().connection_lost(exc)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        if getattr(self, "_header_timer", None) is None:
            self._arm()

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()


class EnvHeaderTimeoutProtocol(HeaderTimeoutProtocol):
    """The same, for API processes uvicorn spawns (its options are pickled, a class made at run
    time is not): the limit comes from QUICKNAV_HEADER_TIMEOUT_S, as the parent's settings did."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.header_timeout_s = float(os.environ.get("QUICKNAV_HEADER_TIMEOUT_S", "10"))


def uvicorn_options(settings, processes: int = 1) -> dict[str, Any]:
    """The uvicorn options every API process runs with (``quicknav serve``, tests' live servers)."""
    if processes > 1:
        os.environ["QUICKNAV_HEADER_TIMEOUT_S"] = str(settings.header_timeout_s)
        protocol = EnvHeaderTimeoutProtocol
    else:
        protocol = type("HeaderTimeoutProtocol", (HeaderTimeoutProtocol,),
                        {"header_timeout_s": settings.header_timeout_s})  # fmt: skip
    # X-Forwarded-For only from the proxies the operator names: uvicorn believes 127.0.0.1 by
    # default, which let one local client pose as any number of addresses
    proxies = [a.strip() for a in (settings.trusted_proxies or "").split(",") if a.strip()]
    forwarded = {"proxy_headers": True, "forwarded_allow_ips": proxies} if proxies else {"proxy_headers": False}
    return {"http": protocol, "timeout_keep_alive": 5, "h11_max_incomplete_event_size": 16 * 1024,
            **forwarded}
