"""Uploaded maps over HTTP against a live server: upload, read back, bad files, configs naming maps
by id, delete while in use, a job on an uploaded map, and the store's copy on another machine."""

from __future__ import annotations

import io
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from quicknav_core.env.maps import load_map
from tests.service.conftest import LiveServer
from tests.service.test_api import TINY, wait_status

RES = 0.05  # metres per pixel of the maps drawn here
FREE, OCCUPIED, UNKNOWN = 254, 0, 205


def room_picture(side_m: float = 7.0, margin_m: float = 0.3) -> np.ndarray:
    """Grey levels, top row first: a square room with a wall across most of it, unknown outside."""
    px = lambda m: round(m / RES)  # noqa: E731
    n = px(side_m + 2 * margin_m)
    img = np.full((n, n), UNKNOWN, np.uint8)
    m, s = px(margin_m), px(side_m)
    img[m:m + s, m:m + s] = OCCUPIED
    t = px(0.1)  # 10 cm walls
    img[m + t:m + s - t, m + t:m + s - t] = FREE
    # a wall from the left, 60 % across, at the middle height (top row first)
    mid = m + s // 2
    img[mid:mid + t, m:m + int(0.6 * s)] = OCCUPIED
    return img


def pgm(img: np.ndarray) -> bytes:
    h, w = img.shape
    return f"P5\n{w} {h}\n255\n".encode() + img.tobytes()


def yaml_for(image: str = "room.pgm", **extra) -> bytes:
    fields = {"image": image, "mode": "trinary", "resolution": RES, "origin": "[-0.3, -0.3, 0.0]",
              "negate": 0, "occupied_thresh": 0.65, "free_thresh": 0.196, **extra}  # fmt: skip
    return "".join(f"{k}: {v}\n" for k, v in fields.items()).encode()


def png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def upload(url: str, files: list[tuple[str, bytes]], **form) -> httpx.Response:
    return httpx.post(f"{url}/maps", files=[("files", (n, b)) for n, b in files],
                      data={k: str(v) for k, v in form.items()}, timeout=30)  # fmt: skip


@pytest.fixture
def server(tmp_path):
    with LiveServer(tmp_path, max_map_pixels=400_000) as s:
        yield s


def test_upload__read_back_as_the_env_reads_it(server, tmp_path):
    img = room_picture()
    r = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(img))], name="test room")
    assert r.status_code == 201, r.text
    meta = r.json()
    assert r.headers["location"] == f"/maps/{meta['id']}" and meta["ref"] == f"map:{meta['id']}"
    assert meta["name"] == "test room" and meta["files"] == ["room.yaml", "room.pgm"]
    assert (meta["width_px"], meta["height_px"]) == (152, 152) and meta["resolution"] == RES
    assert meta["width_m"] == pytest.approx(7.6)
    assert meta["unknown_fraction"] == pytest.approx(float((img == UNKNOWN).mean()), abs=1e-4)
    assert meta["free_fraction"] == pytest.approx(float((img == FREE).mean()), abs=1e-4)
    # 7.6 m at 0.5 m cells: 16 cells and the outer ring; a small room's step limit is the env's
    assert meta["suggested_env"] == {"rooms": "maps", "maps": {"train": [meta["ref"]]},
                                     "grid_size": 18, "room_size": 9.0, "max_steps": 300}  # fmt: skip
    # its 10 cm walls at 0.5 m cells: the grid loses some free space, and says how much
    (note,) = meta["notes"]
    assert note.startswith("room.pgm: at 0.5 m cells the grid keeps") and "free space" in note, note
    # the same files again: the same map
    again = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(img))])
    assert again.status_code == 201 and again.json()["id"] == meta["id"]
    listed = httpx.get(f"{server.url}/maps").json()
    assert listed["count"] == 1 and listed["data"][0]["id"] == meta["id"]
    assert httpx.get(f"{server.url}/maps/{meta['id']}").json() == {**meta, "used_by": []}

    # the stored pair is a map_server map that reads back to the same occupancy, pixel for pixel
    for name in ("map.yaml", "map.pgm"):
        got = httpx.get(f"{server.url}/maps/{meta['id']}/files/{name}")
        assert got.status_code == 200
        (tmp_path / name).write_bytes(got.content)
    assert (tmp_path / "map.pgm").read_bytes() == pgm(img)
    stored = load_map(tmp_path / "map.yaml")
    (tmp_path / "orig.pgm").write_bytes(pgm(img))
    (tmp_path / "orig.yaml").write_bytes(yaml_for("orig.pgm"))
    original = load_map(tmp_path / "orig.yaml")
    assert np.array_equal(stored.blocked, original.blocked)
    assert stored.resolution == original.resolution
    # map_server's origin is where the map sits in the robot's world; QuickNav lays the map's
    # lower-left corner at cell (1, 1) whatever it is, so the stored pair keeps it as uploaded
    assert stored.origin == (-0.3, -0.3)

    # the preview: the picture the right way up (the occupied wall at the middle, from the left)
    prev = httpx.get(f"{server.url}{meta['preview_url']}")
    assert prev.status_code == 200 and prev.headers["content-type"] == "image/png"
    rgb = np.asarray(Image.open(io.BytesIO(prev.content)).convert("RGB"))
    assert rgb.shape == (152, 152, 3)
    dark = rgb.sum(axis=2) < 300
    assert np.array_equal(dark, img == OCCUPIED)
    grey = (rgb == (190, 190, 190)).all(axis=2)
    assert np.array_equal(grey, img == UNKNOWN)
    assert httpx.get(f"{server.url}/maps/{meta['id']}/files/secrets.txt").status_code == 404
    assert httpx.get(f"{server.url}/maps/0000000000000000").status_code == 404
    assert httpx.get(f"{server.url}/maps/not-an-id").status_code == 422


