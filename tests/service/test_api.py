"""End to end over HTTP against a live server: jobs, SSE, artifacts, eval, cancel, idempotency, auth."""

from __future__ import annotations

import json
import time

import httpx
import pytest

from tests.service.conftest import LiveServer

TINY = {"env.grid_size": 8, "env.train_rooms": 32, "env.test_rooms": 16, "env.max_steps": 60,
        "num_envs": 16, "algorithm.num_steps": 32, "algorithm.num_minibatches": 4,
        "total_steps": 1536, "chunk_steps": 512}  # fmt: skip


def submit_tiny(url, **extra) -> dict:
    r = httpx.post(f"{url}/jobs/train", json={"preset": "demo", "overrides": {**TINY, **extra}})
    assert r.status_code == 202, r.text
    assert r.headers["location"] == f"/jobs/{r.json()['id']}"
    return r.json()


def sse_events(url, job_id, last_event_id=None, timeout=300) -> list[tuple[int, str, dict]]:
    headers = {"Last-Event-ID": str(last_event_id)} if last_event_id else {}
    out, cur = [], {}
    with httpx.stream("GET", f"{url}/jobs/{job_id}/events", headers=headers, timeout=timeout) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("id: "):
                cur["id"] = int(line[4:])
            elif line.startswith("event: "):
                cur["event"] = line[7:]
            elif line.startswith("data: "):
                cur["data"] = json.loads(line[6:])
            elif line == "" and cur:
                out.append((cur["id"], cur["event"], cur["data"]))
                cur = {}
    return out


def wait_status(url, job_id, statuses, timeout=300) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        job = httpx.get(f"{url}/jobs/{job_id}").json()
        if job["status"] in statuses:
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} never reached {statuses}: {job}")


