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
import logging
import math
import secrets
import threading
import time
from collections import OrderedDict, deque
from typing import Protocol

log = logging.getLogger("quicknav.auth")

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


class Limiter(Protocol):
    """Failed authentications per client address, for every door of the service (REST, the gRPC
    Rollout and Policy streams): one count, so the doors together allow ``limit``, not each."""

    def retry_after(self, client: str) -> int | None: ...

    def failed(self, client: str) -> None: ...


class FailureLimiter:
    """After ``limit`` failed attempts from one client address within ``window_s`` seconds, every
    further attempt from it is refused until the oldest of them leaves the window. In this process
    (every door of it shares one); at most ``max_clients`` addresses are remembered (the least
    recently seen are forgotten)."""

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


class RedisFailureLimiter:
    """``FailureLimiter``'s rule counted in Redis, so that every API process and gRPC server of a
    fleet shares one count per client address: a sorted set of failure times per address (Redis's
    clock, so machines agree), trimmed to the window, expiring with it. While Redis cannot be
    reached, this process's own count stands in (attempts stay limited, per process)."""

    def __init__(self, url: str, limit: int, window_s: float, prefix: str = "quicknav"):
        import redis

        self.limit = limit
        self.window_s = window_s
        self.prefix = prefix
        self._redis = redis.Redis.from_url(url, socket_timeout=2.0, socket_connect_timeout=2.0)
        self._errors = (redis.RedisError, OSError)
        self.fallback = FailureLimiter(limit, window_s)
        self._down = False  # said once per outage: a flood of guesses must not flood the log

    def _key(self, client: str) -> str:
        return f"{self.prefix}:auth-failures:{client}"

    def _now(self) -> float:
        seconds, micros = self._redis.time()
        return seconds + micros / 1e6

    def _unreachable(self, e: Exception) -> None:
        if not self._down:
            log.warning("auth limiter: Redis unreachable (%s); counting in this process meanwhile",
                        type(e).__name__)  # fmt: skip
        self._down = True

    def retry_after(self, client: str) -> int | None:
        key = self._key(client)
        try:
            now = self._now()
            pipe = self._redis.pipeline()
            pipe.zremrangebyscore(key, "-inf", now - self.window_s)
            pipe.zcard(key)
            pipe.zrange(key, 0, 0, withscores=True)
            _, count, oldest = pipe.execute()
        except self._errors as e:
            self._unreachable(e)
            return self.fallback.retry_after(client)
        if self._down:
            log.info("auth limiter: Redis reachable again")
            self._down = False
        local = self.fallback.retry_after(client)  # failures counted here while Redis was away
        if count < self.limit or not oldest:
            return local
        shared = max(1, math.ceil(self.window_s - (now - oldest[0][1])))
        return max(shared, local or 0)

    def failed(self, client: str) -> None:
        key = self._key(client)
        try:
            now = self._now()
            pipe = self._redis.pipeline()
            pipe.zadd(key, {f"{now:.6f}-{secrets.token_hex(4)}": now})
            pipe.zremrangebyscore(key, "-inf", now - self.window_s)
            pipe.pexpire(key, int(self.window_s * 1000) + 1000)
            pipe.execute()
        except self._errors as e:
            self._unreachable(e)
            self.fallback.failed(client)


def make_limiter(settings) -> Limiter:
    """The failure limiter a service process gives all its doors: counted in Redis when the
    service runs on Redis (QUICKNAV_REDIS_URL: shared by the fleet), else in this process."""
    if settings.redis_url:
        return RedisFailureLimiter(settings.redis_url, settings.auth_failures_max,
                                   settings.auth_failure_window_s)  # fmt: skip
    return FailureLimiter(settings.auth_failures_max, settings.auth_failure_window_s)