def test_upload__plain_image_with_its_resolution(server):
    img = room_picture()
    r = upload(server.url, [("room.png", png(img))], resolution=RES)
    assert r.status_code == 201, r.text
    meta = r.json()
    assert meta["resolution"] == RES and meta["name"] == "room"
    # a negated picture of the same room, said to be negated, is the same occupancy
    neg = upload(server.url, [("neg.png", png(255 - img))], resolution=RES, negate="true")
    assert neg.status_code == 201
    assert neg.json()["free_fraction"] == meta["free_fraction"]
    assert neg.json()["id"] != meta["id"]  # other files, another map


BAD = {
    "no image": ([("room.yaml", yaml_for())], "files", "0 image file"),
    "two images": ([("a.png", png(room_picture())), ("b.png", png(room_picture()))], "files", "2 image file"),
    "yaml names another image": ([("room.yaml", yaml_for("other.pgm")), ("room.pgm", pgm(room_picture()))],
                                 "files", "names image 'other.pgm'"),
    "image without resolution": ([("room.png", png(room_picture()))], "resolution", "give its resolution"),
    "not a picture": ([("room.pgm", b"P5\nthis is not a picture")], "files", "not a PGM or PNG"),
    "a text file": ([("notes.txt", b"hello")], "files", "neither a map_server .yaml"),
    "yaml that is not yaml": ([("room.yaml", b"image: [unclosed"), ("room.pgm", pgm(room_picture()))],
                              "files", "not valid YAML"),
    "rotated origin": ([("room.yaml", yaml_for(origin="[0, 0, 1.57]")), ("room.pgm", pgm(room_picture()))],
                       "files", "yaw"),
    "thresholds out of order": ([("room.yaml", yaml_for(free_thresh=0.9)), ("room.pgm", pgm(room_picture()))],
                                "files", "free_thresh"),
    "all occupied": ([("dark.png", png(np.zeros((40, 40), np.uint8)))], "files", "no free pixel"),
    # hostile files: each a 422 that names the rule, cheaply, never a 500 or an echo of the input
    "truncated text PGM": ([("room.pgm", b"P2\n40 40\n255\n255 255\n")], "files", "truncated"),
    "a 5000-digit number": ([("room.yaml", yaml_for(resolution="1" * 5000)), ("room.pgm", pgm(room_picture()))],
                            "files", "a value of 5,000 characters"),
    "a list nested 5000 deep": ([("room.yaml", yaml_for(extra="[" * 5000 + "]" * 5000)),
                                 ("room.pgm", pgm(room_picture()))], "files", "nested more than 8"),
    "nested aliases": ([("room.yaml", b"a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a]\n"
                         b"c: &c [*b, *b, *b, *b, *b, *b]\nh: &h [*c, *c, *c, *c, *c, *c]\nimage: *h\n"),
                        ("room.pgm", pgm(room_picture()))], "files", "aliases"),
    "resolution 1e300": ([("room.yaml", yaml_for(resolution="1e300")), ("room.pgm", pgm(room_picture()))],
                         "files", "allowed: 0 < resolution <= 100"),
    "a PGM named .png": ([("room.png", pgm(room_picture()))], "files", "its contents are .pgm, not .png"),
}  # fmt: skip
PLAIN = ("all occupied", "not a picture", "truncated text PGM", "a PGM named .png")


