"""The browser view in a real browser: headless Chromium (Debian's `chromium` package, driven by
Playwright) against a live `quicknav serve` with a token set. It signs in, sees every validation
error of a form at once, submits the demo preset through the form, watches the curve grow and the
job succeed, and from that job's page runs an eval, reads its metrics table (held-out success
>= 0.9: a policy that learned) and plays its replay; it follows a sweep, sees a failed job's reason,
and cancels and deletes from the jobs page. The policy that learned is the test run's one trained
demo (``tests/trained.py``), put into this server's store as a succeeded train job.

Screenshots go to $QUICKNAV_SCREENSHOTS (or a pytest temporary folder); the test prints where.
Never skipped: without Chromium it fails and says how to install it."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import httpx
import numpy as np
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
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("web-data")


@pytest.fixture(scope="module")
def server(request, data_dir):
    port = free_port()
    # the workers do not export trained policies (the test run's default, conftest.py): the job
    # page's policy download is the seeded trained demo's, exported once per test run.
    # This module's jobs are short (a few chunks, two tiny trials, evaluations), so its worker
    # compiles as the test run does (tests/compile_settings.py; the module's child CPU 72.6 ->
    # 61.3 s, 2-core Intel Xeon VM); a module whose worker trains to a target
    # (test_web_maps_browser.py) sets SERVER_AS_A_USER and compiles as a user's machine does
    as_a_user = getattr(request.module, "SERVER_AS_A_USER", False)
    proc = quicknav_process(["serve", "--port", str(port), "--no-grpc"], as_a_user=as_a_user,
                            QUICKNAV_DATA_DIR=str(data_dir), QUICKNAV_API_TOKEN=TOKEN)  # fmt: skip
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
def demo(server, data_dir):
    """The module's trained demo job, seeded from the test run's trained demo when a test first
    needs it (the first tests see an empty server)."""
    return {"data_dir": data_dir}


def wait_for_job(server: str, job_id: str, timeout_s: float = JOB_TIMEOUT_MS / 1000) -> dict:
    deadline = time.time() + timeout_s
    while True:
        job = httpx.get(f"{server}/jobs/{job_id}", headers=AUTH).json()
        if job["status"] in ("succeeded", "failed", "cancelled") or time.time() > deadline:
            return job
        time.sleep(1)


def trained_demo(server: str, demo: dict) -> str:
    """The id of a succeeded demo train job whose policy learned: the test run's trained demo
    (``tests/trained.py``), put into this server's store and artifacts."""
    if "id" not in demo:
        from quicknav_service.jobs.sqlite_store import SQLiteJobStore
        from tests.trained import seed_trained_job
        from tests.trained import trained_demo as trained_run

        store = SQLiteJobStore(demo["data_dir"] / "jobs.db")
        try:
            demo["id"] = seed_trained_job(store, demo["data_dir"] / "artifacts", trained_run())
        finally:
            store.close()
        assert wait_for_job(server, demo["id"], 10)["status"] == "succeeded"
    return demo["id"]


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
    # the table is drawn before the first list arrives: wait for what the list says
    page.locator("#jobs").get_by_text("No jobs yet").wait_for(timeout=10_000)


def test_browser__form_shows_the_servers_error_next_to_the_field(server, page, shots):
    page.goto(server + "/ui/submit")
    page.wait_for_selector("#submit-form")
    page.fill("#f-env\\.grid_size", "300")
    page.click("#submit")
    field = page.locator('.field[data-key="env.grid_size"]')
    field.locator(".field-error").wait_for()
    assert "256" in field.locator(".field-error").inner_text()  # the allowed range, from the server
    assert "invalid" in field.get_attribute("class")
    # an unknown key in the free-form box is reported there
    page.fill("#f-env\\.grid_size", "")
    page.fill("#f-overrides", "env.no_such_field=3")
    page.click("#submit")
    box = page.locator('.field[data-key="overrides"] .field-error')
    box.wait_for()
    assert "no_such_field" in box.inner_text()
    assert page.url.endswith("/ui/submit")  # nothing was submitted


