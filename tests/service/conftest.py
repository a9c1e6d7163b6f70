"""A real uvicorn server on a free port in a background thread, and a burst-mode worker."""

from __future__ import annotations

import socket
import threading
import time

import httpx
import pytest
import uvicorn

from service.api.app import create_app
from service.jobs.sqlite_store import SQLiteJobStore
from service.settings import Settings
from service.worker import Worker


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LiveServer:
    def __init__(self, tmp_path, **settings_kw):
        self.settings = Settings(data_dir=tmp_path / "data", embedded_worker=False, lease_s=5.0,
                                 heartbeat_s=0.5, **settings_kw)  # fmt: skip
        self.store = SQLiteJobStore(
            self.settings.data_dir / "jobs.db", max_attempts=self.settings.max_attempts
        )
        self.app = create_app(self.settings, self.store, start_workers=False)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning")
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        deadline = time.time() + 20
        while time.time() < deadline:
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.HTTPError:
                time.sleep(0.05)
        raise RuntimeError("server did not start")

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(10)

    def worker(self, worker_id: str = "test-worker") -> Worker:
        return Worker(self.store, self.settings, worker_id=worker_id)

    def run_worker_in_background(
        self, worker_id: str = "test-worker"
    ) -> tuple[Worker, threading.Thread]:
        w = self.worker(worker_id)

        def loop():
            while not w.shutdown.is_set():
                if not w.run_once():
                    time.sleep(0.05)

        t = threading.Thread(target=loop, daemon=True)
        t.start()
        return w, t


@pytest.fixture
def live(tmp_path):
    with LiveServer(tmp_path) as server:
        yield server
