"""A building map's journey in a real browser (headless Chromium against a live `quicknav serve`):
upload a map_server map on the Maps page, see its preview, train the demo preset on it from the
submit form, evaluate the trained policy on the map (held-out episodes: a policy that learned), and
watch the replay drawn on the map's own picture. Bad files are refused on the page with the
server's reason."""

from __future__ import annotations

import httpx
import pytest

from tests.service.test_maps import pgm, room_picture, yaml_for
from tests.service.test_web_browser import (  # noqa: F401 (fixtures)
    AUTH,
    JOB_TIMEOUT_MS,
    TOKEN,
    data_dir,
    page,
    server,
    shots,
    success_in_table,
)

# the server's worker trains the demo preset to success on the map and evaluates the building
# policy: it compiles as a user's machine compiles, every optimisation on (the `server` fixture)
SERVER_AS_A_USER = True


@pytest.fixture(scope="module")
def map_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("map")
    (folder / "room.yaml").write_bytes(yaml_for())
    (folder / "room.pgm").write_bytes(pgm(room_picture()))
    (folder / "broken.yaml").write_bytes(yaml_for("room.pgm", origin="[0, 0, 0.5]"))
    return folder


def canvas_pixel(page, x_m: float, y_m: float) -> list[int]:  # noqa: F811 (the fixture)
    """The replay canvas's RGB at a point of the room (metres, y up), through the part of the room
    the canvas shows (``data-view``: x0, y0, width, height in metres; a map's own extent)."""
    return page.evaluate(
        """([x, y]) => { const c = document.getElementById("replay-canvas");
        const [x0, y0, w, h] = c.dataset.view.split(",").map(Number);
        const s = c.width / w;
        const d = c.getContext("2d").getImageData(Math.round((x - x0) * s), Math.round(c.height - (y - y0) * s), 1, 1).data;
        return [d[0], d[1], d[2]]; }""", [x_m, y_m])  # fmt: skip


def canvas_view(page) -> list[float]:  # noqa: F811 (the fixture)
    """``[x0, y0, width, height]``: the part of the room the replay canvas shows, in metres."""
    return [float(v) for v in page.get_attribute("#replay-canvas", "data-view").split(",")]


