"""The REST SDK and `quicknav jobs` against a live server (real uvicorn, burst-mode worker).

One tiny train job is trained once per module and shared; every other job is submitted only to be
looked at and cancelled while queued, so the file costs one JAX compile.
"""

from __future__ import annotations

import asyncio
import json
import re
import threading
import time

import httpx
import pytest
from quicknav_client import (
    AsyncQuickNavClient,
    BadRequest,
    Conflict,
    ConnectionFailed,
    NotFound,
    PayloadTooLarge,
    QuickNavClient,
    QuickNavError,
    Unauthorized,
    WaitTimeout,
)
from quicknav_client.rest import SSEParser
from typer.testing import CliRunner

from quicknav_cli.main import app
from tests.service.conftest import LiveServer, free_port

TINY = {"env.grid_size": 8, "env.train_rooms": 32, "env.test_rooms": 16, "env.max_steps": 60,
        "num_envs": 16, "algorithm.num_steps": 32, "algorithm.num_minibatches": 4,
        "total_steps": 1536, "chunk_steps": 512}  # fmt: skip
JOB_ID = re.compile(r"\b[0-9a-f]{32}\b")
runner = CliRunner()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("sdk")) as server:
        yield server


@pytest.fixture
def client(live):
    with QuickNavClient(live.url, backoff_s=0.01) as qn:
        yield qn


@pytest.fixture(scope="module")
def trained(live):
    """(job, events): the tiny train job, followed with wait() while a burst worker runs it."""
    with QuickNavClient(live.url) as qn:
        job = qn.train(preset="demo", overrides=TINY)
        assert job.status == "queued"
        worker = threading.Thread(target=live.worker().run_burst, daemon=True)
        worker.start()
        events: list[dict] = []
        job.wait(progress=True, timeout=300, on_event=events.append)
        worker.join(60)
        yield job, events  # inside the with: the job's methods need its client open


# --------------------------------------------------------------------------- test transports
class Recording(httpx.BaseTransport):
    """Forwards to the network and remembers every request."""

    def __init__(self):
        self.inner = httpx.HTTPTransport()
        self.requests: list[httpx.Request] = []

    def handle_request(self, request):
        self.requests.append(request)
        return self.inner.handle_request(request)

    def close(self):
        self.inner.close()


class LoseFirstSubmissionResponse(Recording):
    """The first POST reaches the server, but its response is lost (a read timeout)."""

    lost = False

    def handle_request(self, request):
        response = super().handle_request(request)
        if request.method == "POST" and not self.lost:
            self.lost = True
            response.read()
            response.close()
            raise httpx.ReadTimeout("response lost on the way back", request=request)
        return response


class _Broken(httpx.SyncByteStream):
    def __init__(self, data: bytes):
        self.data = data

    def __iter__(self):
        yield self.data
        raise httpx.ReadError("connection dropped")


class DropFirstEventStream(Recording):
    """The first /events response breaks off in the middle of its second event."""

    cut = False

    def handle_request(self, request):
        response = super().handle_request(request)
        if request.url.path.endswith("/events") and not self.cut:
            self.cut = True
            body = response.read()
            response.close()
            partial = body[: body.index(b"\n\n") + 2 + 10]
            headers = [(k, v) for k, v in response.headers.multi_items() if k != "content-length"]
            return httpx.Response(response.status_code, headers=headers, stream=_Broken(partial),
                                  request=request)  # fmt: skip
        return response


# --------------------------------------------------------------------------- jobs
def test_wait__follows_the_event_stream_to_the_terminal_event_then_refreshes(trained):
    job, events = trained
    kinds = [e["type"] for e in events]
    assert kinds[0] == "started" and kinds[-1] == "succeeded", kinds
    assert kinds.count("progress") == 4  # the compiling phase, then one per chunk
    assert events[1]["metrics"]["phase"] == "compiling" and events[1]["progress"] == 0
    ids = [e["id"] for e in events]
    assert ids == sorted(set(ids))
    progress = [e["progress"] for e in events if e["type"] == "progress"]
    assert progress == sorted(progress) and progress[-1] == pytest.approx(1.0)
    assert job.done and job.succeeded and job.status == job.raw["status"] == "succeeded"
    assert job.result["env_steps"] >= TINY["total_steps"] and job.attempts == 1
    assert job.metrics["env_steps"] == job.result["env_steps"]


