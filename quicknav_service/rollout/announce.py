"""Announce a gRPC Rollout endpoint in the job store, so the API can list where remote agents
connect (`GET /rollout/endpoints`): the GPU workers that serve Rollout beside their jobs, or the
all-in-one `quicknav serve`. An endpoint that stops renewing disappears after its TTL."""

from __future__ import annotations

import logging
import os
import socket
import threading
from typing import Any

from quicknav_service.jobs.models import StoreUnavailable

log = logging.getLogger("quicknav.rollout")


def device_summary() -> dict[str, Any]:
    """The JAX backend and device model this process steps environments on."""
    import jax

    devices = jax.local_devices()
    return {"backend": jax.default_backend(), "device": getattr(devices[0], "device_kind", "?"),
            "devices": len(devices)}  # fmt: skip


def advertised_address(configured: str | None, port: int, bound_host: str = "0.0.0.0") -> str:
    """host:port that others use to reach this server: QUICKNAV_ROLLOUT_ADVERTISE; else the bound
    address if it is a specific one (127.0.0.1 for a local server); else, bound to every
    interface, this machine's host name (a container's name on a compose network)."""
    if configured:
        return configured if ":" in configured else f"{configured}:{port}"
    if bound_host not in ("0.0.0.0", "::", ""):
        return f"{bound_host}:{port}"
    return f"{socket.gethostname()}:{port}"


class EndpointAnnouncer:
    """Renews ``{worker, address, device, sessions, max_sessions, memory_held_mb, ...}`` every ``interval_s`` (TTL
    three intervals) until ``stop()``, which withdraws it. Store outages are waited out.

    With ``probe_device`` (a worker, which uses its device anyway) the device is read at once;
    otherwise (the API process of `quicknav serve`) only once a stream has used it, so announcing
    never starts JAX, or takes GPU memory, in a process that may never step an env: until then
    ``backend`` and ``device`` are None."""

    def __init__(self, store, name: str, address: str, servicer, interval_s: float,
                 max_sessions: int, probe_device: bool = True):  # fmt: skip
        self.probe_device = probe_device
        self.store = store
        self.name = name
        self.address = address
        self.servicer = servicer
        self.interval_s = interval_s
        self.max_sessions = max_sessions
        self._stop = threading.Event()
        self._device: dict[str, Any] | None = None
        self._thread = threading.Thread(target=self._run, name="rollout-announce", daemon=True)

    def endpoint(self) -> dict[str, Any]:
        used = (getattr(self.servicer, "active_sessions", 0) > 0
                or getattr(self.servicer, "env_steps_served", 0) > 0)  # fmt: skip
        if self._device is None and (self.probe_device or used):
            self._device = device_summary()
        return {"worker": self.name, "address": self.address, "pid": os.getpid(),
                **(self._device or {"backend": None, "device": None, "devices": 0}),
                "sessions": getattr(self.servicer, "active_sessions", 0),
                "env_steps_served": getattr(self.servicer, "env_steps_served", 0),
                "max_sessions": self.max_sessions, **self._memory()}  # fmt: skip

    def _memory(self) -> dict[str, int]:
        """What the open streams hold by their estimates, and the budget (QUICKNAV_ROLLOUT_MEMORY_MB)."""
        memory = getattr(self.servicer, "memory", None)
        if memory is None:
            return {}
        return {"memory_held_mb": memory.held_mb, "memory_budget_mb": memory.budget_mb}

    def announce_once(self) -> bool:
        try:
            self.store.register_endpoint(self.endpoint(), ttl_s=3 * self.interval_s)
            return True
        except StoreUnavailable as e:
            log.warning("cannot announce the Rollout endpoint (%s): retrying", e.reason)
            return False

    def _run(self) -> None:
        while not self._stop.is_set():
            self.announce_once()
            self._stop.wait(self.interval_s)

    def start(self) -> EndpointAnnouncer:
        self.announce_once()  # listed before start() returns, when the store answers
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)
        try:
            self.store.unregister_endpoint(self.name)
        except StoreUnavailable:
            pass  # it expires on its own