@pytest.mark.parametrize("case", list(BAD))
def test_upload__bad_files_are_refused_naming_the_problem(server, case):
    files, field, words = BAD[case]
    form = {"resolution": RES} if case in PLAIN else {}
    r = upload(server.url, files, **form)
    assert r.status_code == 422, r.text
    item = r.json()["detail"][0]
    assert item["loc"] == ["body", field] and words in item["msg"], item
    assert len(r.content) < 2000, f"the answer echoes the input: {len(r.content)} bytes"
    assert httpx.get(f"{server.url}/maps").json()["count"] == 0


def test_upload__limits_and_form_fields(server):
    img = room_picture()
    # a plain-image field with a YAML would be ignored: refused, naming it
    r = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(img))], resolution=0.1)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "resolution"]
    r = upload(server.url, [("room.png", png(img))], resolution=-1)
    assert r.status_code == 422 and "resolution" in r.json()["detail"][0]["loc"]
    # more pixels than this server takes (max_map_pixels=400,000 here)
    big = np.full((700, 700), FREE, np.uint8)
    r = upload(server.url, [("big.png", png(big))], resolution=RES)
    assert r.status_code == 413 and "QUICKNAV_MAX_MAP_PIXELS" in r.json()["detail"]
    # a header that claims a huge picture is 413 with the limit, before anything is decoded
    header = b"P5\n100000 100000\n255\n" + bytes(1000)
    bomb = bytearray(png(np.full((8, 8), FREE, np.uint8)))
    bomb[16:24] = (30000).to_bytes(4, "big") * 2  # IHDR: 30000 x 30000
    for name, data in (("huge.pgm", header), ("bomb.png", bytes(bomb))):
        r = upload(server.url, [(name, data)], resolution=RES)
        assert r.status_code == 413, r.text
        assert "is more than the 400,000" in r.json()["detail"] and "QUICKNAV_MAX_MAP_PIXELS" in r.json()["detail"]
    # the JSON body limit does not apply to uploads, their own does
    assert r.request.headers["content-length"] and int(r.request.headers["content-length"]) < 1_000_000


def test_upload__body_over_the_upload_limit_is_413(tmp_path):
    with LiveServer(tmp_path, max_map_upload_bytes=50_000) as s:
        r = upload(s.url, [("room.pgm", pgm(room_picture()) + b"\0" * 60_000)], resolution=RES)
        assert r.status_code == 413 and "QUICKNAV_MAX_MAP_UPLOAD_BYTES" in r.json()["detail"]


def test_configs_name_maps_by_id__checked_at_submission(server):
    meta = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))]).json()

    def train(**overrides):
        return httpx.post(f"{server.url}/jobs/train", json={"preset": "demo", "overrides": {
            **TINY, "env.rooms": "maps", **overrides}})  # fmt: skip

    r = train(**{"env.maps.train": ["examples/maps/office.yaml"]})
    assert r.status_code == 422
    item = r.json()["detail"][0]
    assert item["loc"] == ["body", "overrides", "env.maps.train", 0] and "POST /maps" in item["msg"]
    r = train(**{"env.maps.train": ["map:0123456789abcdef"]})
    assert r.status_code == 422 and "no such map on this server" in r.text
    # the room is 7.6 m: 8 cells of 1 m (room_size 8 / grid_size 8, TINY) and the ring need 10
    r = train(**{"env.maps.train": [meta["ref"]]})
    assert r.status_code == 422
    item = r.json()["detail"][0]
    assert item["loc"] == ["body", "overrides", "env.maps.train"]
    assert item["msg"].startswith(meta["ref"]) and "Set grid_size >= 10" in item["msg"]
    # an eval body and a sweep body are checked the same way
    r = httpx.post(f"{server.url}/jobs/eval", json={"policy": "oracle", "env": {
        "rooms": "maps", "maps": {"train": ["/home/me/map.yaml"]}}})  # fmt: skip
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][:4] == ["body", "env", "maps", "train"]