def test_browser__form_shows_every_field_error_at_once(server, page, shots):
    page.goto(server + "/ui/submit")
    page.wait_for_selector("#submit-form")
    page.fill("#f-env\\.grid_size", "1000")
    page.fill("#f-total_steps", "-5")
    page.fill("#f-overrides", "env.no_such_field=3\nalgorithm.learning_rate 0.1\nseed")
    page.click("#submit")
    # two lines without '=' are caught in the page, both at once, and nothing is sent
    box = page.locator('.field[data-key="overrides"] .field-error')
    box.wait_for()
    assert "line 2" in box.inner_text() and "line 3" in box.inner_text()
    assert "key=value" in box.inner_text()
    page.fill("#f-overrides", "env.no_such_field=3")
    page.click("#submit")
    page.locator('.field[data-key="total_steps"] .field-error').wait_for()
    errors = {key: page.locator(f'.field[data-key="{key}"] .field-error').inner_text()
              for key in ("env.grid_size", "total_steps", "overrides")}  # fmt: skip
    page.screenshot(path=shots / "form-errors.png", full_page=True)
    assert "256" in errors["env.grid_size"], errors  # each with its allowed range
    assert "1" in errors["total_steps"] and "greater" in errors["total_steps"], errors
    assert "no_such_field" in errors["overrides"], errors
    assert page.url.endswith("/ui/submit")
    jobs = httpx.get(server + "/jobs", headers=AUTH).json()
    assert jobs["count"] == 0


def test_browser__submitted_job_grows_its_curve_and_succeeds(server, page, shots):
    page.goto(server + "/ui/submit")
    page.wait_for_selector("#submit-form")
    page.select_option("#preset", "demo")
    # four chunks of the demo preset, each long enough (24 updates, two seconds or more) for the
    # page to draw it while it watches (the policy that learned, for the tests after this one, is
    # the test run's trained demo)
    steps = 4 * 98_304
    page.fill("#f-total_steps", str(steps))
    page.fill("#f-env\\.grid_size", "")
    page.fill("#f-overrides", "chunk_steps=98304")
    page.click("#submit")
    page.wait_for_url("**/ui/jobs/*", timeout=20_000)
    job_id = page.url.rsplit("/", 1)[-1]
    job = httpx.get(f"{server}/jobs/{job_id}", headers=AUTH).json()
    assert job["config"]["total_steps"] == steps and job["config"]["chunk_steps"] == 98_304
    assert job["request"]["preset"] == "demo"

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
    # long event lines (the result with its note) wrap inside the log instead of running past it
    widths = page.eval_on_selector("#events", "e => [e.scrollWidth, e.clientWidth]")
    assert widths[0] <= widths[1], widths
    page.screenshot(path=shots / "job-succeeded.png", full_page=True)


def test_browser__replay_of_the_trained_policy_advances_frames(server, page, shots, demo):
    job_id = trained_demo(server, demo)
    page.goto(f"{server}/ui/jobs/{job_id}")
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
    assert [e["config"]["source"] for e in evals] == [job_id]
    assert evals[0]["config"]["split"] == "test" and evals[0]["status"] == "succeeded"
    # the replay page is Replay in the navigation, and only it
    assert page.locator("header nav a.active").all_inner_texts() == ["Replay"]


def in_a_player(server: str, page, episode: dict, room_size: float, script: str):
    """Play one written episode in the replay's player (the page's own ``player``, paused, in an
    element of its own) and return what ``script`` returns. The script's body sees ``data``,
    ``into``, ``canvas``, ``slider``, ``show(t)`` (go to step t) and ``at(x, y)`` (the canvas's
    RGB at a point of the room, metres, through the canvas's ``data-view``)."""
    data = {"agent": "test", "room_size": room_size, "grid_size": len(episode["walls"]),
            "robot_radius": 0.15, "goal_radius": 0.3, "dt": 0.1, "beam_angles": [],
            "hit_codes": {"none": 0, "wall": 1, "goal": 2}, "episodes": [episode]}  # fmt: skip
    page.goto(server + "/ui/")
    return page.evaluate("""(data) => {
      const into = document.createElement("div");
      document.body.append(into);
      player(data, into);
      into.querySelector("#play").click();  // pause
      const slider = into.querySelector("#step-slider"), canvas = into.querySelector("canvas");
      const show = (t) => { slider.value = String(t); slider.dispatchEvent(new Event("input")); };
      const at = (x, y) => {
        const [x0, y0, w] = canvas.dataset.view.split(",").map(Number), s = canvas.width / w;
        return Array.from(canvas.getContext("2d").getImageData(
          Math.floor((x - x0) * s), Math.floor(canvas.height - (y - y0) * s), 1, 1).data).slice(0, 3);
      };
      const out = (() => {""" + script + """})();
      into.remove();
      return out;
    }""", data)  # fmt: skip