@pytest.mark.slow  # trains the demo preset to success on the map
def test_browser__upload_a_map_train_on_it_evaluate_and_replay_on_its_picture(
    server, page, shots, map_files  # noqa: F811 (fixtures of test_web_browser)
):
    page.goto(f"{server}/ui/maps")
    page.wait_for_selector("#login")
    page.fill("input[name=token]", TOKEN)
    page.click("#login button[type=submit]")
    page.wait_for_selector("#map-form")
    assert page.locator("header nav a.active").all_inner_texts() == ["Maps"]
    # a map the env cannot lay on its grid is refused with the server's reason, nothing stored
    page.set_input_files("#map-files", [map_files / "broken.yaml", map_files / "room.pgm"])
    page.click("#upload")
    page.wait_for_selector("#map-errors .error-box")
    assert "yaw" in page.inner_text("#map-errors")
    assert httpx.get(f"{server}/maps", headers=AUTH).json()["count"] == 0

    page.set_input_files("#map-files", [map_files / "room.yaml", map_files / "room.pgm"])
    page.fill("#map-name", "test room")
    page.click("#upload")
    page.wait_for_selector("#map-uploaded")
    stored = httpx.get(f"{server}/maps", headers=AUTH).json()["data"]
    assert [m["name"] for m in stored] == ["test room"]
    m = stored[0]
    card = page.locator(f'figure[data-map="{m["id"]}"]')
    card.locator("img").wait_for()
    assert card.locator("img").evaluate("img => img.complete && img.naturalWidth") == 152
    page.screenshot(path=shots / "maps.png", full_page=True)

    # train on it from the submit form: the map is chosen, its grid comes with it
    card.locator("text=Train on this map").click()
    page.wait_for_selector("#submit-form")
    assert page.input_value("#rooms") == m["id"]
    page.click("#submit")
    page.wait_for_url(lambda url: "/ui/jobs/" in url, timeout=20_000)
    job_id = page.url.rsplit("/", 1)[-1]
    job = httpx.get(f"{server}/jobs/{job_id}", headers=AUTH).json()
    env = job["config"]["env"]
    assert (env["rooms"], env["maps"]["train"], env["grid_size"], env["room_size"]) == (
        "maps", [m["ref"]], 18, 9.0)  # fmt: skip
    page.wait_for_selector('#job-head .badge[data-status="succeeded"]', timeout=JOB_TIMEOUT_MS)

    # evaluate it on the map: held-out episodes (starts and goals no training episode drew)
    page.wait_for_selector("#run-eval")
    page.fill("#eval-episodes", "100")
    page.click("#run-eval")
    page.wait_for_url(lambda url: "/ui/jobs/" in url and job_id not in url, timeout=20_000)
    eval_id = page.url.rsplit("/", 1)[-1]
    page.wait_for_selector('#job-head .badge[data-status="succeeded"]', timeout=JOB_TIMEOUT_MS)
    page.wait_for_selector("#eval-metrics")
    shown = success_in_table(page)
    assert shown >= 0.8, f"the policy did not learn to drive in the map: held-out success {shown}"
    ev = httpx.get(f"{server}/jobs/{eval_id}", headers=AUTH).json()
    assert ev["config"]["env"]["maps"]["train"] == [m["ref"]] and ev["warnings"] == []

    # the replay: the map's picture under the grid's walls; its episodes were on the map (held-out
    # episodes on the map the policy trained on, no held-out rooms), named as it was uploaded (the
    # page asks the API for the map's name once, for the chooser's words and the replay's)
    named = []
    page.on("request", lambda r: named.append(r.url) if r.url.endswith(f"/maps/{m['ref'][4:]}") else None)
    page.click("#replay-link")
    canvas = page.locator("#replay-canvas")
    canvas.wait_for(timeout=20_000)
    assert 'on map "test room" (seed' in page.inner_text("#replay-source"), page.inner_text("#replay-source")
    assert len(named) == 1, named
    page.wait_for_timeout(300)
    # the canvas shows the map's own extent (its free cells and the wall ring around them), as
    # the GIFs do (render.map_view on the same grid, computed here in Python), in its shape
    from quicknav_core.env.maps import map_room
    from quicknav_core.env.render import map_view

    x0, x1, y0, y1 = map_view(map_room(map_files / "room.yaml", 0.5, 18), 9.0)
    expected = [x0, y0, x1 - x0, y1 - y0]
    assert canvas_view(page) == pytest.approx(expected) and max(expected[2:]) < 9.0, (canvas_view(page), expected)
    size = page.evaluate("""() => { const c = document.getElementById("replay-canvas");
        return [c.width, c.height]; }""")  # fmt: skip
    assert max(size) == 520 and size[0] / size[1] == pytest.approx((x1 - x0) / (y1 - y0), rel=0.02), size
    # (0.6 m, 4 m): the map's unknown margin (grey 190 in the picture) in a wall cell of the grid,
    # drawn 35 % dark over the picture; without the picture a wall cell is #3b3b3b (59)
    r, g, b = canvas_pixel(page, 0.6, 4.0)
    assert 120 <= r <= 170 and r == g == b, (r, g, b)
    # (4.3 m, 2 m): free floor in the picture and in the grid: the floor colour
    assert canvas_pixel(page, 4.3, 2.0) == [244, 241, 234]
    # a successful episode, halfway, for the picture
    options = page.locator("#episode option").all_inner_texts()
    page.select_option("#episode", index=next(i for i, t in enumerate(options) if "reached" in t))
    page.click("#play")  # pause
    page.locator("#step-slider").fill(str(int(page.get_attribute("#step-slider", "max")) // 2))
    page.screenshot(path=shots / "map-replay.png", full_page=True)

    # the map is in use while a job that names it waits; a finished job does not hold it
    assert httpx.delete(f"{server}/maps/{m['id']}", headers={**AUTH}).status_code == 204


@pytest.mark.slow  # an evaluation of the building policy on the map, compiled as a worker does
def test_browser__a_building_policy_evaluated_on_an_uploaded_map_replays_its_plan_and_obstacles(
    server, page, shots, map_files, data_dir, trained_building_run  # noqa: F811 (fixtures)
):
    """docs/building.md's journey in the browser: a building policy (the test run's shorter
    training of the preset, seeded as a succeeded job: it trained on floor plans only) evaluated
    on a map uploaded to the server, from the job page's evaluation form, and replayed with its
    global plan and the boxes and people it met drawn."""
    from quicknav_service.jobs.sqlite_store import SQLiteJobStore
    from tests.trained import seed_trained_job

    files = [("files", ("room.yaml", (map_files / "room.yaml").read_bytes())),
             ("files", ("room.pgm", (map_files / "room.pgm").read_bytes()))]  # fmt: skip
    up = httpx.post(f"{server}/maps", headers=AUTH, files=files, data={"name": "building room"})
    assert up.status_code in (200, 201), up.text
    m = up.json()
    store = SQLiteJobStore(data_dir / "jobs.db")
    try:
        job_id = seed_trained_job(store, data_dir / "artifacts", trained_building_run, {"preset": "building"})
    finally:
        store.close()
    page.goto(f"{server}/ui/jobs/{job_id}")
    page.wait_for_selector("#login, #eval-where")
    if page.locator("#login").count():  # signed in by the module's first test, unless run alone
        page.fill("input[name=token]", TOKEN)
        page.click("#login button[type=submit]")
    page.wait_for_selector(f'#eval-where option[value="{m["id"]}"]', state="attached")
    page.select_option("#eval-where", m["id"])
    page.fill("#eval-episodes", "20")
    page.click("#run-eval")
    page.wait_for_function(f"!location.pathname.endsWith('{job_id}') || !!document.querySelector('.error-box')",
                           timeout=20_000)  # fmt: skip
    assert not page.locator(".error-box").count(), page.inner_text(".error-box")
    eval_id = page.url.rsplit("/", 1)[-1]
    page.wait_for_selector('#job-head .badge[data-status="succeeded"]', timeout=JOB_TIMEOUT_MS)
    ev = httpx.get(f"{server}/jobs/{eval_id}", headers=AUTH).json()
    env = ev["config"]["env"]
    # the map at the policy's 0.5 m cells, the policy's own sensors and unmapped obstacles
    assert env["maps"]["train"] == [m["ref"]] and env["grid_size"] == m["suggested_env"]["grid_size"], env
    assert env["observe_plan"] and env["obstacles"]["static"] == 6 and env["obstacles"]["moving"] == 3, env
    # the train job's list of evaluations names the map as it was uploaded (quoted, as the
    # replay and the pictures name it)
    page.goto(f"{server}/ui/jobs/{job_id}")
    page.wait_for_selector(f'#evals tr[data-id="{eval_id}"]')
    row = page.inner_text(f'#evals tr[data-id="{eval_id}"]')
    assert 'map "building room"' in row, row

    page.click("#replay-link")
    canvas = page.locator("#replay-canvas")
    canvas.wait_for(timeout=20_000)
    page.click("#play")  # pause
    drawn = []
    for i in range(len(page.locator("#episode option").all_inner_texts())):
        page.select_option("#episode", index=i)
        drawn.append({k: int(canvas.get_attribute(f"data-{k}")) for k in ("plan", "boxes", "people")})
    assert all(d["plan"] >= 2 for d in drawn), drawn  # the start, cells, the goal
    assert sum(d["boxes"] + d["people"] for d in drawn) > 0, drawn
    legend = page.inner_text(".legend")
    assert "global plan" in legend and ("box" in legend or "person" in legend), legend
    page.screenshot(path=shots / "building-replay.png", full_page=True)


def test_browser__a_non_square_map_from_the_submit_form_takes_its_own_grid(server, page):  # noqa: F811
    """The submit form sends a non-square map's own grid with it (the office: 29 x 45 cells at
    0.5 m, rows x cols), not only its longer side; the request is held back (nothing trains)."""
    from tests.journeys.readme import ROOT

    office = ROOT / "examples" / "maps"
    files = [("files", ("office.yaml", (office / "office.yaml").read_bytes())),
             ("files", ("office.pgm", (office / "office.pgm").read_bytes()))]  # fmt: skip
    up = httpx.post(f"{server}/maps", headers=AUTH, files=files, data={"name": "office"})
    assert up.status_code in (200, 201), up.text
    m = up.json()
    assert (m["suggested_env"]["grid_size"], m["suggested_env"]["grid_rows"]) == (45, 29), m
    page.goto(f"{server}/ui/submit?map={m['id']}")
    page.wait_for_selector("#login, #submit-form")
    if page.locator("#login").count():  # signed in by the module's first test, unless run alone
        page.fill("input[name=token]", TOKEN)
        page.click("#login button[type=submit]")
    page.wait_for_selector("#submit-form")
    assert page.input_value("#rooms") == m["id"]
    sent = []
    page.route("**/jobs/train", lambda route: (sent.append(route.request.post_data_json), route.abort()))
    page.click("#submit")
    for _ in range(50):
        if sent:
            break
        page.wait_for_timeout(100)
    page.unroute("**/jobs/train")
    (body,) = sent
    o = body["overrides"]
    assert (o["env.rooms"], o["env.grid_size"], o["env.grid_rows"], o["env.room_size"]) == (
        "maps", 45, 29, 22.5), o  # fmt: skip
    assert "env.grid_cols" not in o, o
    assert httpx.delete(f"{server}/maps/{m['id']}", headers=AUTH).status_code == 204