def test_delete__refused_while_a_queued_job_uses_the_map(server):
    meta = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))]).json()
    r = httpx.post(f"{server.url}/jobs/train", json={"preset": "demo", "overrides": {
        **TINY, "env.rooms": "maps", "env.maps.train": [meta["ref"]], "env.grid_size": 18,
        "env.room_size": 9.0}})  # fmt: skip
    assert r.status_code == 202, r.text
    job = r.json()
    assert httpx.get(f"{server.url}/maps/{meta['id']}").json()["used_by"] == [job["id"]]
    r = httpx.delete(f"{server.url}/maps/{meta['id']}")
    assert r.status_code == 409 and job["id"] in r.json()["detail"]
    assert httpx.post(f"{server.url}/jobs/{job['id']}/cancel", json={}).status_code == 200
    assert httpx.delete(f"{server.url}/maps/{meta['id']}").status_code == 204
    assert httpx.get(f"{server.url}/maps/{meta['id']}").status_code == 404
    assert httpx.delete(f"{server.url}/maps/{meta['id']}").status_code == 404


def test_train_and_eval_jobs_run_on_an_uploaded_map(server, monkeypatch):
    """The worker reads the map from the store by its id; the eval's replay carries the map, and
    its pictures' titles name it as it was uploaded (the worker's Runtime.map_name)."""
    from quicknav_core.eval import pictures

    titles = []
    drawn = pictures.draw_trajectories
    monkeypatch.setattr(pictures, "draw_trajectories",
                        lambda *a, **kw: (titles.append(kw["where"]), drawn(*a, **kw))[1])  # fmt: skip
    meta = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))],
                  name="test room").json()  # fmt: skip
    env = {"env.rooms": "maps", "env.maps.train": [meta["ref"]], "env.grid_size": 18,
           "env.room_size": 9.0}  # fmt: skip
    r = httpx.post(f"{server.url}/jobs/train", json={"preset": "demo", "overrides": {**TINY, **env}})
    assert r.status_code == 202, r.text
    train = r.json()
    worker = server.worker()
    worker.run_burst(poll_s=0.05)
    assert wait_status(server.url, train["id"], {"succeeded", "failed"})["status"] == "succeeded"
    config = json.loads(httpx.get(f"{server.url}/jobs/{train['id']}/artifacts/config.json").content)
    assert config["env"]["maps"]["train"] == [meta["ref"]]  # the run names the map by its id
    r = httpx.post(f"{server.url}/jobs/eval", json={"job_id": train["id"], "episodes": 4})
    assert r.status_code == 202, r.text
    ev = r.json()
    worker.run_burst(poll_s=0.05)
    assert wait_status(server.url, ev["id"], {"succeeded", "failed"})["status"] == "succeeded"
    replay = json.loads(httpx.get(f"{server.url}/jobs/{ev['id']}/artifacts/replay.json").content)
    # where the map's picture lies in the room: its lower-left corner at cell (1, 1)
    assert replay["maps"] == {meta["ref"]: {"x0": 0.5, "y0": 0.5, "width_m": 7.6, "height_m": 7.6}}
    assert {e["map"] for e in replay["episodes"]} == {meta["ref"]}
    assert titles == ['map "test room"'], titles