def test_browser__replay_draws_the_plan_boxes_and_people_where_they_are(server, page, shots):
    """The replay's canvas draws an episode's global plan (dashed) and the obstacles the map does
    not show (``replay.json``'s ``plan``, ``boxes`` and ``people``; tests/core/eval/
    test_replay_unmapped.py holds them to the env) where they are at the step shown, in the GIFs'
    colours, and its legend names them. The episode is written here: the test run's trained demo
    observes no plan and meets no obstacles."""
    walls = ["########"] + ["#......#"] * 6 + ["########"]
    episode = {"index": 0, "success": True, "steps": 1, "return": 1.0, "walls": walls,
               "goal": [3.1, 3.1], "x": [0.9, 0.95], "y": [3.1, 3.1], "theta": [0.0, 0.0],
               "ranges": [[], []], "hits": [[], []],
               "plan": [[0.75, 0.75], [3.25, 0.75], [3.25, 3.1]], "boxes": [[1.5, 2.0, 0.25]],
               "people": [{"radius": 0.25, "x": [2.5, 2.5], "y": [2.0, 2.6]}]}  # fmt: skip
    seen = in_a_player(server, page, episode, 4.0, """
      show(0);
      const first = {box: at(1.5, 2.0), person: at(2.5, 2.0), plan: [1, 1.5, 2, 2.5, 3].map((x) => at(x, 0.75)),
                     dataset: {...canvas.dataset}};
      show(1);
      const second = {person: at(2.5, 2.6), left: at(2.5, 2.0)};
      const legend = Array.from(into.querySelectorAll(".legend span")).map((s) => s.textContent);
      return {first, second, legend};""")  # fmt: skip
    near = lambda rgb, hex_: sum(abs(a - int(hex_[i : i + 2], 16)) for a, i in zip(rgb, (1, 3, 5), strict=True)) < 60  # noqa: E731
    assert near(seen["first"]["box"], "#8c564b"), seen
    assert near(seen["first"]["person"], "#9467bd"), seen
    assert any(near(c, "#17becf") for c in seen["first"]["plan"]), seen  # dashed: some points on a dash
    assert seen["first"]["dataset"]["plan"] == "3" and seen["first"]["dataset"]["boxes"] == "1"
    assert seen["first"]["dataset"]["people"] == "1"
    # at step 1 the person has walked on: drawn where it is, gone from where it was
    assert near(seen["second"]["person"], "#9467bd") and not near(seen["second"]["left"], "#9467bd"), seen
    assert {"global plan", "box (not on the map)", "person walking"} <= set(seen["legend"]), seen["legend"]


def test_browser__a_wide_maps_replay_canvas_takes_the_maps_shape(server, page):
    """A map's replay canvas shows the map's own extent in its own shape (520 px along its longer
    side; more for a long narrow map, whose short side keeps 200 px), as the GIFs do (``render.map_view``; the slow maps browser test holds the two equal on
    an uploaded map): a map 4 m wide and 2 m high in an 8-cell grid of 0.5 m cells."""
    from quicknav_core.env.render import map_view

    walls = ["########", "#......#", "#......#"] + ["########"] * 5  # row 0 at the bottom
    episode = {"index": 0, "success": True, "steps": 1, "return": 1.0, "walls": walls, "map": "wide",
               "goal": [3.0, 0.75], "x": [0.75, 0.8], "y": [0.75, 0.75], "theta": [0.0, 0.0],
               "ranges": [[], []], "hits": [[], []]}  # fmt: skip
    assert map_view(np.array([[c == "#" for c in row] for row in walls]), 4.0) == (0.0, 4.0, 0.0, 2.0)
    seen = in_a_player(server, page, episode, 4.0, """
      return {size: [canvas.width, canvas.height], view: canvas.dataset.view,
              floor: at(2.0, 1.2), wall: at(2.0, 1.8)};""")  # fmt: skip
    assert seen["size"] == [520, 260] and seen["view"] == "0,0,4,2", seen
    assert seen["floor"] == [244, 241, 234] and seen["wall"] == [59, 59, 59], seen
    # a corridor 1 m wide and 6 m long (2 m x 7 m with its wall ring): the longer side grows so the
    # short one keeps 200 px (at most twice 520): 100 px a metre, 200 x 700, not 149 x 520
    tall = ["################"] + ["#..#############"] * 12 + ["################"] * 3
    corridor = {**episode, "walls": tall, "goal": [0.75, 5.5], "x": [0.75, 0.75], "y": [0.75, 0.8]}
    assert map_view(np.array([[c == "#" for c in row] for row in tall]), 8.0) == (0.0, 2.0, 0.0, 7.0)
    seen = in_a_player(server, page, corridor, 8.0, """
      return {size: [canvas.width, canvas.height], view: canvas.dataset.view, floor: at(0.75, 3.0)};""")
    assert seen["size"] == [200, 700] and seen["view"] == "0,0,2,7", seen
    assert seen["floor"] == [244, 241, 234], seen


