"""A real uvicorn server on a free port in a background thread, and a burst-mode worker."""

from __future__ import annotations

import os
import socket
import sys
import threading
import time

import httpx
import pytest
import uvicorn

from quicknav_service.api.app import create_app
from quicknav_service.api.http import uvicorn_options
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings
from quicknav_service.worker import Worker
from tests.compile_settings import as_a_user_runs
from tests.processes import LoggedProcess


def quicknav_process(args: list[str], as_a_user: bool = False, **env: str) -> LoggedProcess:
    """`quicknav ARGS` in a child process with QUICKNAV_* ``env`` (and no Redis from outside);
    ``as_a_user``: compiled as a user's machine compiles (``tests/compile_settings.py``), for a
    process that trains more than it compiles."""
    full = {**(as_a_user_runs() if as_a_user else os.environ), **env}
    full.pop("QUICKNAV_REDIS_URL", None)
    return LoggedProcess([sys.executable, "-m", "quicknav_cli", *args], env=full)


def wait_until_up(url: str, proc: LoggedProcess, verify=True, timeout: float = 60.0) -> None:
    """Until ``url``/healthz answers 200; fails with the process's output if it exits first."""
    deadline = time.time() + timeout
    while True:
        try:
            if httpx.get(f"{url}/healthz", verify=verify, timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        assert proc.poll() is None and time.time() < deadline, proc.output()
        time.sleep(0.2)


# ports this process has handed out: the kernel may give a just-released port again at once, and a
# server started with `free_port(), free_port()` for HTTP and gRPC then found both on one port
_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A port free now on 127.0.0.1, never one this process handed out before."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port


class LiveServer:
    """The API on a free port (uvicorn in a thread); SQLite unless a ``store`` is given; worker
    processes only with ``start_workers=True`` (then supervised child processes, as in serve)."""

    def __init__(self, tmp_path, store=None, start_workers: bool = False, data_dir=None,
                 **settings_kw):  # fmt: skip
        self.settings = Settings(data_dir=data_dir or tmp_path / "data", embedded_worker=False,
                                 lease_s=5.0, heartbeat_s=0.5, **settings_kw)  # fmt: skip
        self.store = store or SQLiteJobStore(
            self.settings.data_dir / "jobs.db", max_attempts=self.settings.max_attempts
        )
        self.app = create_app(self.settings, self.store, start_workers=start_workers)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning",
                           **uvicorn_options(self.settings))
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
        t = threading.Thread(target=w.run_forever, kwargs={"poll_s": 0.05}, daemon=True)
        t.start()
        return w, t


@pytest.fixture
def live(tmp_path):
    with LiveServer(tmp_path) as server:
        yield server