def test_eval_job_with_a_map__laid_at_the_policys_cell_size_and_refused_naming_the_map(server):
    """POST /jobs/eval {"map": "map:<id>"} (the SDK's ``evaluate(map=)``): a policy trained in
    carved rooms of 1 m cells (TINY) drives the uploaded map laid at 1 m cells, the grid and step
    limit following the map (its suggestion at 0.5 m cells would be a grid of 18); an unknown id
    and a file on the server's disk are refused, naming the field."""
    from quicknav_client import QuickNavClient

    meta = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))]).json()
    r = httpx.post(f"{server.url}/jobs/train", json={"preset": "demo", "overrides": TINY})
    assert r.status_code == 202, r.text
    train = r.json()
    worker = server.worker()
    worker.run_burst(poll_s=0.05)
    assert wait_status(server.url, train["id"], {"succeeded", "failed"})["status"] == "succeeded"
    with QuickNavClient(server.url) as qn:
        ev = qn.evaluate(train["id"], map=meta["ref"], episodes=4)
    env = ev.raw["config"]["env"]
    assert (env["rooms"], env["maps"]["train"]) == ("maps", [meta["ref"]]), env
    assert env["room_size"] / env["grid_size"] == 1.0 and env["grid_size"] == 10, env  # 7.6 m + the ring
    assert meta["suggested_env"]["grid_size"] == 18 and env["max_steps"] != 60, env
    assert ev.raw["request"]["map"] == meta["ref"]
    worker.run_burst(poll_s=0.05)
    assert wait_status(server.url, ev.id, {"succeeded", "failed"})["status"] == "succeeded"
    replay = json.loads(httpx.get(f"{server.url}/jobs/{ev.id}/artifacts/replay.json").content)
    assert {e["map"] for e in replay["episodes"]} == {meta["ref"]}
    for bad, says in (("map:0123456789abcdef", "no such map"), ("/etc/hostname", "only maps uploaded")):
        r = httpx.post(f"{server.url}/jobs/eval", json={"job_id": train["id"], "map": bad})
        assert r.status_code == 422, r.text
        [item] = r.json()["detail"]
        assert item["loc"][-1] == "map" and says in item["msg"], item
    # how the map is read goes with it (env maps.<field>), the map lists may not
    r = httpx.post(f"{server.url}/jobs/eval", json={"job_id": train["id"], "map": meta["ref"],
                                                    "env": {"maps.unknown": "free"}})  # fmt: skip
    assert r.status_code == 202, r.text
    maps = r.json()["config"]["env"]["maps"]
    assert (maps["train"], maps["test"], maps["unknown"]) == ([meta["ref"]], None, "free"), maps
    r = httpx.post(f"{server.url}/jobs/eval", json={"job_id": train["id"], "map": meta["ref"],
                                                    "env": {"maps.test": ["map:0123456789abcdef"]}})  # fmt: skip
    assert r.status_code == 422, r.text
    [item] = r.json()["detail"]
    assert item["loc"][-2:] == ["env", "maps.test"] and "the request's map" in item["msg"], item


def test_rollout_start_on_an_uploaded_map_steps_as_the_env_on_the_file(tmp_path):
    """A gRPC Start naming map:<id> runs the rooms the same map gives as a file on disk."""
    import jax
    import jax.numpy as jnp
    from quicknav_client.rollout import RolloutClient, RolloutError

    from quicknav_core.config import EnvConfig
    from quicknav_core.env.batch import env_and_params
    from quicknav_service.maps import UploadedFile, library
    from quicknav_service.rollout.server import BackgroundServer
    from quicknav_service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", host="127.0.0.1", grpc_port=0, max_envs=16)
    meta = library(settings).add([UploadedFile("room.yaml", yaml_for()),
                                  UploadedFile("room.pgm", pgm(room_picture()))])  # fmt: skip
    (tmp_path / "room.yaml").write_bytes(yaml_for())
    (tmp_path / "room.pgm").write_bytes(pgm(room_picture()))
    base = {"rooms": "maps", "grid_size": 18, "room_size": 9.0, "train_rooms": 4, "test_rooms": 4,
            "lidar_beams": 8, "max_steps": 50}  # fmt: skip
    srv = BackgroundServer(settings, port=0).start()
    try:
        with RolloutClient(f"127.0.0.1:{srv.port}") as rc:
            started = rc.start(num_envs=4, seed=3, config={**base, "maps": {"train": [meta["ref"]]}})
            assert started.env_config["maps"]["train"] == [meta["ref"]]
            env, params = env_and_params(EnvConfig(**base, maps={"train": [str(tmp_path / "room.yaml")]}), "train")
            _, sub, _ = jax.random.split(jax.random.PRNGKey(3), 3)
            obs, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(sub, 4), params)
            np.testing.assert_allclose(started.observations, np.asarray(obs), rtol=1e-4, atol=1e-5)
            rc.step(np.zeros((4, 2), np.float32))
            rc.close()
        with RolloutClient(f"127.0.0.1:{srv.port}") as rc, pytest.raises(RolloutError, match="POST /maps"):
            rc.start(num_envs=4, seed=3, config={**base, "maps": {"train": ["/home/me/room.yaml"]}})
        del jnp
    finally:
        srv.stop()