def success_in_table(page) -> float:
    """The success rate the eval page's metrics table shows, as a fraction."""
    row = page.locator("#eval-metrics tr", has_text="Success rate").locator("td").inner_text()
    return float(row.split("%")[0]) / 100


def test_browser__replay_words_name_an_uploaded_map_by_its_name(server, page):
    """Where a replay's episodes were, and how each ended, in words (``evalWhere``): an uploaded map by the name it was
    given (``mapNames`` asks the API), a map file by its file name, a room bank by its split; a
    map the API no longer knows keeps its reference."""
    page.goto(server + "/ui/")
    words = page.evaluate("""async () => {
      const job = (maps, split, request) => ({ request: request || {}, config: { split, env: { rooms: "maps", maps } } });
      const gone = job({ train: ["map:0123456789abcdef"] }, "test");
      return [
        evalWhere(job({ train: ["map:aaaa"] }, "test"), { "map:aaaa": "test room" }),
        evalWhere(job({ train: ["/x/office.yaml", "map:aaaa"], test: ["map:bbbb"] }, "test"), { "map:bbbb": "annex" }),
        evalWhere(job({ train: ["/x/office.yaml", "map:aaaa"] }, "test"), { "map:aaaa": "test room" }),
        evalWhere(job({ train: ["map:aaaa"] }, "test", { map: "map:cccc" }), { "map:cccc": "depot" }),
        evalWhere({ request: {}, config: { split: "test", env: { rooms: "floorplan" } } }),
        evalWhere(gone, await mapNames(gone)),
      ];
    }""")  # fmt: skip
    assert words == ['map "test room"', 'map "annex"', '2 maps (office.yaml, "test room")', 'the map "depot"',
                     "held-out test rooms", "map map:0123456789abcdef"], words  # fmt: skip
    # how each episode ended, in the pictures' words (replay.json's outcome; an older file's
    # episodes say reached or not)
    ends = page.evaluate("""() => [
      episodeEnd({ outcome: "reached", success: true, steps: 40 }),
      episodeEnd({ outcome: "collided", success: false, steps: 42 }),
      episodeEnd({ outcome: "timed out", success: false, steps: 600 }),
      episodeEnd({ success: false, steps: 7 }),
    ]""")  # fmt: skip
    assert ends == ["reached the goal in 40 steps", "collided after 42 steps", "timed out after 600 steps",
                    "failed after 7 steps"], ends  # fmt: skip