def test_train_job__sse_artifacts_metrics_then_eval_job(live):
    job = submit_tiny(live.url)
    assert job["status"] == "queued" and job["kind"] == "train"
    worker, thread = live.run_worker_in_background()
    try:
        events = sse_events(live.url, job["id"])
        kinds = [e[1] for e in events]
        assert kinds[0] == "started" and kinds[-1] == "succeeded"
        # before the first chunk the job says it compiles (and since when); then one per chunk
        phases = [e[2]["metrics"].get("phase") for e in events if e[1] == "progress"]
        assert phases == ["compiling", "training", "training", "training"], phases
        compiling = next(e[2]["metrics"] for e in events if e[1] == "progress")
        assert 0 < time.time() - compiling["phase_since"] < 600
        ids = [e[0] for e in events]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
        progress = [e[2]["progress"] for e in events if e[1] == "progress"]
        assert progress == sorted(progress) and progress[-1] == pytest.approx(1.0)
        # resumable: everything after the second event
        tail = sse_events(live.url, job["id"], last_event_id=ids[1])
        assert [e[0] for e in tail] == ids[2:]

        done = httpx.get(f"{live.url}/jobs/{job['id']}").json()
        assert (
            done["status"] == "succeeded"
            and done["result"]["env_steps"] >= 1536
            and done["attempts"] == 1
        )
        rows = httpx.get(f"{live.url}/jobs/{job['id']}/metrics").json()["metrics"]
        assert len(rows) == 3 and rows[-1]["env_steps"] == done["result"]["env_steps"]
        names = {
            a["name"]
            for a in httpx.get(f"{live.url}/jobs/{job['id']}/artifacts").json()["artifacts"]
        }
        assert {
            "config.json",
            "metrics.jsonl",
            "learning_curve.png",
            "checkpoint/state.msgpack",
        } <= names
        ckpt = httpx.get(f"{live.url}/jobs/{job['id']}/artifacts/checkpoint/state.msgpack")
        assert ckpt.status_code == 200
        assert (
            ckpt.content
            == (
                live.settings.artifacts_dir / job["id"] / "checkpoint" / "state.msgpack"
            ).read_bytes()
        )
        png = httpx.get(f"{live.url}/jobs/{job['id']}/artifacts/learning_curve.png")
        assert png.content[:8] == b"\x89PNG\r\n\x1a\n"

        # split and env overrides reach the worker through the stored config (split once did not)
        body = {"job_id": job["id"], "episodes": 8, "split": "train", "env": {"max_steps": 30},
                "robustness": True, "shield": True}
        ev = httpx.post(f"{live.url}/jobs/eval", json=body)
        assert ev.status_code == 202, ev.text
        assert ev.json()["config"]["split"] == "train" and ev.json()["config"]["env"]["max_steps"] == 30
        assert ev.json()["config"]["env"]["grid_size"] == 8  # the train job's env underneath
        ev_done = wait_status(live.url, ev.json()["id"], {"succeeded", "failed"})
        assert ev_done["status"] == "succeeded", ev_done["error"]
        assert ev_done["result"]["metrics"]["episodes"] == 8
        names = {
            a["name"]
            for a in httpx.get(f"{live.url}/jobs/{ev.json()['id']}/artifacts").json()["artifacts"]
        }
        assert {"eval.json", "trajectories.png", "episodes.gif", "robustness.png"} <= names
        measured = httpx.get(f"{live.url}/jobs/{ev.json()['id']}/artifacts/eval.json").json()
        # the robustness option reached the worker: a row per level, on the same 8 episodes
        from quicknav_core.eval.robustness import LEVELS

        assert ev.json()["config"]["robustness"] is True
        # and the safety layer: the policy's commands went through it
        assert ev.json()["config"]["shield"] is True and measured["agent"].endswith("+shield")
        assert [r["label"] for r in measured["robustness"]] == [lv.label for lv in LEVELS]
        assert {r["episodes"] for r in measured["robustness"]} == {8}
        assert measured["eval_config"]["split"] == "train" and measured["env_config"]["max_steps"] == 30
        assert max(measured["per_episode"]["steps"]) <= 30
        # an env the policy cannot read (another observation length) is refused up front
        r = httpx.post(f"{live.url}/jobs/eval", json={"job_id": job["id"], "env": {"lidar_beams": 4}})
        assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "env"]
        assert "lidar_beams" in r.text
        listed = httpx.get(f"{live.url}/jobs", params={"kind": "eval"}).json()
        assert listed["count"] == 1 and listed["data"][0]["id"] == ev.json()["id"]
        listed = httpx.get(f"{live.url}/jobs", params={"status": "succeeded", "limit": 1}).json()
        assert listed["count"] == 2 and len(listed["data"]) == 1
        # finished jobs can be deleted, with their artifacts
        assert httpx.delete(f"{live.url}/jobs/{ev.json()['id']}").status_code == 204
        assert httpx.get(f"{live.url}/jobs/{ev.json()['id']}").status_code == 404
    finally:
        worker.shutdown.set()
        thread.join(30)


def test_cancel_queued_and_running_jobs(live):
    queued = submit_tiny(live.url)
    r = httpx.post(f"{live.url}/jobs/{queued['id']}/cancel", json={})
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert httpx.post(f"{live.url}/jobs/{queued['id']}/cancel", json={}).json()["status"] == "cancelled"
    running = submit_tiny(live.url, total_steps=512 * 40)
    worker, thread = live.run_worker_in_background()
    try:
        with httpx.stream("GET", f"{live.url}/jobs/{running['id']}/events", timeout=300) as stream:
            for line in stream.iter_lines():
                if line.startswith("event: progress"):
                    break
        r = httpx.post(f"{live.url}/jobs/{running['id']}/cancel", json={})
        assert r.json()["cancel_requested"]
        done = wait_status(live.url, running["id"], {"cancelled", "succeeded", "failed"})
        assert done["status"] == "cancelled" and done["worker"] == worker.id
        assert httpx.get(f"{live.url}/jobs/{queued['id']}").json()["worker"] is None
        assert done["result"]["chunks_done"] < 40, "stopped at a chunk boundary, not at the end"
        assert (
            live.settings.artifacts_dir / running["id"] / "checkpoint" / "state.msgpack"
        ).exists()
    finally:
        worker.shutdown.set()
        thread.join(30)