def test_metrics_artifacts_and_download__match_the_servers_files(trained, client, live, tmp_path):
    job, _ = trained
    rows = client.job(job.id).metrics_history()
    assert len(rows) == 3 and rows[-1]["env_steps"] == job.result["env_steps"]
    listed = {a["name"]: a["bytes"] for a in job.artifacts()}
    assert {"config.json", "metrics.jsonl", "checkpoint/state.msgpack"} <= set(listed)

    path = job.download("config.json", tmp_path)
    assert path == tmp_path / "config.json"
    config = json.loads(path.read_text())
    assert config == job.config and config["env"]["grid_size"] == 8

    ckpt = client.download(job.id, "checkpoint/state.msgpack", tmp_path / "sub" / "ckpt.bin")
    on_server = live.settings.artifacts_dir / job.id / "checkpoint" / "state.msgpack"
    assert ckpt.read_bytes() == on_server.read_bytes()
    assert ckpt.stat().st_size == listed["checkpoint/state.msgpack"] > 0

    with pytest.raises(NotFound, match=r"no artifact 'nope\.bin'"):
        job.download("nope.bin", tmp_path / "nope.bin")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json", "sub"]


def test_events__resume_with_last_event_id_after_a_dropped_connection(trained, live):
    job, events = trained
    ids = [e["id"] for e in events]
    transport = DropFirstEventStream()
    with QuickNavClient(live.url, backoff_s=0.01, transport=transport) as qn:
        resumed = list(qn.events(job.id))
        tail = list(job.events(after=ids[1]))
    assert [e["id"] for e in resumed] == ids, "no event lost or repeated across the reconnect"
    assert [e["type"] for e in resumed] == [e["type"] for e in events]
    streams = [r for r in transport.requests if r.url.path.endswith("/events")]
    assert len(streams) == 2
    assert "last-event-id" not in streams[0].headers
    assert streams[1].headers["last-event-id"] == str(ids[0])
    assert [e["id"] for e in tail] == ids[2:]


def test_evaluate__maps_to_the_eval_request__cancel_wait_delete(trained, client):
    job, _ = trained
    ev = client.evaluate(job=job, episodes=4, seed=3)
    assert ev.kind == "eval" and ev.status == "queued"
    # the body the API publishes names the train job ``job_id``
    assert ev.request == {"job_id": job.id, "episodes": 4, "seed": 3, "split": "test",
                          "deterministic": True}  # fmt: skip
    # the stored config is resolved: the train job's own env, every field filled in
    assert ev.config["policy"] == "trained" and ev.config["source"] == job.id
    assert ev.config["env"] == job.config["env"] and ev.config["deterministic"] is True
    assert ev.cancel() is ev and ev.status == "cancelled" and ev.done and not ev.succeeded
    assert ev.wait(timeout=10).status == "cancelled"
    ev.delete()
    with pytest.raises(NotFound):
        client.job(ev.id)

    with pytest.warns(DeprecationWarning, match="deterministic"):
        base = client.evaluate(policy="oracle", episodes=2, env={"grid_size": 8}, stochastic=True)
    try:
        assert base.request["policy"] == "oracle" and base.request["env"] == {"grid_size": 8}
        assert "source" not in base.request and base.request["deterministic"] is False
        assert base.config["env"]["grid_size"] == 8 and base.config["deterministic"] is False
        assert base.config["env"]["lidar_beams"] == 16  # defaults filled in
    finally:
        base.cancel()


def test_wait__raises_wait_timeout_when_the_job_does_not_finish(client):
    job = client.train("demo", overrides=TINY)  # queued; no worker runs while this test does
    try:
        start = time.monotonic()
        with pytest.raises(WaitTimeout):
            job.wait(timeout=1.0)
        assert time.monotonic() - start < 5
        assert job.refresh().status == "queued"
    finally:
        assert job.cancel().status == "cancelled"


def test_jobs__filters_and_counts(trained, client):
    job, _ = trained
    page = client.jobs(kind="train", status="succeeded")
    assert page.count >= 1 and job.id in {j.id for j in page}
    assert all(j.kind == "train" and j.status == "succeeded" for j in page)
    assert client.jobs(limit=1).count == client.jobs().count and len(client.jobs(limit=1)) == 1
    assert "demo" in client.presets() and client.health() == {"status": "ok"}
    assert client.ready() == {"status": "ready", "checks": {"store": "ok", "disk": "ok"}}


# --------------------------------------------------------------------------- idempotency, retries
def test_a_retried_submission_returns_the_same_job(live):
    transport = LoseFirstSubmissionResponse()
    with QuickNavClient(live.url, backoff_s=0.01, transport=transport) as qn:
        before = qn.jobs(kind="eval").count
        job = qn.evaluate(policy="random", episodes=3, env={"grid_size": 8})
        try:
            posts = [r for r in transport.requests if r.method == "POST"]
            assert len(posts) == 2, "the lost response was retried"
            keys = {r.headers.get("idempotency-key") for r in posts}
            assert len(keys) == 1 and None not in keys
            assert qn.jobs(kind="eval").count == before + 1, "the retry made no second job"
        finally:
            job.cancel()
        # a new call gets a new key: a new job
        other = qn.evaluate(policy="random", episodes=3, env={"grid_size": 8}).cancel()
        assert other.id != job.id