def _write_map(folder) -> None:
    (folder / "room.yaml").write_bytes(yaml_for())
    (folder / "room.pgm").write_bytes(pgm(room_picture()))


def test_sdk__upload_list_preview_download_delete(server, tmp_path):
    from quicknav_client import BadRequest, Conflict, NotFound, QuickNavClient

    _write_map(tmp_path)
    with QuickNavClient(server.url) as qn:
        m = qn.upload_map(tmp_path / "room.yaml", name="room")  # the .pgm it names goes with it
        assert m["ref"] == f"map:{m['id']}" and m["files"] == ["room.yaml", "room.pgm"]
        assert [x["id"] for x in qn.maps()] == [m["id"]] and qn.map(m["ref"])["name"] == "room"
        png_path = qn.map_preview(m["id"], tmp_path / "p.png")
        assert Image.open(png_path).size == (152, 152)
        got = qn.download_map(m["ref"], tmp_path / "back")
        assert got == tmp_path / "back" / "map.yaml" and (tmp_path / "back" / "map.pgm").read_bytes() == pgm(room_picture())
        assert np.array_equal(load_map(got).blocked, load_map(tmp_path / "room.yaml").blocked)
        with pytest.raises(BadRequest, match="give its resolution"):
            qn.upload_map(tmp_path / "back" / "map.pgm")
        with pytest.raises(FileNotFoundError, match="no such map file"):
            qn.upload_map(tmp_path / "missing.yaml")
        (tmp_path / "lost.yaml").write_bytes(yaml_for("lost.pgm"))
        with pytest.raises(FileNotFoundError, match=r"lost\.yaml names image 'lost\.pgm', which is not"
                                                    rf" there \({tmp_path}/lost\.pgm: no such file\)"):  # fmt: skip
            qn.upload_map(tmp_path / "lost.yaml")
        job = qn.train(preset="demo", overrides={**TINY, "env.rooms": "maps", "env.maps.train": [m["ref"]],
                                                 "env.grid_size": 18, "env.room_size": 9.0})  # fmt: skip
        with pytest.raises(Conflict, match=job.id):
            qn.delete_map(m["id"])
        job.cancel()
        qn.delete_map(m["id"])
        with pytest.raises(NotFound):
            qn.map(m["id"])


def test_sdk__async_client_uploads_and_lists(server, tmp_path):
    import asyncio

    from quicknav_client import AsyncQuickNavClient

    _write_map(tmp_path)

    async def go():
        async with AsyncQuickNavClient(server.url) as qn:
            m = await qn.upload_map(tmp_path / "room.pgm", resolution=RES)
            assert [x["id"] for x in await qn.maps()] == [m["id"]]
            assert (await qn.download_map(m["id"], tmp_path / "back")).name == "map.yaml"
            await qn.delete_map(m["ref"])
            return await qn.maps()

    assert asyncio.run(go()) == []


def test_cli__maps_upload_list_show_delete(server, tmp_path):
    from typer.testing import CliRunner

    from quicknav_cli.main import app

    _write_map(tmp_path)
    cli = CliRunner()
    url = ["maps", "--url", server.url]
    up = cli.invoke(app, [*url, "upload", str(tmp_path / "room.yaml"), "--name", "my room"])
    assert up.exit_code == 0, up.output
    map_id = up.output.split()[1]
    assert up.output.startswith(f"map {map_id} (my room): 152 x 152 pixels at 0.05 m, 7.6 m x 7.6 m")
    assert f"--set env.maps.train='[\"map:{map_id}\"]' --set env.grid_size=18 --set env.room_size=9" in up.output
    listed = cli.invoke(app, [*url, "list"])
    assert listed.exit_code == 0 and map_id in listed.output and "my room" in listed.output
    # 8 characters of the id are enough, as for jobs; fewer is refused, an unknown prefix is 404
    # the same files again under another name: the same map, renamed (not silently the old name)
    again = cli.invoke(app, [*url, "upload", str(tmp_path / "room.yaml"), "--name", "lab"])
    assert again.exit_code == 0 and again.output.split()[1] == map_id and "(lab)" in again.output, again.output
    assert httpx.get(f"{server.url}/maps/{map_id}").json()["name"] == "lab"
    short = cli.invoke(app, [*url, "show", map_id[:8]])
    assert short.exit_code == 0 and map_id in short.output, short.output
    assert httpx.get(f"{server.url}/maps/{map_id[:8]}/files/map.yaml").status_code == 200
    assert httpx.get(f"{server.url}/maps/{map_id[:7]}").status_code == 422
    unknown = "0123456789abcdef"[: 8] if not map_id.startswith("01234567") else "fedcba98"
    assert httpx.get(f"{server.url}/maps/{unknown}").status_code == 404
    shown = cli.invoke(app, [*url, "show", map_id, "--preview", str(tmp_path / "p.png"),
                             "--download", str(tmp_path / "dl")])  # fmt: skip
    assert shown.exit_code == 0, shown.output
    assert (tmp_path / "p.png").is_file() and (tmp_path / "dl" / "map.pgm").is_file()
    bad = cli.invoke(app, [*url, "upload", str(tmp_path / "room.pgm")])
    assert bad.exit_code == 1 and "give its resolution" in bad.output
    gone = cli.invoke(app, [*url, "delete", f"map:{map_id}"])
    assert gone.exit_code == 0 and f"deleted map {map_id}" in gone.output
    missing = cli.invoke(app, [*url, "show", map_id])
    assert missing.exit_code == 1 and "no map" in missing.output


