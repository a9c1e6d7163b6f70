"""An exposed server, probed as an attacker would: cross-site requests cannot change anything
(token or not), the API answers only the host names it trusts (DNS rebinding), and the checks
hold in a real browser: a page on another local origin tries to cancel a job."""

from __future__ import annotations

import http.server
import socketserver
import threading

import httpx
import pytest
from fastapi.testclient import TestClient

from quicknav_service.api.main import create_app
from quicknav_service.jobs.models import JobKind
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings
from tests.processes import LoggedProcess
from tests.service.conftest import LiveServer, free_port


@pytest.fixture
def api(tmp_path):
    store = SQLiteJobStore(tmp_path / "jobs.db")
    settings = Settings(data_dir=tmp_path, embedded_worker=False, allowed_origins="http://lab.example:9000")
    with TestClient(create_app(settings, store, start_workers=False)) as client:
        yield client, store


def queued_job(store) -> str:
    job, _ = store.submit(JobKind.train, {"preset": "demo"}, {"total_steps": 1000})
    return job.id


def test_cross_site__a_foreign_origin_changes_nothing(api):
    client, store = api
    job = queued_job(store)
    for origin in ("http://evil.example", "null", "http://testserver.evil.example"):
        r = client.post(f"/jobs/{job}/cancel", json={}, headers={"Origin": origin})
        assert r.status_code == 403 and "cross-site" in r.json()["detail"], (origin, r.text)
    r = client.delete(f"/jobs/{job}", headers={"Origin": "http://evil.example"})
    assert r.status_code == 403
    r = client.post("/jobs/train", json={"preset": "demo"}, headers={"Origin": "http://evil.example"})
    assert r.status_code == 403
    assert store.get(job).status.value == "queued" and store.counts().get("queued") == 1
    # the server's own pages, and an origin the operator allowed, may
    ok = client.post(f"/jobs/{job}/cancel", json={}, headers={"Origin": "http://testserver"})
    assert ok.status_code == 200 and ok.json()["status"] == "cancelled"
    other = queued_job(store)
    ok = client.post(f"/jobs/{other}/cancel", json={}, headers={"Origin": "http://lab.example:9000"})
    assert ok.status_code == 200


def test_cross_site__a_post_must_be_json_or_carry_the_web_header(api):
    client, store = api
    job = queued_job(store)
    for kind in ("application/x-www-form-urlencoded", "text/plain", "multipart/form-data; boundary=x"):
        r = client.post(f"/jobs/{job}/cancel", content=b"a=1", headers={"Content-Type": kind})
        assert r.status_code == 415 and "application/json" in r.json()["detail"], (kind, r.text)
    assert client.post(f"/jobs/{job}/cancel").status_code == 415  # no body at all
    assert store.get(job).status.value == "queued"
    assert client.post(f"/jobs/{job}/cancel", headers={"X-QuickNav-Web": "1"}).status_code == 200
    assert client.post(f"/jobs/{queued_job(store)}/cancel", json={}).status_code == 200
    assert client.post(f"/jobs/{queued_job(store)}/cancel", json={"x": 1}).status_code == 422


def test_trusted_hosts__a_foreign_host_name_is_refused_everywhere(api):
    client, _ = api
    for path in ("/healthz", "/jobs", "/"):
        r = client.get(path, headers={"Host": "attacker.example"})
        assert r.status_code == 400, path
        assert "attacker.example" in r.json()["detail"] and "QUICKNAV_ALLOWED_HOSTS" in r.json()["detail"]
        # the names the server does answer to are not told to a stranger
        assert not any(h in r.json()["detail"] for h in ("testserver", "127.0.0.1", "localhost")), r.text
    assert client.get("/healthz", headers={"Host": "localhost:8000"}).status_code == 200
    assert client.get("/healthz", headers={"Host": "[::1]:8000"}).status_code == 200


def test_security_headers__no_other_site_may_frame_any_answer(api):
    client, _ = api
    for path, host in (("/", "localhost"), ("/healthz", "localhost"), ("/docs", "localhost"),
                       ("/jobs/nope", "localhost"), ("/healthz", "attacker.example")):  # fmt: skip
        r = client.get(path, headers={"Host": host})
        assert r.headers["x-frame-options"] == "DENY", (path, r.status_code)
        assert r.headers["content-security-policy"] == "frame-ancestors 'none'", path
        assert r.headers["x-content-type-options"] == "nosniff", path


