"""Prometheus metrics through prometheus-client, checked by parsing the page with its own parser."""

from __future__ import annotations

import httpx
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from quicknav_service.api.main import create_app
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings
from tests.service.conftest import free_port, quicknav_process, wait_until_up


def samples(text: str) -> dict[tuple[str, tuple], float]:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def value(page: dict, name: str, **labels) -> float:
    return page[(name, tuple(sorted(labels.items())))]


def grown(before: dict, after: dict, name: str, **labels) -> float:
    """How much a counter grew (request counters live as long as the process: other tests' apps
    in this process count too)."""
    key = (name, tuple(sorted(labels.items())))
    return after[key] - before.get(key, 0.0)


def test_metrics__requests_jobs_heartbeats_durations_and_rollout_servers(tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path, lease_s=30, heartbeat_s=5)
    store = SQLiteJobStore(tmp_path / "jobs.db")
    client = TestClient(create_app(settings, store, start_workers=False))
    before = samples(client.get("/metrics").text)
    ids = [client.post("/jobs/eval", json={"policy": "random", "episodes": 2}).json()["id"]
           for _ in range(3)]  # fmt: skip
    for job_id in ids:
        assert client.get(f"/jobs/{job_id}").status_code == 200
    assert client.get("/jobs/ffff0000").status_code == 404
    running = store.claim("w-1", lease_s=30)  # a worker took one; it heartbeats
    store.finish(store.claim("w-2", lease_s=30).id, "w-2", "succeeded", result={})
    store.register_endpoint({"worker": "worker-a", "address": "gpu-a:50051", "sessions": 2,
                             "env_steps_served": 123_456, "memory_held_mb": 751,
                             "memory_budget_mb": 8192}, ttl_s=60)  # fmt: skip

    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    page = samples(r.text)
    # requests: per route template (not per id), method and status; latency histogram
    assert grown(before, page, "quicknav_http_requests_total", route="/jobs/{job_id}",
                 method="GET", status="200") == 3  # fmt: skip
    assert grown(before, page, "quicknav_http_requests_total", route="/jobs/{job_id}",
                 method="GET", status="404") == 1  # fmt: skip
    assert grown(before, page, "quicknav_http_requests_total", route="/jobs/eval",
                 method="POST", status="202") == 3  # fmt: skip
    assert grown(before, page, "quicknav_http_request_duration_seconds_count",
                 route="/jobs/eval", method="POST") == 3  # fmt: skip
    # the job system
    assert value(page, "quicknav_jobs", status="queued") == 1
    assert value(page, "quicknav_jobs_by_kind", kind="eval", status="running") == 1
    assert value(page, "quicknav_jobs_by_kind", kind="train", status="queued") == 0
    assert value(page, "quicknav_queue_depth") == 1 and value(page, "quicknav_busy_workers") == 1
    age = value(page, "quicknav_worker_heartbeat_age_seconds", job=running.id, worker="w-1")
    assert 0 <= age < 5
    assert value(page, "quicknav_job_duration_seconds_count", kind="eval", status="succeeded") == 1
    assert value(page, "quicknav_rollout_streams_open", address="gpu-a:50051",
                 worker="worker-a") == 2  # fmt: skip
    assert value(page, "quicknav_rollout_env_steps_served_total", address="gpu-a:50051",
                 worker="worker-a") == 123_456  # fmt: skip
    assert value(page, "quicknav_rollout_memory_held_mb", address="gpu-a:50051", worker="worker-a") == 751
    assert value(page, "quicknav_rollout_memory_budget_mb", address="gpu-a:50051", worker="worker-a") == 8192


def test_metrics__summed_over_several_api_processes(tmp_path):
    """`serve --api-workers 2`: whichever process answers /metrics counts every process's requests."""
    port = free_port()
    proc = quicknav_process(["serve", "--no-worker", "--no-grpc", "--api-workers", "2", "--port",
                             str(port)], QUICKNAV_DATA_DIR=str(tmp_path / "data"),
                            PROMETHEUS_MULTIPROC_DIR="")  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, proc)
        for _ in range(40):  # new connections: both processes answer some
            assert httpx.get(f"{url}/presets", timeout=5).status_code == 200
        totals = set()
        for _ in range(6):
            page = samples(httpx.get(f"{url}/metrics", timeout=5).text)
            totals.add(value(page, "quicknav_http_requests_total", route="/presets",
                             method="GET", status="200"))  # fmt: skip
        assert min(totals) >= 40, totals
    finally:
        proc.terminate()
        proc.wait(30)


def test_metrics__head_answers_like_get_without_a_body(tmp_path):
    """Uptime probes check the page with HEAD: 200 and the GET's content type, no body."""
    settings = Settings(_env_file=None, data_dir=tmp_path)
    client = TestClient(create_app(settings, SQLiteJobStore(tmp_path / "jobs.db"), start_workers=False))
    head, get = client.head("/metrics"), client.get("/metrics")
    assert head.status_code == get.status_code == 200
    assert head.headers["content-type"] == get.headers["content-type"] and head.content == b""
