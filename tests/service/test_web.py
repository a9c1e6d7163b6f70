"""The browser view over HTTP: its page and files are served offline, and with a token set a browser
session (cookie) reads jobs and artifacts but nothing is readable without it."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from quicknav_service.api.deps import SESSION_COOKIE, WEB_HEADER
from quicknav_service.api.main import create_app
from quicknav_service.jobs.models import JobKind
from quicknav_service.settings import Settings

TOKEN = "web-test-token-1"


@pytest.fixture
def open_client(tmp_path):
    return TestClient(create_app(Settings(_env_file=None, data_dir=tmp_path), start_workers=False))


@pytest.fixture
def locked(tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path, api_token=TOKEN)
    app = create_app(settings, start_workers=False)
    return TestClient(app), app.state.store, settings


def test_web__page_and_every_file_it_loads_come_from_the_server(open_client):
    page = open_client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", page.text)
    external = [r for r in refs if re.match(r"(https?:)?//", r)]
    assert not external, f"the page loads from elsewhere: {external}"
    assets = [r for r in refs if r.startswith("/web/static/")]
    assert {"/web/static/app.js", "/web/static/vendor/uplot/uPlot.iife.min.js"} <= set(assets)
    for ref in assets:
        assert open_client.get(ref).status_code == 200, ref
    script = open_client.get("/web/static/app.js").text
    assert not re.findall(r"""["'`](https?:)?//""", script), "app.js fetches from another origin"
    # every view of the page is the same shell, routed in the browser
    for path in ("/ui/jobs/abc", "/ui/jobs/abc/replay", "/ui/submit", "/ui/replay"):
        r = open_client.get(path)
        assert r.status_code == 200 and r.text == page.text, path


def test_web__without_a_token_the_session_says_none_is_needed(open_client):
    assert open_client.get("/auth/session").json() == {"token_required": False, "authenticated": True}
    assert open_client.get("/jobs").status_code == 200


def test_web__session_cookie_reads_jobs_and_artifacts_only_with_the_right_token(locked):
    client, store, settings = locked
    job, _ = store.submit(JobKind.train, {"preset": "demo"}, {"total_steps": 1})
    folder = settings.artifacts_dir / job.id
    folder.mkdir(parents=True)
    (folder / "learning_curve.png").write_bytes(b"\x89PNG\r\n\x1a\nfake")

    # nothing is readable without the token: the list, a job, its picture, its events
    for path in ("/jobs", f"/jobs/{job.id}", f"/jobs/{job.id}/artifacts/learning_curve.png",
                 f"/jobs/{job.id}/events", "/presets"):  # fmt: skip
        assert client.get(path).status_code == 401, path
    assert client.get("/auth/session").json() == {"token_required": True, "authenticated": False}

    wrong = client.post("/auth/session", json={"token": "not-the-token"})
    assert wrong.status_code == 401 and "token" in wrong.json()["detail"]
    assert SESSION_COOKIE not in client.cookies
    empty = client.post("/auth/session", json={"token": ""})
    assert empty.status_code == 422 and empty.json()["detail"][0]["loc"] == ["body", "token"]

    ok = client.post("/auth/session", json={"token": TOKEN})
    assert ok.status_code == 200 and ok.json()["authenticated"] is True
    cookie = ok.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie.replace("Strict", "strict")
    assert TOKEN not in cookie  # the cookie holds a digest, not the token
    # an <img> sends no Authorization header: the cookie alone opens the picture
    img = client.get(f"/jobs/{job.id}/artifacts/learning_curve.png")
    assert img.status_code == 200 and img.content.startswith(b"\x89PNG")
    assert client.get("/jobs").json()["count"] == 1
    assert client.get("/auth/session").json()["authenticated"] is True

    # a change made with the cookie alone needs the page's header (a cross-site form cannot set it)
    bare = client.post(f"/jobs/{job.id}/cancel", json={})
    assert bare.status_code == 403 and WEB_HEADER in bare.json()["detail"]
    assert store.get(job.id).status.value == "queued"
    done = client.post(f"/jobs/{job.id}/cancel", headers={WEB_HEADER: "1"})
    assert done.status_code == 200 and done.json()["status"] == "cancelled"

    # a forged cookie opens nothing; signing out forgets the session
    forged = TestClient(client.app, cookies={SESSION_COOKIE: "0" * 64})
    assert forged.get("/jobs").status_code == 401
    assert client.delete("/auth/session").status_code == 204
    assert client.get("/jobs").status_code == 401
    # the API's own header keeps working beside the browser session
    assert client.get("/jobs", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200


def test_web__presets_carry_the_whole_resolved_config_for_the_form(open_client):
    presets = open_client.get("/presets").json()
    demo = presets["demo"]
    assert demo["config"]["total_steps"] == demo["resolved"]["total_steps"]
    # fields the preset leaves at their defaults are filled in
    assert demo["resolved"]["env"]["grid_size"] == 16 and "grid_size" not in demo["config"]["env"]
