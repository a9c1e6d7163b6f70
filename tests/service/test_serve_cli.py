"""`quicknav serve` as a user starts it: one command with the HTTP API, the gRPC Rollout server and a
supervised worker process; a demo-sized job runs through the SDK and the same server process serves
a rollout stream."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import httpx
import numpy as np
from quicknav_client import QuickNavClient, RolloutClient

from tests.service.conftest import free_port


def test_serve__http_grpc_and_a_supervised_worker_in_one_command(tmp_path):
    http_port, grpc_port = free_port(), free_port()
    env = {**os.environ, "QUICKNAV_DATA_DIR": str(tmp_path / "data")}
    env.pop("QUICKNAV_REDIS_URL", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "quicknav_cli", "serve", "--port", str(http_port),
         "--grpc-port", str(grpc_port)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    url = f"http://127.0.0.1:{http_port}"
    try:
        deadline = time.time() + 60
        while True:
            try:
                if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert proc.poll() is None and time.time() < deadline, proc.stdout.read()
            time.sleep(0.2)
        with QuickNavClient(url) as qn:
            job = qn.evaluate(policy="random", episodes=4, env={"grid_size": 8, "train_rooms": 16,
                                                               "test_rooms": 8, "max_steps": 20})  # fmt: skip
            job = job.wait(timeout=120)
            assert job.status == "succeeded", job.error
            assert job.result["metrics"]["episodes"] == 4
        with RolloutClient(f"127.0.0.1:{grpc_port}") as rc:
            started = rc.start(
                num_envs=2, config={"grid_size": 8, "train_rooms": 16, "test_rooms": 8}
            )
            t = rc.step(np.zeros((2, 2), np.float32))
            assert t.observations.shape == started.observations.shape
    finally:
        proc.terminate()
        proc.wait(30)