def test_idempotency_key(live):
    body = {"preset": "demo", "overrides": TINY}
    a = httpx.post(f"{live.url}/jobs/train", json=body, headers={"Idempotency-Key": "abc"})
    b = httpx.post(f"{live.url}/jobs/train", json=body, headers={"Idempotency-Key": "abc"})
    assert a.status_code == b.status_code == 202 and a.json()["id"] == b.json()["id"]
    c = httpx.post(
        f"{live.url}/jobs/train", json={"preset": "paper-ppo"}, headers={"Idempotency-Key": "abc"}
    )
    assert c.status_code == 409 and "abc" in c.json()["detail"]
    assert httpx.get(f"{live.url}/jobs").json()["count"] == 1


def test_bad_input_is_refused_with_named_fields(live):
    r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "env": {"grid_size": 2}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "env", "grid_size"]
    r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "env": {"gird_size": 8}})
    assert r.status_code == 422 and "unknown field 'gird_size'" in r.text
    r = httpx.post(f"{live.url}/jobs/sweep", json={"space": "ppo", "total_steps": 1})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "total_steps"]
    r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": {"algorithm.learning_rate": "NaN"}})
    assert r.status_code == 422 and "finite" in r.text
    r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "overrides": {"num_envs": 0}})
    assert r.status_code == 422 and "num_envs" in r.text
    r = httpx.post(
        f"{live.url}/jobs/train",
        json={"preset": "demo", "overrides": {"num_envs": 8192, "total_steps": 10**8}},
    )
    assert (
        r.status_code == 422
        and "max_envs=4096" in r.text
        and r.json()["detail"][0]["loc"][-1] == "num_envs"
    )
    r = httpx.post(f"{live.url}/jobs/train", json={"preset": "nope"})
    assert r.status_code == 422 and "unknown preset 'nope'" in r.text
    r = httpx.post(f"{live.url}/jobs/train", json={"preset": "demo", "colour": "red"})
    assert r.status_code == 422 and "colour" in r.text
    r = httpx.post(f"{live.url}/jobs/train", json={"config": {"env": {"grid_size": 2}}})
    assert r.status_code == 422 and "grid_size" in r.text
    r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 0})
    assert r.status_code == 422 and "episodes" in r.text
    # an offset beyond SQLite's 64-bit integers was a 500 (found by the fuzz test)
    r = httpx.get(f"{live.url}/jobs", params={"offset": 2**63})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "offset"]
    assert "2147483647" in r.text
    r = httpx.post(f"{live.url}/jobs/eval", json={"policy": "random", "episodes": 4})
    job = r.json()["id"]
    for bad in (str(2**63), "-1", "abc", "+5", "", "1_000"):  # ASCII digits only (the document's pattern)
        r = httpx.get(f"{live.url}/jobs/{job}/events", headers={"Last-Event-ID": bad})
        assert r.status_code == 400 and "Last-Event-ID" in r.text, (bad, r.text)
    r = httpx.post(f"{live.url}/jobs/eval", json={"job_id": "nope"})
    assert r.status_code == 404
    big = {"preset": "demo", "overrides": {"note": "x" * 2_000_000}}
    r = httpx.post(f"{live.url}/jobs/train", json=big)
    assert r.status_code == 413 and "exceeds the limit" in r.text
    # a chunked body (no Content-Length) is counted as it arrives
    chunks = (json.dumps(big)[i : i + 65536].encode() for i in range(0, 2_000_100, 65536))
    r = httpx.post(f"{live.url}/jobs/train", content=chunks,
                   headers={"Content-Type": "application/json"})  # fmt: skip
    assert r.status_code == 413 and "exceeds the limit" in r.text


