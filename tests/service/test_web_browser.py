"""The browser view in a real browser: headless Chromium (Debian's `chromium` package, driven by
Playwright) against a live `quicknav serve` with a token set. It signs in, submits a demo job
through the form, watches the curve grow and the job succeed, replays the policy, sees a validation
error next to its field, follows a sweep, and cancels and deletes from the jobs page.

Screenshots go to $QUICKNAV_SCREENSHOTS (or a pytest temporary folder); the test prints where.
Never skipped: without Chromium it fails and says how to install it."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import free_port, quicknav_process, wait_until_up

TOKEN = "browser-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
JOB_TIMEOUT_MS = 240_000  # a CI machine with 2 busy cores compiles slowly


def chromium_path() -> str:
    for candidate in (os.environ.get("QUICKNAV_CHROMIUM"), "chromium", "chromium-browser",
                      "google-chrome"):  # fmt: skip
        if candidate and (found := shutil.which(candidate)):
            return found
    pytest.fail("no Chromium found: install Debian's package (`apt-get install chromium`) or set"
                " QUICKNAV_CHROMIUM to a Chromium/Chrome executable; .ci/run installs it")  # fmt: skip


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("web-data")
    port = free_port()
    proc = quicknav_process(["serve", "--port", str(port), "--no-grpc"], QUICKNAV_DATA_DIR=str(data),
                            QUICKNAV_API_TOKEN=TOKEN)  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        wait_until_up(url, proc)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except Exception:
            proc.kill()


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    folder = Path(os.environ.get("QUICKNAV_SCREENSHOTS") or tmp_path_factory.mktemp("screenshots"))
    folder.mkdir(parents=True, exist_ok=True)
    print(f"\nscreenshots: {folder}")
    return folder


@pytest.fixture(scope="module")
def page(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), args=["--no-sandbox"])
        context = browser.new_context(viewport={"width": 1300, "height": 900})
        pg = context.new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.errors = errors
        yield pg
        browser.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def test_browser__asks_for_the_token_and_signs_in(server, page, shots):
    page.goto(server + "/")
    page.wait_for_selector("#login")
    assert "QUICKNAV_API_TOKEN" in page.inner_text("#login")
    page.fill("input[name=token]", "wrong-token-123")
    page.click("#login button[type=submit]")
    page.wait_for_selector("#login .error-box")
    assert "not the server's token" in page.inner_text("#login .error-box")
    page.screenshot(path=shots / "sign-in.png")
    page.fill("input[name=token]", TOKEN)
    page.click("#login button[type=submit]")
    page.wait_for_selector("#jobs")
    assert "No jobs yet" in page.inner_text("#jobs")


def test_browser__form_shows_the_servers_error_next_to_the_field(server, page, shots):
    page.goto(server + "/ui/submit")
    page.wait_for_selector("#submit-form")
    page.fill("#f-env\\.grid_size", "200")
    page.click("#submit")
    field = page.locator('.field[data-key="env.grid_size"]')
    field.locator(".field-error").wait_for()
    assert "128" in field.locator(".field-error").inner_text()  # the allowed range, from the server
    assert "invalid" in field.get_attribute("class")
    page.screenshot(path=shots / "form-error.png", full_page=True)
    # an unknown key in the free-form box is reported there
    page.fill("#f-env\\.grid_size", "")
    page.fill("#f-overrides", "env.no_such_field=3")
    page.click("#submit")
    box = page.locator('.field[data-key="overrides"] .field-error')
    box.wait_for()
    assert "no_such_field" in box.inner_text()
    assert page.url.endswith("/ui/submit")  # nothing was submitted
    jobs = httpx.get(server + "/jobs", headers=AUTH).json()
    assert jobs["count"] == 0


def test_browser__submitted_job_grows_its_curve_and_succeeds(server, page, shots):
    page.goto(server + "/ui/submit")
    page.wait_for_selector("#submit-form")
    page.select_option("#preset", "demo")
    page.fill("#f-total_steps", "800000")
    page.fill("#f-env\\.grid_size", "")
    page.fill("#f-overrides", "chunk_steps=16384")
    page.click("#submit")
    page.wait_for_url("**/ui/jobs/*", timeout=20_000)
    job_id = page.url.rsplit("/", 1)[-1]
    job = httpx.get(f"{server}/jobs/{job_id}", headers=AUTH).json()
    assert job["config"]["total_steps"] == 800000 and job["config"]["chunk_steps"] == 16384

    # watch the curve while the job runs: the number of points it draws, as the page says
    seen: list[tuple[str, int]] = []
    deadline = time.time() + JOB_TIMEOUT_MS / 1000
    while time.time() < deadline:
        status = page.get_attribute("#job-head .badge", "data-status")
        points = int(page.get_attribute("#curve .chart", "data-points"))
        seen.append((status, points))
        if status in ("succeeded", "failed", "cancelled"):
            break
        if status == "running" and points and len({p for s, p in seen if s == "running"}) == 2:
            page.screenshot(path=shots / "job-running.png", full_page=True)
        time.sleep(0.3)
    assert seen[-1][0] == "succeeded", seen[-1]
    running = sorted({p for s, p in seen if s == "running" and p > 0})
    assert len(running) >= 2, f"the curve did not gain points while the job ran: {seen}"
    final = int(page.get_attribute("#curve .chart", "data-points"))
    assert final >= running[-1]
    # the learning-curve picture opens with the session cookie (an <img> sends no header)
    img = page.locator('#images img[alt="learning_curve.png"]')
    img.wait_for(timeout=20_000)
    page.wait_for_function(
        "document.querySelector('#images img[alt=\"learning_curve.png\"]').naturalWidth > 100"
    )
    page.locator("#events").get_by_text("succeeded").first.wait_for()
    page.screenshot(path=shots / "job-succeeded.png", full_page=True)
    page.job_id = job_id


def test_browser__replay_of_the_trained_policy_advances_frames(server, page, shots):
    page.goto(f"{server}/ui/jobs/{page.job_id}")
    page.click("#replay-link")
    page.wait_for_selector("#new-replay")
    page.click("#new-replay")
    canvas = page.locator("#replay-canvas")
    canvas.wait_for(timeout=JOB_TIMEOUT_MS)
    first = int(canvas.get_attribute("data-step"))
    page.wait_for_timeout(800)
    later = int(canvas.get_attribute("data-step"))
    assert later != first, "the replay does not advance"
    page.screenshot(path=shots / "replay.png", full_page=True)
    page.click("#play")  # pause: the frame stays
    paused = int(canvas.get_attribute("data-step"))
    page.wait_for_timeout(500)
    assert int(canvas.get_attribute("data-step")) == paused
    page.locator("#step-slider").fill("5")
    assert int(canvas.get_attribute("data-step")) == 5 and "step 5 /" in page.inner_text("#step-label")
    # the episodes come from the eval job the page started, on the held-out bank
    evals = httpx.get(server + "/jobs?kind=eval", headers=AUTH).json()["data"]
    assert [e["config"]["source"] for e in evals] == [page.job_id]
    assert evals[0]["config"]["split"] == "test" and evals[0]["status"] == "succeeded"


def test_browser__jobs_page_updates_live_cancels_deletes_and_shows_a_sweep(server, page, shots):
    page.goto(server + "/")
    page.wait_for_selector("#jobs tbody tr[data-id]")
    sweep = httpx.post(server + "/jobs/sweep", headers=AUTH, json={
        "space": "ppo", "trials": 2, "total_steps": 131072,
        "overrides": {"base.num_envs": 64, "parallel": 1}}).json()  # fmt: skip
    long = httpx.post(server + "/jobs/train", headers=AUTH,
                      json={"preset": "demo", "overrides": {"total_steps": 5_000_000}}).json()  # fmt: skip
    # both rows appear without a reload
    row = page.locator(f'#jobs tr[data-id="{long["id"]}"]')
    row.wait_for(timeout=10_000)
    page.locator(f'#jobs tr[data-id="{sweep["id"]}"]').wait_for(timeout=10_000)
    row.get_by_role("button", name="Cancel").click()
    page.wait_for_selector(f'#jobs tr[data-id="{long["id"]}"][data-status="cancelled"]', timeout=60_000)
    page.screenshot(path=shots / "jobs.png", full_page=True)
    page.once("dialog", lambda d: d.accept())
    page.locator(f'#jobs tr[data-id="{long["id"]}"]').get_by_role("button", name="Delete").click()
    page.wait_for_selector(f'#jobs tr[data-id="{long["id"]}"]', state="detached", timeout=10_000)
    assert httpx.get(f"{server}/jobs/{long['id']}", headers=AUTH).status_code == 404

    # the sweep's page: trials table, best trial and the history plot fill in as trials finish
    page.goto(f"{server}/ui/jobs/{sweep['id']}")
    page.wait_for_selector('#job-head .badge[data-status="succeeded"]', timeout=JOB_TIMEOUT_MS)
    page.wait_for_function("document.querySelectorAll('#trials tbody tr').length === 2")
    page.wait_for_function("document.querySelector('.chart').dataset.points === '2'")
    assert page.locator("#trials tr.best").count() == 1
    trials = httpx.get(f"{server}/jobs/{sweep['id']}/artifacts/trials.json", headers=AUTH).json()
    best = max(trials["trials"], key=lambda t: t["value"])
    assert page.inner_text("#trials tr.best td").strip() == str(best["number"])
    assert page.inner_text("#best-trial").startswith(f"Trial {best['number']}: success_rate")
    page.locator('#images img[alt="optimization_history.png"]').wait_for(timeout=20_000)
    page.screenshot(path=shots / "sweep.png", full_page=True)