def test_sweep_job_on_an_uploaded_map__its_trial_batches_read_it_on_the_worker(server):
    from tests.core.test_sweep import BASE, SPACE

    meta = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))]).json()
    base = {**BASE, "env": {**BASE["env"], "rooms": "maps", "maps": {"train": [meta["ref"]]},
                            "grid_size": 18, "room_size": 9.0}}  # fmt: skip
    r = httpx.post(f"{server.url}/jobs/sweep", json={"config": {
        "base": base, "space": SPACE, "trials": 2, "parallel": 1, "eval_episodes": 4,
        "objective": "return"}})  # fmt: skip
    assert r.status_code == 202, r.text
    sweep = r.json()
    server.worker().run_burst(poll_s=0.05)
    done = wait_status(server.url, sweep["id"], {"succeeded", "failed"})
    assert done["status"] == "succeeded", done["error"]
    batches = httpx.get(f"{server.url}/jobs", params={"kind": "trial"}).json()["data"]
    assert len(batches) == 2 and all(b["status"] == "succeeded" for b in batches)
    assert all(b["config"]["sweep"]["base"]["env"]["maps"]["train"] == [meta["ref"]] for b in batches)
    from quicknav_service.maps import maps_named

    assert all(maps_named(b["config"]) == {meta["id"]} for b in batches)  # what DELETE's 409 reads


def test_upload__concurrent_big_images_are_read_within_the_decode_budget(tmp_path):
    """Six 4000 x 4000 PNGs uploaded at once to a `quicknav serve` with QUICKNAV_MAP_DECODE_MB=450:
    each holds its share (24 bytes a pixel, 366 MB) while it is read, so they are read one after
    another and the API's peak memory grows by about one image's worth, not six (the adversarial
    run saw 2.8 GB for six 5000 x 5000 ones)."""
    import concurrent.futures

    from tests.service.conftest import free_port, quicknav_process, wait_until_up

    port = free_port()
    proc = quicknav_process(["serve", "--port", str(port), "--no-grpc"], QUICKNAV_DATA_DIR=str(tmp_path),
                            QUICKNAV_EMBEDDED_WORKER="false", QUICKNAV_MAP_DECODE_MB="450")  # fmt: skip
    url = f"http://127.0.0.1:{port}"

    def peak_mb() -> float:
        status = Path(f"/proc/{proc.pid}/status").read_text()
        return int(status.split("VmHWM:")[1].split()[0]) / 1024

    try:
        wait_until_up(url, proc)
        pictures = []
        for k in range(6):  # six different maps (the same files would be one map)
            img = np.full((4000, 4000), 254, np.uint8)
            img[:, : 3 + k] = 0
            img[:3] = 0
            pictures.append(png(img))
        # warm: the first upload's imports and the preview code, before the baseline
        assert upload(url, [("small.png", png(room_picture()))], resolution=RES).status_code == 201
        before = peak_mb()
        with concurrent.futures.ThreadPoolExecutor(6) as pool:
            answers = list(pool.map(lambda b: httpx.post(f"{url}/maps", files=[("files", ("big.png", b))],
                                                         data={"resolution": "0.05"}, timeout=120),
                                    pictures))  # fmt: skip
        assert [a.status_code for a in answers] == [201] * 6, [a.text[:300] for a in answers]
        grown = peak_mb() - before
        assert grown < 800, f"peak memory grew by {grown:.0f} MB for six 16-Mpixel maps"
    finally:
        proc.terminate()
        proc.wait(30)