def test_artifacts__a_file_rewritten_while_the_job_runs_is_served_anew_never_from_a_cache(live):
    """A running job rewrites its files under the same name (a sweep's trials.json): every answer
    says ``Cache-Control: no-cache``, so a browser asks again instead of keeping a copy it thinks
    fresh (Chromium did, from Last-Modified alone, and a finished sweep's page kept its running
    trials), and gets the file as it is now."""
    job = submit_tiny(live.url)
    folder = live.settings.artifacts_dir / job["id"]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "trials.json").write_text('{"trials": [{"number": 0, "state": "RUNNING"}]}')
    url = f"{live.url}/jobs/{job['id']}/artifacts/trials.json"
    first = httpx.get(url)
    assert first.status_code == 200 and first.headers["cache-control"] == "no-cache"
    (folder / "trials.json").write_text('{"trials": [{"number": 0, "state": "COMPLETE", "value": 0.5}]}')
    again = httpx.get(url, headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 200 and again.headers["cache-control"] == "no-cache"
    assert again.json()["trials"][0]["state"] == "COMPLETE"


def test_artifact_names_cannot_escape_the_job_folder(live):
    job = submit_tiny(live.url)
    (live.settings.artifacts_dir / job["id"]).mkdir(parents=True, exist_ok=True)
    for name in ("%2e%2e/jobs.db", "..%2f..%2fjobs.db", "%2e%2e%2f%2e%2e%2fjobs.db"):
        r = httpx.get(f"{live.url}/jobs/{job['id']}/artifacts/{name}")
        assert r.status_code in (400, 404), (name, r.status_code)
        assert b"SQLite" not in r.content


def test_auth_token_required_on_job_endpoints(tmp_path):
    with LiveServer(tmp_path, api_token="s3cret-token") as live:
        assert httpx.get(f"{live.url}/jobs").status_code == 401
        assert (
            httpx.get(
                f"{live.url}/jobs", headers={"Authorization": "Bearer wrong-token"}
            ).status_code
            == 401
        )
        ok = httpx.get(f"{live.url}/jobs", headers={"Authorization": "Bearer s3cret-token"})
        assert ok.status_code == 200
        assert httpx.get(f"{live.url}/healthz").status_code == 200
        assert httpx.get(f"{live.url}/readyz").status_code == 200
        assert httpx.post(f"{live.url}/jobs/train", json={"preset": "demo"}).status_code == 401


def test_prometheus_metrics_and_presets(live):
    submit_tiny(live.url)
    text = httpx.get(f"{live.url}/metrics").text
    assert 'quicknav_jobs{status="queued"} 1' in text and "quicknav_queue_depth 1" in text
    presets = httpx.get(f"{live.url}/presets").json()
    assert "demo" in presets and "paper-lstm" in presets


def test_events__non_finite_metrics_travel_as_null(live):
    job, _ = live.store.submit("eval", {"policy": "random", "episodes": 1, "seed": 0}, {})
    live.store.publish(job.id, {"type": "progress", "metrics": {"return": float("nan"), "n": 1}})
    with httpx.stream("GET", f"{live.url}/jobs/{job.id}/events", timeout=10) as r:
        lines = []
        for line in r.iter_lines():
            lines.append(line)
            if line.startswith("data:") and "progress" in line:
                live.store.cancel(job.id)  # a queued job is cancelled at once: the stream ends
    text = "\n".join(lines)
    assert "NaN" not in text
    data = [json.loads(x.removeprefix("data:")) for x in lines if x.startswith("data:")]
    assert data[0]["metrics"] == {"return": None, "n": 1}
    assert data[-1]["type"] == "cancelled"


def test_sweep_trial_limit_names_the_field_the_client_sent(live):
    limit = live.settings.max_sweep_trials
    r = httpx.post(f"{live.url}/jobs/sweep", json={"space": "ppo", "trials": limit + 1})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "trials"] and "max_sweep_trials" in r.text
    from quicknav_core.config import resolve_sweep

    cfg = resolve_sweep({"space": "ppo", "trials": limit + 1}).model_dump(mode="json")
    r = httpx.post(f"{live.url}/jobs/sweep", json={"config": cfg})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "config", "trials"]