def test_idempotency_key__same_body_same_job__other_body_conflict(client):
    a = client.train(preset="demo", overrides=TINY, idempotency_key="sdk-key-1")
    try:
        b = client.train(preset="demo", overrides=TINY, idempotency_key="sdk-key-1")
        assert a.id == b.id
        with pytest.raises(Conflict) as e:
            client.train(preset="demo", overrides={**TINY, "seed": 7}, idempotency_key="sdk-key-1")
        assert e.value.status_code == 409 and "sdk-key-1" in str(e.value)
    finally:
        a.cancel()


# --------------------------------------------------------------------------- errors
def test_errors__carry_the_servers_message(client):
    with pytest.raises(BadRequest) as e:
        client.train(preset="demo", num_envs=0)
    assert e.value.status_code == 422 and e.value.detail[0]["loc"][-1] == "num_envs"
    assert "overrides.num_envs" in str(e.value) and "greater than" in str(e.value)

    with pytest.raises(BadRequest, match=r"num_envs=8192 exceeds .* max_envs=4096"):
        client.train(preset="demo", overrides={"num_envs": 8192, "total_steps": 10**8})
    with pytest.raises(BadRequest, match="unknown preset 'nope'"):
        client.train(preset="nope")
    with pytest.raises(BadRequest, match="episodes"):
        client.evaluate(policy="random", episodes=0)
    with pytest.raises(BadRequest, match="exactly one of 'job_id'"):
        client.evaluate()
    with pytest.raises(NotFound) as e:
        client.job("nope")
    assert e.value.status_code == 404 and "no job 'nope'" in str(e.value)
    with pytest.raises(NotFound, match="no job 'nope'"):
        client.evaluate(job="nope")
    with pytest.raises(PayloadTooLarge, match="exceeds the limit"):
        client.train(preset="demo", overrides={"note": "x" * 2_000_000})
    with pytest.raises(ValueError, match="exactly one of"):
        client.train()
    assert issubclass(PayloadTooLarge, QuickNavError) and issubclass(WaitTimeout, TimeoutError)


def test_errors__4xx_are_not_retried(live):
    transport = Recording()
    with QuickNavClient(live.url, backoff_s=0.01, transport=transport) as qn:
        with pytest.raises(BadRequest):
            qn.train(preset="nope")
        with pytest.raises(NotFound):
            qn.job("nope")
    assert len(transport.requests) == 2


def test_errors__connection_failed_after_retries():
    transport = Recording()
    url = f"http://127.0.0.1:{free_port()}"
    qn = QuickNavClient(url, retries=2, backoff_s=0.01, transport=transport)
    with qn, pytest.raises(ConnectionFailed, match="could not reach") as e:
        qn.jobs()
    assert len(transport.requests) == 3 and e.value.status_code is None
    assert url in str(e.value)


def test_auth__token_is_sent_and_a_missing_one_is_unauthorized(tmp_path):
    with LiveServer(tmp_path, api_token="s3cret-token") as server:
        with QuickNavClient(server.url) as anonymous:
            assert anonymous.health() == {"status": "ok"}
            with pytest.raises(Unauthorized, match="bearer token") as e:
                anonymous.jobs()
            assert e.value.status_code == 401
        with QuickNavClient(server.url, token="wrong-token") as wrong, pytest.raises(Unauthorized):
            wrong.presets()
        with QuickNavClient(server.url, token="s3cret-token") as ok:
            assert ok.jobs().count == 0

        denied = runner.invoke(app, ["jobs", "--url", server.url, "list"])
        assert denied.exit_code == 1 and "bearer token" in denied.output
        allowed = runner.invoke(app, ["jobs", "--url", server.url, "list"],
                                env={"QUICKNAV_API_TOKEN": "s3cret-token"})  # fmt: skip
        assert allowed.exit_code == 0, allowed.output
        assert "0 of 0 jobs" in allowed.output


# --------------------------------------------------------------------------- async client
def test_async_client__submit_get_list_cancel_wait(live, tmp_path):
    async def scenario():
        async with AsyncQuickNavClient(live.url, backoff_s=0.01) as qn:
            job = await qn.train(preset="demo", overrides=TINY)
            got = await qn.job(job.id)
            assert got.id == job.id and got.status == "queued" and got.request == job.request
            queued = await qn.jobs(kind="train", status="queued")
            assert job.id in {j.id for j in queued} and queued.count >= 1
            assert (await got.cancel()).status == "cancelled"
            assert (await got.wait(timeout=10)).status == "cancelled"
            events = [e async for e in got.events()]
            assert events[-1]["type"] == "cancelled"
            with pytest.raises(NotFound, match="no job 'nope'"):
                await qn.job("nope")
            return job.id

    assert JOB_ID.fullmatch(asyncio.run(scenario()))