def test_browser__journey_from_the_trained_job_runs_an_eval_reads_its_metrics_and_replays(
    server, page, shots, demo, data_dir
):
    job_id = trained_demo(server, demo)
    page.goto(f"{server}/ui/jobs/{job_id}")
    page.wait_for_selector("#run-eval")
    assert page.locator("header nav a.active").all_inner_texts() == ["Jobs"]
    # the trained policy is offered as a download, and what the link gives is the job's file
    link = page.locator('#policy-download a[download="policy.onnx"]')
    link.wait_for(timeout=20_000)
    with page.expect_download() as download:
        link.click()
    served = httpx.get(f"{server}/jobs/{job_id}/artifacts/policy.onnx", headers=AUTH).content
    assert Path(download.value.path()).read_bytes() == served and len(served) > 1000
    assert page.locator('#policy-download a[download="policy.json"]').count() == 1
    # the replay test's eval is already listed, linked to its page
    first_eval = page.locator("#evals tbody tr[data-id]").first
    first_eval.wait_for()
    earlier = first_eval.get_attribute("data-id")
    assert first_eval.locator("a").get_attribute("href") == f"/ui/jobs/{earlier}"
    page.fill("#eval-episodes", "100")
    page.click("#run-eval")
    page.wait_for_url(lambda url: "/ui/jobs/" in url and job_id not in url, timeout=20_000)
    eval_id = page.url.rsplit("/", 1)[-1]
    page.wait_for_selector('#job-head .badge[data-status="succeeded"]', timeout=JOB_TIMEOUT_MS)
    page.wait_for_selector("#eval-metrics")
    job = httpx.get(f"{server}/jobs/{eval_id}", headers=AUTH).json()
    assert job["config"]["source"] == job_id and job["config"]["episodes"] == 100
    assert job["warnings"] == [], job["warnings"]  # every picture rendered
    assert page.locator("#job-warnings").count() == 0
    shown = success_in_table(page)
    assert shown == pytest.approx(job["result"]["metrics"]["success_rate"], abs=0.0005)
    assert shown >= 0.9, f"the demo policy did not learn: held-out success {shown}"
    clean = page.locator("#eval-metrics tr", has_text="Success without a collision").locator("td")
    assert clean.inner_text() == f"{100 * job['result']['metrics']['collision_free_success_rate']:.1f} %"
    assert page.get_attribute("#source-job", "href") == f"/ui/jobs/{job_id}"
    page.locator('#images img[alt="trajectories.png"]').wait_for(timeout=20_000)
    page.screenshot(path=shots / "eval.png", full_page=True)

    page.click("#replay-link")
    canvas = page.locator("#replay-canvas")
    canvas.wait_for(timeout=20_000)
    first = int(canvas.get_attribute("data-step"))
    page.wait_for_timeout(800)
    assert int(canvas.get_attribute("data-step")) != first, "the replay does not advance"
    page.screenshot(path=shots / "eval-replay.png", full_page=True)

    # the train job lists both evals, newest first, each linked
    page.goto(f"{server}/ui/jobs/{job_id}")
    page.wait_for_selector(f'#evals tr[data-id="{eval_id}"]')
    assert page.locator("#evals tbody tr[data-id]").evaluate_all(
        "rows => rows.map(r => r.dataset.id)") == [eval_id, earlier]  # fmt: skip
    page.screenshot(path=shots / "job-evals.png", full_page=True)
    # the train job's replay plays the newest eval that wrote a replay: this one, and the earlier
    # one once this one's replay is gone
    page.goto(f"{server}/ui/jobs/{job_id}/replay")
    page.wait_for_selector("#replay-source")
    assert page.get_attribute("#replay-source a", "href") == f"/ui/jobs/{eval_id}"
    assert "on held-out test rooms (seed" in page.inner_text("#replay-source")
    (data_dir / "artifacts" / eval_id / "replay.json").unlink()
    page.goto(f"{server}/ui/jobs/{job_id}/replay")
    page.wait_for_selector("#replay-source")
    assert page.get_attribute("#replay-source a", "href") == f"/ui/jobs/{earlier}"

    # the safety layer's box beside the button: the request carries it, the job holds it, and the
    # list marks the eval that drives through it. (That an eval job with it runs the layer is the API
    # test's; this one is cancelled at once. The demo policy, trained where contacts do not end an
    # episode, slides along cave walls: on the 100 held-out goals above, 94 % and 6.1 contacts per
    # episode alone, 82 % and 2.9 through the layer, which holds it at walls until the step limit;
    # a 2-core AMD EPYC VM)
    page.goto(f"{server}/ui/jobs/{job_id}")
    page.wait_for_selector("#run-eval")
    page.fill("#eval-episodes", "1")
    page.check("#eval-shield")
    with page.expect_request(lambda r: r.method == "POST" and r.url.endswith("/jobs/eval")) as sent:
        page.click("#run-eval")
    body = sent.value.post_data_json
    assert body["shield"] is True and body["robustness"] is False and body["episodes"] == 1, body
    page.wait_for_url(lambda url: "/ui/jobs/" in url and url.rsplit("/", 1)[-1] not in (job_id, eval_id),
                      timeout=20_000)  # fmt: skip
    shielded = page.url.rsplit("/", 1)[-1]
    assert httpx.post(f"{server}/jobs/{shielded}/cancel", headers=AUTH, json={}).status_code == 200
    assert httpx.get(f"{server}/jobs/{shielded}", headers=AUTH).json()["config"]["shield"] is True
    page.goto(f"{server}/ui/jobs/{job_id}")
    row = page.locator(f'#evals tr[data-id="{shielded}"]')
    row.wait_for()
    assert "safety layer" in row.inner_text() and "safety layer" not in page.inner_text(f'#evals tr[data-id="{eval_id}"]')
    page.screenshot(path=shots / "job-evals-shield.png", full_page=True)