def test_trusted_hosts__defaults_are_localhost_and_the_bound_address(tmp_path):
    s = Settings(data_dir=tmp_path, host="10.1.2.3", allowed_hosts=None)
    assert s.trusted_hosts == ["localhost", "127.0.0.1", "::1", "10.1.2.3"]
    wide = Settings(data_dir=tmp_path, host="0.0.0.0", allowed_hosts=None).trusted_hosts
    assert "0.0.0.0" not in wide and {"localhost", "127.0.0.1"} <= set(wide) and len(wide) >= 4
    assert Settings(data_dir=tmp_path, allowed_hosts="api, *.lab.example").trusted_hosts == [
        "api", "*.lab.example"]  # fmt: skip


EVIL_PAGE = """<!doctype html><html><body>
<form id="f" method="POST" action="{api}/jobs/{job}/cancel" enctype="text/plain">
  <input name='{{"x":"' value='"}}'>
</form>
<script>
  // a fetch needing no preflight: text/plain, no custom header
  fetch("{api}/jobs/{job}/cancel", {{method: "POST", mode: "no-cors", body: "{{}}",
                                     headers: {{"Content-Type": "text/plain"}}}})
    .finally(() => {{ document.title = "fetched"; document.getElementById("f").submit(); }});
</script></body></html>"""


def test_cross_site__a_page_on_another_origin_cannot_cancel_in_a_real_browser(tmp_path):
    from playwright.sync_api import sync_playwright

    from tests.service.test_web_browser import chromium_path

    with LiveServer(tmp_path) as live:
        job = queued_job(live.store)
        (tmp_path / "evil.html").write_text(EVIL_PAGE.format(api=live.url, job=job))
        port = free_port()
        handler = lambda *a: http.server.SimpleHTTPRequestHandler(*a, directory=str(tmp_path))  # noqa: E731
        with socketserver.TCPServer(("127.0.0.1", port), handler) as evil:
            threading.Thread(target=evil.serve_forever, daemon=True).start()
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium_path(), args=["--no-sandbox"])
                page = browser.new_page()
                page.goto(f"http://localhost:{port}/evil.html")
                page.wait_for_url(f"{live.url}/jobs/{job}/cancel", timeout=20_000)  # the form posted
                shown = page.content()
                browser.close()
            evil.shutdown()
        assert "cross-site request refused" in shown or "application/json" in shown, shown[:500]
        assert httpx.get(f"{live.url}/jobs/{job}").json()["status"] == "queued"


# --------------------------------------------------------------------------- failed logins
TOKEN = "exposure-test-token-0123456789"


@pytest.fixture
def locked(tmp_path):
    store = SQLiteJobStore(tmp_path / "jobs.db")
    settings = Settings(data_dir=tmp_path, embedded_worker=False, api_token=TOKEN,
                        auth_failures_max=5, auth_failure_window_s=30)  # fmt: skip
    with TestClient(create_app(settings, store, start_workers=False)) as client:
        yield client, store, settings