def test_async_client__downloads_an_artifact(trained, live, tmp_path):
    job, _ = trained

    async def scenario():
        async with AsyncQuickNavClient(live.url) as qn:
            remote = await qn.job(job.id)
            rows = await remote.metrics_history()
            path = await remote.download("metrics.jsonl", tmp_path)
            return rows, path

    rows, path = asyncio.run(scenario())
    # compare env_steps: the file holds NaN where the JSON endpoint says null (nan != nan anyway)
    in_file = [json.loads(x)["env_steps"] for x in path.read_text().splitlines()]
    assert in_file == [r["env_steps"] for r in rows] and len(rows) == 3


# --------------------------------------------------------------------------- CLI
def jobs_cli(live, *args: str):
    return runner.invoke(app, ["jobs", "--url", live.url, *args])


def test_cli__submit_list_show_cancel_follow(live):
    sets = [x for k, v in TINY.items() for x in ("--set", f"{k}={v}")]
    r = jobs_cli(live, "submit", "train", "--preset", "demo", *sets)
    assert r.exit_code == 0, r.output
    job_id = JOB_ID.search(r.output).group()
    assert "queued" in r.output

    r = jobs_cli(live, "list", "--kind", "train", "--status", "queued")
    assert r.exit_code == 0 and job_id in r.output, r.output
    r = jobs_cli(live, "show", job_id, "--json")
    shown = json.loads(r.output)
    assert shown["id"] == job_id and shown["config"]["env"]["grid_size"] == 8
    assert shown["request"] == {"preset": "demo", "overrides": TINY}
    r = jobs_cli(live, "show", job_id)
    assert r.exit_code == 0 and "queued" in r.output and "grid_size" in r.output

    r = jobs_cli(live, "cancel", job_id)
    assert r.exit_code == 0 and "cancelled" in r.output
    r = jobs_cli(live, "follow", job_id)
    assert r.exit_code == 1 and "cancelled" in r.output


def test_cli__eval_baseline_request(live):
    r = jobs_cli(
        live, "submit", "eval", "--policy", "random", "--episodes", "3", "--set", "grid_size=8"
    )
    assert r.exit_code == 0, r.output
    job_id = JOB_ID.search(r.output).group()
    with QuickNavClient(live.url) as qn:
        job = qn.job(job_id).cancel()
    assert job.request["env"] == {"grid_size": 8} and job.request["episodes"] == 3


def test_cli__follow_and_download_a_finished_job(trained, live, tmp_path):
    job, _ = trained
    r = jobs_cli(live, "follow", job.id)
    assert r.exit_code == 0 and "succeeded" in r.output, r.output
    r = jobs_cli(live, "artifacts", job.id)
    assert r.exit_code == 0 and "checkpoint/state.msgpack" in r.output
    r = jobs_cli(live, "download", job.id, "config.json", "--out", str(tmp_path / "c.json"))
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "c.json").read_text())["env"]["grid_size"] == 8


def test_cli__errors_print_the_servers_message_and_exit_1(live):
    r = jobs_cli(live, "show", "nope")
    assert r.exit_code == 1 and "no job 'nope'" in r.output and "Traceback" not in r.output
    r = jobs_cli(live, "submit", "train", "--preset", "demo", "--set", "num_envs=0")
    assert r.exit_code == 1 and "num_envs" in r.output and "greater than" in r.output
    r = jobs_cli(live, "submit", "train", "--set", "novalue")
    assert r.exit_code == 2 and "expected key=value" in r.output
    r = jobs_cli(live, "submit", "deploy")
    assert r.exit_code == 2 and "train, sweep and eval" in r.output


# --------------------------------------------------------------------------- SSE parsing
def test_sse_parser__multiline_data_comments_and_events_without_data():
    parser = SSEParser()
    lines = [": keep-alive", "", "id: 7", "event: progress", 'data: {"progress":', "data: 0.5}",
             "", "id: 8", "", "data: plain text", ""]  # fmt: skip
    out = [e for e in map(parser.feed, lines) if e is not None]
    assert out == [{"progress": 0.5, "type": "progress", "id": 7},
                   {"data": "plain text", "type": "message", "id": None}]  # fmt: skip


def test_metrics_summary__skips_nan_and_missing_values():
    from quicknav_client.rest import metrics_summary

    assert metrics_summary({"success_rate": float("nan"), "mean_return": None}) == ""
    shown = metrics_summary({"success_rate": 0.5, "mean_return": -2.25, "steps_per_s": 12345.6})
    assert shown == "success 50%, return -2.2, 12,346 steps/s"