def test_browser__nav_marks_only_the_current_page_and_never_api_docs(server, page):
    for path, current in (("/", "Jobs"), ("/ui/submit", "New training job"), ("/ui/replay", "Replay")):
        page.goto(server + path)
        page.wait_for_selector("header nav a.active")
        assert page.locator("header nav a.active").all_inner_texts() == [current], path
        weights = page.locator("header nav a").evaluate_all(
            "links => links.map(a => [a.textContent, getComputedStyle(a).fontWeight])")
        assert dict(weights)["API docs"] == "400", weights
        assert dict(weights)[current] == "600", weights


def test_browser__compiling_phase_and_failed_reason_as_the_pages_show_them(server, page):
    page.goto(server + "/")
    page.wait_for_selector("#jobs")
    shown = page.evaluate("""() => {
        const t = Date.now() / 1000;
        const job = (status, metrics, error) => ({ status, metrics, error, progress: 1, started_at: t - 20 });
        return [jobProgress(job("running", { phase: "compiling", phase_since: t - 12 })).textContent,
                jobProgress(job("running", { phase: "training" })).textContent,
                jobProgress(job("failed", {}, "Traceback ...\\n  ...\\nValueError: bad")).textContent];
    }""")  # fmt: skip
    assert shown[0] == "compiling 12 s"
    assert shown[1] == "100 %"
    assert shown[2] == "ValueError: bad"  # the reason, not a full bar


def test_browser__jobs_page_updates_live_cancels_deletes_and_shows_a_sweep(server, page, shots):
    page.goto(server + "/")
    page.wait_for_selector("#jobs tbody tr[data-id]")
    # two trials of the paper's PPO that differ only in traced numbers: one compiled program
    # trains both side by side (the built-in space draws rollout lengths and minibatch counts,
    # a program each, which this page does not need)
    sweep = httpx.post(server + "/jobs/sweep", headers=AUTH, json={
        "space": "ppo", "trials": 2, "parallel": 2, "total_steps": 131072,
        "overrides": {"base.num_envs": 64, "space": {
            "algorithm.learning_rate": {"type": "log_float", "low": 1e-4, "high": 1e-3},
            "algorithm.gamma": {"type": "float", "low": 0.9, "high": 0.99}}}}).json()  # fmt: skip
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
    # beside the objective, what each trial's policy did (its collisions too), as trials.json says
    heads = page.locator("#trials thead th").all_inner_texts()
    assert heads[2:6] == ["Value (success_rate)", "Success", "Collisions / episode",
                          "Success without a collision"], heads  # fmt: skip
    cells = page.locator("#trials tr.best td").all_inner_texts()
    m = best["metrics"]
    shown = [float(c.rstrip(" %")) for c in cells[3:6]]
    assert shown == pytest.approx([100 * m["success_rate"], m["collisions_per_episode"],
                                   100 * m["collision_free_success_rate"]], abs=0.051), cells  # fmt: skip
    page.locator('#images img[alt="optimization_history.png"]').wait_for(timeout=20_000)
    page.screenshot(path=shots / "sweep.png", full_page=True)


def test_browser__jobs_page_shows_a_failed_jobs_reason_not_a_full_bar(server, page, data_dir, shots):
    from quicknav_service.jobs.models import JobKind
    from quicknav_service.jobs.sqlite_store import SQLiteJobStore

    # a stored config no TrainConfig accepts (the API would refuse it): the worker fails the job
    store = SQLiteJobStore(data_dir / "jobs.db")
    job, _ = store.submit(JobKind.train, {"preset": "demo"}, {"total_steps": "many"})
    assert wait_for_job(server, job.id, 120)["status"] == "failed"
    page.goto(server + "/")
    row = page.locator(f'#jobs tr[data-id="{job.id}"][data-status="failed"]')
    row.wait_for(timeout=10_000)
    error = httpx.get(f"{server}/jobs/{job.id}", headers=AUTH).json()["error"]
    shown = row.locator(".reason").inner_text()
    assert shown and shown == error.strip().splitlines()[-1].strip()
    assert row.locator(".bar").count() == 0 and "100 %" not in row.inner_text()
    page.screenshot(path=shots / "jobs-failed.png", full_page=True)
    # its page: the failed event carries the whole traceback on one line; it wraps inside the log
    page.goto(f"{server}/ui/jobs/{job.id}")
    failed_line = page.locator("#events div", has_text="failed")
    failed_line.wait_for(timeout=10_000)
    assert len(failed_line.inner_text()) > 300  # long enough to overflow if it did not wrap
    widths = page.evaluate("""() => { const log = document.getElementById("events");
        return [log.scrollWidth, log.clientWidth, document.documentElement.scrollWidth, innerWidth]; }""")
    assert widths[0] <= widths[1] and widths[2] <= widths[3], f"the event log overflows: {widths}"
    page.screenshot(path=shots / "job-failed-events.png", full_page=True)


