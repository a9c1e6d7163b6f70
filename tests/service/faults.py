"""Fault injection for the fault suite and the chaos benchmark: a Redis server of our own that can
be killed and restarted, and a small file system that can be filled."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
from pathlib import Path

import redis


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RedisServer:
    """A redis-server on a free port with its append-only file in ``folder``: kill -9 it, start it
    again, and it comes back with what it had acknowledged (appendfsync always)."""

    def __init__(self, folder: Path, password: str | None = None):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.password = password
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        auth = f":{self.password}@" if self.password else ""
        return f"redis://{auth}127.0.0.1:{self.port}/0"

    def start(self, timeout: float = 10.0) -> RedisServer:
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--dir",
             str(self.folder), "--appendonly", "yes", "--appendfsync", "always", "--save", "",
             "--daemonize", "no", "--logfile", str(self.folder / "redis.log"),
             *(["--requirepass", self.password] if self.password else [])],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        client = redis.Redis(port=self.port, socket_connect_timeout=0.5, password=self.password)
        deadline = time.time() + timeout
        while time.time() < deadline:
            with contextlib.suppress(redis.ConnectionError, redis.BusyLoadingError):
                if client.ping():
                    return self
            time.sleep(0.05)
        raise RuntimeError(f"redis-server did not start on port {self.port}")

    def kill(self) -> None:
        """kill -9: no shutdown, no final save."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def __enter__(self) -> RedisServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.kill()


class SmallDisk:
    """A tmpfs of ``mb`` MiB mounted at ``path`` (needs root, as CI and the dev VM have)."""

    def __init__(self, path: Path, mb: int):
        self.path = Path(path)
        self.mb = mb
        self.filler = self.path / "filler.bin"

    def __enter__(self) -> SmallDisk:
        self.path.mkdir(parents=True, exist_ok=True)
        result = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={self.mb}m", "tmpfs",
                                 str(self.path)], capture_output=True, text=True)  # fmt: skip
        if result.returncode != 0:
            raise RuntimeError(
                "the disk-full test mounts a small tmpfs and needs root for it: "
                + result.stderr.strip()
            )
        return self

    def __exit__(self, *exc) -> None:
        subprocess.run(["umount", "-l", str(self.path)], capture_output=True)

    def free_bytes(self) -> int:
        st = os.statvfs(self.path)
        return st.f_bavail * st.f_frsize

    def fill(self, leave_bytes: int = 0) -> None:
        """Write a filler file until only ``leave_bytes`` are free (0: until ENOSPC)."""
        chunk = b"\0" * 65536
        with open(self.filler, "ab") as f:
            while True:
                room = self.free_bytes() - leave_bytes
                if room <= 0:
                    break
                try:
                    f.write(chunk[: min(len(chunk), room)])
                    f.flush()
                except OSError:
                    break

    def empty(self) -> None:
        self.filler.unlink(missing_ok=True)
