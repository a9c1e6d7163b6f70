"""`quicknav serve` as a user starts it: one command with the HTTP API, the gRPC Rollout server and a
supervised worker process; a demo-sized job runs through the SDK and the same server process serves
a rollout stream."""

from __future__ import annotations

import time

import numpy as np
from quicknav_client import QuickNavClient, RolloutClient

from tests.service.conftest import free_port, quicknav_process, wait_until_up


def test_serve__http_grpc_and_a_supervised_worker_in_one_command(tmp_path):
    http_port, grpc_port = free_port(), free_port()
    proc = quicknav_process(["serve", "--port", str(http_port), "--grpc-port", str(grpc_port)],
                            QUICKNAV_DATA_DIR=str(tmp_path / "data"))  # fmt: skip
    url = f"http://127.0.0.1:{http_port}"
    try:
        wait_until_up(url, proc)
        with QuickNavClient(url) as qn:
            job = qn.evaluate(policy="random", episodes=4, env={"grid_size": 8, "train_rooms": 16,
                                                               "test_rooms": 8, "max_steps": 20})  # fmt: skip
            job = job.wait(timeout=120)
            assert job.status == "succeeded", job.error
            assert job.result["metrics"]["episodes"] == 4
            # the all-in-one server lists its own Rollout endpoint
            listed = qn.rollout_endpoints()
            assert [e["address"] for e in listed] == [f"127.0.0.1:{grpc_port}"], listed
            assert listed[0]["max_sessions"] >= 1
            # announcing did not start JAX in the API process (on a GPU it would take memory the
            # worker processes need): the device is known once a stream has used it
            assert listed[0]["backend"] is None
        with RolloutClient(listed[0]["address"]) as rc:
            started = rc.start(
                num_envs=2, config={"grid_size": 8, "train_rooms": 16, "test_rooms": 8}
            )
            t = rc.step(np.zeros((2, 2), np.float32))
            assert t.observations.shape == started.observations.shape
    finally:
        proc.terminate()
        proc.wait(30)


def test_worker__serves_rollout_on_its_device_and_the_api_lists_it(tmp_path):
    """`quicknav worker --grpc-port`: the process that owns the accelerator serves Rollout; the
    API (here without a gRPC server of its own) lists it, and it is gone once the worker stops."""
    from tests.service.conftest import LiveServer

    with LiveServer(tmp_path, grpc_enabled=False) as live, QuickNavClient(live.url) as qn:
        assert qn.rollout_endpoints() == []
        grpc_port = free_port()
        proc = quicknav_process(["worker", "--grpc-port", str(grpc_port)],
                                QUICKNAV_DATA_DIR=str(live.settings.data_dir),
                                QUICKNAV_HEARTBEAT_S="1")  # fmt: skip
        try:
            deadline = time.time() + 90
            while not (listed := qn.rollout_endpoints()):
                assert proc.poll() is None and time.time() < deadline, proc.output()
                time.sleep(0.3)
            assert len(listed) == 1 and listed[0]["address"] == f"127.0.0.1:{grpc_port}"
            assert listed[0]["worker"].startswith("worker-") and listed[0]["pid"] == proc.pid
            with RolloutClient(listed[0]["address"]) as rc:
                started = rc.start(num_envs=4, config={"grid_size": 8, "train_rooms": 16,
                                                       "test_rooms": 8, "max_steps": 5})  # fmt: skip
                for _ in range(8):  # past the 5-step limit: final observations come back
                    t = rc.step(np.zeros((4, 2), np.float32))
                assert t.observations.shape == started.observations.shape
            assert qn.rollout_endpoints()[0]["sessions"] in (0, 1)
        finally:
            proc.terminate()
            proc.wait(30)
        assert qn.rollout_endpoints() == []  # withdrawn on SIGTERM