def test_browser__a_job_no_worker_can_run_says_why_it_waits(server, page, data_dir, shots):
    from quicknav_service.jobs.models import JobKind
    from quicknav_service.jobs.sqlite_store import SQLiteJobStore
    from tests.service.test_worker_capabilities import _config

    # two devices: the server's worker has one (the API would refuse it, QUICKNAV_MAX_DEVICES=1)
    store = SQLiteJobStore(data_dir / "jobs.db")
    job, _ = store.submit(JobKind.train, {"preset": "demo"}, _config(2))
    try:
        page.goto(server + "/")
        row = page.locator(f'#jobs tr[data-id="{job.id}"][data-status="queued"]')
        row.wait_for(timeout=10_000)
        assert row.locator(".reason.waiting").inner_text() == "waiting for a worker that can run it"
        page.goto(f"{server}/ui/jobs/{job.id}")
        note = page.locator("#job-waiting")
        note.wait_for(timeout=10_000)
        assert note.inner_text().startswith("waiting for a worker with 2 devices; the 1 live worker has 1 device")
        page.screenshot(path=shots / "job-waiting.png", full_page=True)
    finally:
        httpx.post(f"{server}/jobs/{job.id}/cancel", headers=AUTH, json={})


def test_browser__maps_form_sends_the_plain_image_fields(server, page, tmp_path):
    """The Maps page's form carries what `quicknav maps upload` does for a plain image: resolution,
    negate and both thresholds. A mid-grey room is unknown at the default thresholds and free with
    free_thresh 0.6, as the server reads it."""
    from tests.service.test_maps import pgm

    img = np.full((40, 40), 0, np.uint8)  # black: a wall all round
    img[2:38, 2:38] = 128  # darkness 0.5: above the default free_thresh (0.196), below 0.65
    (tmp_path / "grey.pgm").write_bytes(pgm(img))
    page.goto(f"{server}/ui/maps")
    page.wait_for_selector("#map-form")
    page.set_input_files("#map-files", [tmp_path / "grey.pgm"])
    page.fill("#map-name", "grey room")
    page.fill("#map-resolution", "0.1")
    page.fill("#map-occupied_thresh", "0.9")
    page.fill("#map-free_thresh", "0.6")
    page.click("#upload")
    page.wait_for_selector("#map-uploaded")
    (m,) = [m for m in httpx.get(f"{server}/maps", headers=AUTH).json()["data"] if m["name"] == "grey room"]
    assert m["resolution"] == 0.1 and m["unknown_fraction"] == 0, m
    assert m["free_fraction"] == pytest.approx(36 * 36 / (40 * 40)), m
    # the card says what the API's notes say (here: the free space its 0.5 m cells keep)
    card = page.locator(f'figure[data-map="{m["id"]}"]')
    card.wait_for()
    assert m["notes"] and card.locator(".map-note").all_inner_texts() == m["notes"], m["notes"]
    page.screenshot(path=tmp_path / "maps-notes.png", full_page=True)
    # a threshold out of its range is the server's 422, shown on the page, nothing stored
    page.set_input_files("#map-files", [tmp_path / "grey.pgm"])
    page.fill("#map-resolution", "0.1")
    page.fill("#map-free_thresh", "1.5")
    page.click("#upload")
    page.wait_for_selector("#map-errors .error-box")
    assert "free_thresh" in page.inner_text("#map-errors")
    assert httpx.get(f"{server}/maps", headers=AUTH).json()["count"] == 1
    assert httpx.delete(f"{server}/maps/{m['id']}", headers=AUTH).status_code == 204