def test_auth__guessing_is_rate_limited_per_address_with_retry_after(locked):
    client, _, _ = locked
    for _ in range(5):
        assert client.get("/jobs", headers={"Authorization": "Bearer nope"}).status_code == 401
    r = client.get("/jobs", headers={"Authorization": "Bearer nope"})
    assert r.status_code == 429 and 1 <= int(r.headers["Retry-After"]) <= 30
    assert "QUICKNAV_AUTH_FAILURES_MAX" in r.json()["detail"]
    # while blocked, even the right token waits; the session route counts and is refused too
    assert client.get("/jobs", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 429
    assert client.post("/auth/session", json={"token": TOKEN}).status_code == 429


@pytest.mark.parametrize("proxies", [None, "127.0.0.1"])
def test_auth__x_forwarded_for_counts_only_from_a_proxy_the_operator_names(tmp_path, proxies):
    """Thirty wrong tokens from one local client, each claiming another address: by default the
    claim is ignored and the limiter stops it; behind a proxy the operator names
    (QUICKNAV_TRUSTED_PROXIES), each forwarded address is its own client."""
    with LiveServer(tmp_path, api_token=TOKEN, auth_failures_max=5, auth_failure_window_s=30,
                    trusted_proxies=proxies) as live:  # fmt: skip
        codes = [httpx.get(f"{live.url}/jobs", headers={"Authorization": "Bearer nope",
                                                         "X-Forwarded-For": f"10.1.0.{i}"}).status_code
                 for i in range(30)]  # fmt: skip
    if proxies is None:
        assert codes[:5] == [401] * 5 and set(codes[5:]) == {429}, codes
    else:
        assert set(codes) == {401}, codes


def test_auth__the_session_route_counts_failures_too(locked):
    client, _, _ = locked
    for _ in range(5):
        assert client.post("/auth/session", json={"token": "guess"}).status_code == 401
    assert client.get("/jobs", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 429


def test_sessions__random_server_side_revoked_by_sign_out_and_by_a_token_change(locked, tmp_path):
    client, store, settings = locked
    first = client.post("/auth/session", json={"token": TOKEN})
    cookie = first.cookies["quicknav_session"]
    again = TestClient(client.app).post("/auth/session", json={"token": TOKEN}).cookies["quicknav_session"]
    assert cookie != again and TOKEN not in cookie and len(cookie) >= 40  # random per login
    assert client.get("/jobs").status_code == 200
    # signed out: the old cookie no longer opens anything, even when sent again by hand
    assert client.delete("/auth/session").status_code == 204
    replay = TestClient(client.app, cookies={"quicknav_session": cookie})
    assert replay.get("/jobs").status_code == 401
    # a token change ends every session opened with the old token
    other = TestClient(client.app, cookies={"quicknav_session": again})
    assert other.get("/jobs").status_code == 200
    changed = settings.model_copy(update={"api_token": "a-new-token-9876543210"})
    with TestClient(create_app(changed, store, start_workers=False),
                    cookies={"quicknav_session": again}) as after:  # fmt: skip
        assert after.get("/jobs").status_code == 401


def test_metrics__needs_a_token_when_the_server_has_one(tmp_path):
    store = SQLiteJobStore(tmp_path / "jobs.db")
    settings = Settings(data_dir=tmp_path, embedded_worker=False, api_token=TOKEN,
                        metrics_token="scrape-only-token-42")  # fmt: skip
    with TestClient(create_app(settings, store, start_workers=False)) as client:
        assert client.get("/metrics").status_code == 401
        assert client.head("/metrics").status_code == 401
        page = client.get("/metrics", headers={"Authorization": "Bearer scrape-only-token-42"})
        assert page.status_code == 200 and "quicknav_jobs" in page.text
        assert client.get("/metrics", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
        # the metrics token opens /metrics only
        assert client.get("/jobs", headers={"Authorization": "Bearer scrape-only-token-42"}).status_code == 401
        assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200


def test_readyz__writes_its_disk_probe_at_most_every_few_seconds(tmp_path, monkeypatch):
    from quicknav_service import disk

    probes = []
    real = disk._probe_disk
    monkeypatch.setattr(disk, "_probe_disk", lambda d: probes.append(d) or real(d))
    store = SQLiteJobStore(tmp_path / "jobs.db")
    with TestClient(create_app(Settings(data_dir=tmp_path, embedded_worker=False), store,
                               start_workers=False)) as client:  # fmt: skip
        for _ in range(50):
            assert client.get("/readyz").status_code == 200
    assert len(probes) == 1


def test_readyz__a_full_disk_is_probed_again_so_its_recovery_shows_at_once(tmp_path, monkeypatch):
    from quicknav_service import disk

    answers = iter(["full", "full", "ok", "ok"])
    probes = []
    monkeypatch.setattr(disk, "_probe_disk", lambda d: probes.append(d) or next(answers))
    store = SQLiteJobStore(tmp_path / "jobs.db")
    with TestClient(create_app(Settings(data_dir=tmp_path, embedded_worker=False), store,
                               start_workers=False)) as client:  # fmt: skip
        codes = [client.get("/readyz").status_code for _ in range(5)]
    assert codes == [503, 503, 200, 200, 200] and len(probes) == 3  # the good answer is reused
    # a cached "ok" is not trusted once the file system reports almost no free space
    monkeypatch.setattr(disk, "_free_bytes", lambda d: 0)
    assert disk.disk_check(tmp_path) == "ok" and len(probes) == 4


def test_idempotency__a_client_key_cannot_name_the_services_own(tmp_path):
    from quicknav_service.jobs.service import JobsService
    from quicknav_service.schemas import TrainJobCreate

    store = SQLiteJobStore(tmp_path / "jobs.db")
    jobs = JobsService(store, Settings(data_dir=tmp_path))
    # the service files a sweep's batches under "sweep:<id>:batch:<i>"; a client sending that key
    # gets a job of its own, and the service's key is still free for the service
    sweep_key = "sweep:abc:batch:0"
    mine = jobs.submit_train(TrainJobCreate(preset="demo"), sweep_key)
    theirs, created = store.submit(JobKind.train, {"x": 1}, {"total_steps": 1}, idempotency_key=sweep_key)
    assert created and theirs.id != mine.id
    assert jobs.submit_train(TrainJobCreate(preset="demo"), sweep_key).id == mine.id  # a retry is still safe


# --------------------------------------------------------------------------- live servers
def test_headers__a_client_that_never_finishes_its_headers_is_cut_off(tmp_path):
    import socket
    import time

    with LiveServer(tmp_path, header_timeout_s=0.5) as live:
        with socket.create_connection(("127.0.0.1", live.port), timeout=5) as s:
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
            t0 = time.time()
            assert s.recv(1024) == b""  # closed by the server, no answer
            assert time.time() - t0 < 3
        # a request that completes in time is answered as usual
        assert httpx.get(f"{live.url}/healthz").status_code == 200


def test_event_streams__capped_per_client_with_retry_after(tmp_path):
    with LiveServer(tmp_path, sse_max_per_client=2) as live:
        job = queued_job(live.store)  # queued, no worker: its stream stays open
        with httpx.Client(timeout=10) as c:
            streams = [c.stream("GET", f"{live.url}/jobs/{job}/events") for _ in range(2)]
            opened = [s.__enter__() for s in streams]
            assert all(r.status_code == 200 for r in opened)
            third = c.get(f"{live.url}/jobs/{job}/events")
            assert third.status_code == 503 and third.headers["Retry-After"] == "5"
            assert "QUICKNAV_SSE_MAX_PER_CLIENT" in third.json()["detail"]
            streams[0].__exit__(None, None, None)
            import time

            deadline = time.time() + 5
            while live.app.state.streams.open.get("127.0.0.1", 0) > 1 and time.time() < deadline:
                time.sleep(0.05)
            with c.stream("GET", f"{live.url}/jobs/{job}/events") as again:
                assert again.status_code == 200
            streams[1].__exit__(None, None, None)


def test_grpc__same_token_format_as_rest_and_guessing_is_limited(tmp_path):
    import grpc
    import numpy as np
    from quicknav_client.rollout import RolloutClient

    from quicknav_service.rollout.server import BackgroundServer

    settings = Settings(data_dir=tmp_path, grpc_port=0, api_token=TOKEN, auth_failures_max=3)
    srv = BackgroundServer(settings, port=0).start()
    target = f"127.0.0.1:{srv.port}"
    config = {"grid_size": 8, "lidar_beams": 8, "train_rooms": 8, "test_rooms": 8}
    try:
        from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
        from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc

        def code_of(metadata):
            """One stream opened with exactly this metadata: the status it ends with."""
            with grpc.insecure_channel(target) as channel:
                start = pb.AgentMessage(start=pb.Start(num_envs=1))
                replies = pb_grpc.RolloutServiceStub(channel).Rollout(iter([start]), metadata=metadata)
                with pytest.raises(grpc.RpcError) as e:
                    list(replies)
            return e.value.code()

        # the bare token (no "Bearer ") is refused, as REST refuses it
        assert code_of((("authorization", TOKEN),)) == grpc.StatusCode.UNAUTHENTICATED
        assert code_of((("authorization", "Bearer wrong"),)) == grpc.StatusCode.UNAUTHENTICATED
        assert code_of((("authorization", "Bearer wrong"),)) == grpc.StatusCode.UNAUTHENTICATED
        assert code_of((("authorization", f"Bearer {TOKEN}"),)) == grpc.StatusCode.RESOURCE_EXHAUSTED
    finally:
        srv.stop()
    srv = BackgroundServer(settings, port=0).start()  # a fresh process's limiter: the token works
    try:
        with RolloutClient(f"127.0.0.1:{srv.port}", token=TOKEN) as rc:
            rc.start(num_envs=1, config=config)
            assert rc.step(np.zeros((1, 2), np.float32)).observations.shape[0] == 1
    finally:
        srv.stop()


@pytest.mark.slow  # serves with Redis, runs a tiny job through a worker process: ~40 s
def test_secrets__never_in_logs_answers_or_readiness(tmp_path):
    import os
    import signal
    import sys
    import time

    from tests.service.conftest import wait_until_up
    from tests.service.faults import RedisServer

    password = "redis-Secret-pw-4711"
    with RedisServer(tmp_path / "redis", password=password) as redis_server:
        port, grpc_port = free_port(), free_port()
        env = {**os.environ, "QUICKNAV_REDIS_URL": redis_server.url, "QUICKNAV_API_TOKEN": TOKEN,
               "QUICKNAV_DATA_DIR": str(tmp_path / "data"), "QUICKNAV_PORT": str(port),
               "QUICKNAV_GRPC_PORT": str(grpc_port), "QUICKNAV_AUTH_FAILURES_MAX": "3"}  # fmt: skip
        server = LoggedProcess([sys.executable, "-m", "quicknav_cli", "serve"], env=env,
                               start_new_session=True)
        url = f"http://127.0.0.1:{port}"
        answers = []
        try:
            wait_until_up(url, server, timeout=90)
            auth = {"Authorization": f"Bearer {TOKEN}"}
            tiny = {"env.grid_size": 8, "env.train_rooms": 16, "env.test_rooms": 8, "num_envs": 8,
                    "algorithm.num_steps": 16, "algorithm.num_minibatches": 2, "total_steps": 512}  # fmt: skip
            job = httpx.post(f"{url}/jobs/train", json={"preset": "demo", "overrides": tiny},
                             headers=auth).json()  # fmt: skip
            deadline = time.time() + 240
            while time.time() < deadline:
                state = httpx.get(f"{url}/jobs/{job['id']}", headers=auth)
                if state.json()["status"] in ("succeeded", "failed"):
                    break
                time.sleep(1)
            answers += [state.text, httpx.get(f"{url}/readyz").text,
                        httpx.get(f"{url}/metrics", headers=auth).text,
                        httpx.get(f"{url}/rollout/endpoints", headers=auth).text]  # fmt: skip
            assert state.json()["status"] == "succeeded", state.text
            for _ in range(4):  # failed logins, then the 429
                answers.append(httpx.get(f"{url}/jobs", headers={"Authorization": "Bearer x"}).text)
        finally:
            os.killpg(server.pid, signal.SIGTERM)
            log = server.finish(60)
    for text in [log, *answers]:
        assert password not in text and TOKEN not in text, text[-3000:]
    assert "redis://:***@127.0.0.1" in log  # the store is named, its password is not


# --------------------------------------------------------------------------- one count, every door
LIMITER_REDIS = "redis://127.0.0.1:6379/10"  # this test's own DB index


def test_auth__one_count_for_rest_rollout_and_policy_in_quicknav_serve(tmp_path):
    """`quicknav serve` gives its three doors one limiter: wrong tokens spread over REST, the
    Rollout stream and the Policy stream add up to QUICKNAV_AUTH_FAILURES_MAX (each door used to
    keep its own count, which gave three times the documented guesses)."""
    import grpc
    from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
    from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc

    from tests.service.conftest import quicknav_process, wait_until_up

    http_port, grpc_port = free_port(), free_port()
    proc = quicknav_process(["serve", "--port", str(http_port), "--grpc-port", str(grpc_port)],
                            QUICKNAV_DATA_DIR=str(tmp_path / "data"), QUICKNAV_API_TOKEN=TOKEN,
                            QUICKNAV_AUTH_FAILURES_MAX="6", QUICKNAV_EMBEDDED_WORKER="false")  # fmt: skip
    url = f"http://127.0.0.1:{http_port}"

    def rest(token: str) -> int:
        return httpx.get(f"{url}/jobs", headers={"Authorization": f"Bearer {token}"}).status_code

    def stream(service: str, token: str) -> grpc.StatusCode:
        with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
            if service == "rollout":
                calls = pb_grpc.RolloutServiceStub(channel).Rollout
                first = pb.AgentMessage(start=pb.Start(num_envs=1, config_json='{"grid_size": 0}'))
            else:
                calls = pb_grpc.PolicyServiceStub(channel).Act
                first = pb.PolicyRequest(load=pb.LoadPolicy(job_id="no-such-job"))
            with pytest.raises(grpc.RpcError) as e:
                list(calls(iter([first]), metadata=(("authorization", f"Bearer {token}"),), timeout=30))
        return e.value.code()

    try:
        wait_until_up(url, proc)
        assert [rest("nope"), rest("nope")] == [401, 401]
        for service in ("rollout", "policy"):
            codes = [stream(service, "nope") for _ in range(2)]
            assert codes == [grpc.StatusCode.UNAUTHENTICATED] * 2, (service, codes)
        # six failures in all: every door now refuses this address, even with the right token
        assert rest(TOKEN) == 429
        assert stream("rollout", TOKEN) == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert stream("policy", TOKEN) == grpc.StatusCode.RESOURCE_EXHAUSTED
    finally:
        proc.terminate()
        proc.wait(30)


def test_auth__on_redis_the_count_is_shared_by_every_api_process_and_survives_an_outage(tmp_path, caplog):
    """With the service on Redis, two API processes (two apps, as uvicorn's workers or two
    machines run them) share one count per address; while Redis is unreachable each process
    still counts on its own."""
    import redis

    from quicknav_service.auth import RedisFailureLimiter, make_limiter

    redis.Redis.from_url(LIMITER_REDIS).flushdb()
    settings = Settings(data_dir=tmp_path, embedded_worker=False, api_token=TOKEN, redis_url=LIMITER_REDIS,
                        auth_failures_max=5, auth_failure_window_s=30)  # fmt: skip
    assert isinstance(make_limiter(settings), RedisFailureLimiter)
    apps = [create_app(settings, SQLiteJobStore(tmp_path / f"jobs-{i}.db"), start_workers=False) for i in (0, 1)]
    try:
        with TestClient(apps[0]) as a, TestClient(apps[1]) as b:
            wrong = {"Authorization": "Bearer nope"}
            assert [a.get("/jobs", headers=wrong).status_code for _ in range(3)] == [401] * 3
            assert [b.get("/jobs", headers=wrong).status_code for _ in range(2)] == [401] * 2
            for client in (a, b):  # five in all, across the two processes
                r = client.get("/jobs", headers={"Authorization": f"Bearer {TOKEN}"})
                assert r.status_code == 429 and 1 <= int(r.headers["Retry-After"]) <= 30, r.text
        keys = redis.Redis.from_url(LIMITER_REDIS).keys("quicknav:auth-failures:*")
        assert len(keys) == 1 and 0 < redis.Redis.from_url(LIMITER_REDIS).pttl(keys[0]) <= 31_000
    finally:
        redis.Redis.from_url(LIMITER_REDIS).flushdb()

    # Redis gone: the limiter counts in this process, and says so in the log
    down = RedisFailureLimiter(f"redis://127.0.0.1:{free_port()}/0", limit=2, window_s=30)
    with caplog.at_level("WARNING", logger="quicknav.auth"):
        assert down.retry_after("10.0.0.1") is None
        down.failed("10.0.0.1")
        down.failed("10.0.0.1")
        assert 1 <= down.retry_after("10.0.0.1") <= 30 and down.retry_after("10.0.0.2") is None
    said = [r.getMessage() for r in caplog.records if r.name == "quicknav.auth"]
    assert len(said) == 1 and "Redis unreachable" in said[0], said  # once per outage, not per guess