def test_upload__waits_for_the_decode_budget_then_503_with_retry_after(server):
    """While other uploads hold the memory for reading maps, an upload waits; past the wait it is
    503 with Retry-After, naming the setting, and nothing is stored."""
    budget = server.app.state.map_decode_budget
    budget.wait_s = 0.3
    with budget.hold(budget.total, "another upload"):
        r = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))])
    assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
    assert "QUICKNAV_MAP_DECODE_MB" in r.json()["detail"] and r.json()["detail"].startswith("files: room.pgm")
    assert httpx.get(f"{server.url}/maps").json()["count"] == 0
    r = upload(server.url, [("room.yaml", yaml_for()), ("room.pgm", pgm(room_picture()))])
    assert r.status_code == 201, r.text


def corridor_picture(length_m: float, width_m: float, res: float) -> np.ndarray:
    """A straight corridor ``length_m`` long and ``width_m`` wide (walls one pixel thick)."""
    h, w = round((width_m + 2 * res) / res), round(length_m / res)
    img = np.full((h, w), OCCUPIED, np.uint8)
    img[1:-1, 1:-1] = FREE
    return img


@pytest.mark.parametrize("length_m,res", [(20.0, 0.1), (40.0, 0.2), (70.0, 0.2), (140.0, 0.25)])
def test_upload__suggestion_sets_a_step_limit_and_says_what_the_server_and_the_cells_allow(
    tmp_path, length_m, res
):
    """A long corridor: the suggested step limit covers its longest path (twice it, at full speed,
    as `quicknav eval --map` sets it); a grid above this server's QUICKNAV_MAX_GRID_SIZE (64) says
    so and names the setting; a map larger than any grid at 0.5 m cells says so."""
    from quicknav_core.config import EnvConfig

    with LiveServer(tmp_path, max_map_pixels=400_000) as server:
        r = upload(server.url, [("corridor.png", png(corridor_picture(length_m, 2.0, res)))], resolution=res)
    assert r.status_code == 201, r.text
    m = r.json()
    env, notes = m["suggested_env"], m["notes"]
    grid = int(np.ceil(length_m / 0.5)) + 2
    assert env["grid_size"] == grid and env["room_size"] == grid * 0.5
    if grid <= 256:
        step_m = EnvConfig().max_wheel_speed * EnvConfig().dt
        assert env["max_steps"] >= 2 * (length_m - 2) / step_m, env  # end to end, at full speed, twice
        # the grid follows the corridor's shape: 5 cells across (2 m and its walls) and the ring
        assert env["grid_rows"] == 7 and "grid_cols" not in env, env
        assert EnvConfig.model_validate(env).grid_shape == (7, grid)
    limit = [n for n in notes if "this server's limit" in n]
    if grid <= 64:
        assert limit == [], notes
    elif grid <= 256:
        assert len(limit) == 1 and f"grid_size {grid} is above this server's limit of 64" in limit[0]
        assert "QUICKNAV_MAX_GRID_SIZE, which the operator can raise to 256" in limit[0], notes
    else:
        assert "max_steps" not in env and any("above the 256 an env may have" in n for n in notes), notes
        assert all("/tmp" not in n for n in notes), notes  # the client's file name, not a server path


def test_upload__a_map_that_loses_free_space_at_half_metre_cells_says_so(server):
    """A room whose doorway is narrower than a 0.5 m cell: the grid keeps only one side."""
    n = round(6.0 / RES)
    img = np.full((n, n), OCCUPIED, np.uint8)
    img[2:-2, 2:-2] = FREE
    img[:, n // 2 - 2 : n // 2 + 2] = OCCUPIED  # a wall down the middle ...
    img[n // 2 - 3 : n // 2 + 3, n // 2 - 2 : n // 2 + 2] = FREE  # ... with a 0.3 m gap
    r = upload(server.url, [("split.png", png(img))], resolution=RES)
    assert r.status_code == 201, r.text
    (note,) = r.json()["notes"]
    assert "split.png: at 0.5 m cells the grid keeps" in note and "of the map's free space" in note, note
