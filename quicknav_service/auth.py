"""Authentication pieces shared by the HTTP API and the gRPC server: the token check, a limit on
failed attempts per client address, and the browser view's server-side sessions.

Sessions: the cookie holds a random id (256 bits) and nothing else. The store keeps, under a
digest of that id, a proof that ties the session to the token it was opened with: an HMAC of the
token keyed by the id. Neither the cookie nor the store tells anything about the token without
the other, a token change ends every session (the proofs no longer match), and signing out
deletes the session.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
import threading
import time
from collections import OrderedDict, deque

BEARER = "Bearer "


def token_matches(sent: str | None, token: str) -> bool:
    """Whether an Authorization value is ``Bearer <token>`` (the same format for REST and gRPC)."""
    if not sent or not sent.startswith(BEARER):
        return False
    return hmac.compare_digest(sent[len(BEARER):].strip().encode(), token.encode())


def new_session_id() -> str:
    return secrets.token_urlsafe(32)


def session_key(session_id: str) -> str:
    """What the store files a session under (a leaked store hands out no cookie)."""
    return hashlib.sha256(session_id.encode()).hexdigest()


def session_proof(session_id: str, token: str) -> str:
    return hmac.new(session_id.encode(), token.encode(), hashlib.sha256).hexdigest()


class FailureLimiter:
    """After ``limit`` failed attempts from one client address within ``window_s`` seconds, every
    further attempt from it is refused until the oldest of them leaves the window. Per process;
    at most ``max_clients`` addresses are remembered (the least recently seen are forgotten)."""

    def __init__(self, limit: int, window_s: float, max_clients: int = 100_000):
        self.limit = limit
        self.window_s = window_s
        self.max_clients = max_clients
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> deque[float]:
        seen = self._failures.get(client)
        if seen is None:
            return deque()
        while seen and now - seen[0] >= self.window_s:
            seen.popleft()
        if not seen:
            del self._failures[client]
        return seen

    def retry_after(self, client: str) -> int | None:
        """Seconds until ``client`` may try again, or None if it may now."""
        now = time.monotonic()
        with self._lock:
            seen = self._recent(client, now)
            if len(seen) < self.limit:
                return None
            return max(1, math.ceil(self.window_s - (now - seen[0])))

    def failed(self, client: str) -> None:
        now = time.monotonic()
        with self._lock:
            seen = self._recent(client, now)
            seen.append(now)
            self._failures[client] = seen
            self._failures.move_to_end(client)
            while len(self._failures) > self.max_clients:
                self._failures.popitem(last=False)
