import json

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import EnvConfig
from quicknav_core.env.numpy_env import QuickNavNumpyEnv
from quicknav_core.env.render import episode_frames, render_frame, save_gif
from tests.journeys.readme import ROOT

runner = CliRunner()


def test_render_frame__draws_rays_by_hit_type():
    cfg = EnvConfig(grid_size=8, train_rooms=4)
    env = QuickNavNumpyEnv(cfg)
    env.reset(seed=0)
    snap = env.snapshot()
    rgb = render_frame(snap, cfg)
    assert rgb.dtype == np.uint8 and rgb.shape[2] == 3
    red = (rgb[..., 0] > 180) & (rgb[..., 1] < 80) & (rgb[..., 2] < 80)
    assert red.sum() > 20, "wall-hitting rays are drawn red"
    # a snapshot with every beam on the goal draws green rays and no red
    snap["lidar_hits"] = np.full_like(snap["lidar_hits"], 2)
    rgb2 = render_frame(snap, cfg)
    red2 = (rgb2[..., 0] > 180) & (rgb2[..., 1] < 80) & (rgb2[..., 2] < 80)
    assert red2.sum() < red.sum() / 4


def test_gif__has_one_frame_per_snapshot(tmp_path):
    cfg = EnvConfig(grid_size=8, train_rooms=4)
    env = QuickNavNumpyEnv(cfg)
    env.reset(seed=1)
    snaps = [env.snapshot()]
    for _ in range(4):
        env.step([1.0, 0.5])
        snaps.append(env.snapshot())
    path = save_gif(episode_frames(snaps, cfg, size_px=160), tmp_path / "ep.gif")
    with Image.open(path) as im:
        assert im.n_frames == 5


def test_cli_env_demo__writes_png_and_gif(tmp_path):
    result = runner.invoke(app, ["env", "demo", "--out", str(tmp_path), "--set", "grid_size=8"])
    assert result.exit_code == 0, result.output
    assert "reached the goal" in result.output
    assert Image.open(tmp_path / "demo.png").size[0] >= 300
    with Image.open(tmp_path / "demo.gif") as im:
        assert im.n_frames > 3


def test_cli_env_demo__on_a_map_lays_it_as_eval_does_and_names_the_option_when_it_cannot(tmp_path):
    office = ROOT / "examples/maps/office.yaml"  # 21.2 m x 13.2 m: 22 x 14 cells of 1 m
    result = runner.invoke(app, ["env", "demo", "--out", str(tmp_path), "--map", str(office),
                                 "--set", "room_size=16", "--set", "grid_size=16"])  # fmt: skip
    assert result.exit_code == 0, result.output
    # the env's 1 m cells (room_size 16 / grid_size 16): the grid that holds the map, and its wall
    assert f"on {office}: grid 16 x 24 (rows x cols) of 1 m cells, step limit" in " ".join(result.output.split())
    assert "reached the goal" in result.output
    with Image.open(tmp_path / "demo.gif") as im:
        assert im.n_frames > 3
    missing = runner.invoke(app, ["env", "demo", "--out", str(tmp_path), "--map", str(tmp_path / "no.yaml")])
    assert missing.exit_code == 2 and "--map: " in missing.output and "no such file" in missing.output
    # a 30 m x 2 m corridor at 0.1 m cells would need a grid of 302: refused before anything
    # compiles, naming the env's cells (no policy here) and the cell size that fits
    (tmp_path / "long.pgm").write_bytes(b"P5 300 20 255\n" + bytes([254]) * (300 * 20))
    (tmp_path / "long.yaml").write_text("image: long.pgm\nresolution: 0.1\norigin: [0, 0, 0]\n"
                                        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")
    big = runner.invoke(app, ["env", "demo", "--out", str(tmp_path), "--map", str(tmp_path / "long.yaml"),
                              "--set", "room_size=6.4", "--set", "grid_size=64"])  # fmt: skip
    said = " ".join(big.output.split())
    assert big.exit_code == 2 and "--map: " in said and "at the env's 0.1 m cells" in said, said
    assert "a grid of 302, above the 256" in said and "cells of at least 0.12 m" in said, said


def test_cli_env_rooms__writes_figure(tmp_path):
    out = tmp_path / "rooms.png"
    result = runner.invoke(app, ["env", "rooms", "--out", str(out), "--per-row", "2"])
    assert result.exit_code == 0, result.output
    assert Image.open(out).size[0] > 300
    # a name without a suffix gets the PNG's, and the line says the file written (it said "rooms")
    named = runner.invoke(app, ["env", "rooms", "--out", str(tmp_path / "figure"), "--per-row", "2"])
    assert named.exit_code == 0 and (tmp_path / "figure.png").is_file(), named.output
    assert named.output.replace("\n", "").endswith("figure.png"), named.output


def test_cli__bad_config_is_reported_with_field_and_range(tmp_path):
    result = runner.invoke(app, ["env", "demo", "--out", str(tmp_path), "--set", "lidar_beams=0"])
    assert result.exit_code == 2
    assert "lidar_beams" in result.output and "greater than or equal to 1" in result.output
    bad = tmp_path / "cfg.json"
    bad.write_text(json.dumps({"grid_size": 8, "robot_radius": 0.9}))  # fits in no cave's passages
    result = runner.invoke(app, ["env", "demo", "--config", str(bad)])
    assert result.exit_code == 2 and "robot_radius: a robot of radius 0.9 m fits in" in result.output
    result = runner.invoke(app, ["env", "demo", "--policy", "smart"])
    assert result.exit_code == 2 and "allowed values" in result.output


def test_fit_title__a_long_title_stays_inside_a_320_px_frame():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from quicknav_core.env.render import fit_title

    title = "trained 0123456789abcdef (rppo-lstm) · test room 117 · step 243/300 · success · SPL 0.91"
    fig = plt.figure(figsize=(3.2, 3.2), dpi=100)
    try:
        ax = fig.add_axes((0.02, 0.02, 0.96, 0.90))
        renderer = fig.canvas.get_renderer()
        plain = ax.set_title(title, fontsize=9.0).get_window_extent(renderer)
        assert plain.x0 < 0 or plain.x1 > fig.bbox.width  # what the GIFs showed: cut off at both ends
        fit_title(fig, ax, title)
        box = ax.title.get_window_extent(renderer)
        assert box.x0 >= 0 and box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height
        assert ax.title.get_text().replace("\n", " ").split()[-1] == "0.91"  # nothing dropped
    finally:
        plt.close(fig)


def test_gif__one_palette_keeps_every_frame_and_a_colour_only_one_unsampled_frame_has(tmp_path):
    from matplotlib.colors import to_rgb

    from quicknav_core.env.render import FREE_COLOUR, PATH_COLOUR, RAY_COLOURS, WALL_COLOUR

    def rgb(name):
        return np.array([round(255 * c) for c in to_rgb(name)], np.uint8)

    frames = []
    for i in range(40):  # the palette samples every second frame: frame 7 is not among them
        f = np.empty((64, 96, 3), np.uint8)
        f[:] = rgb(FREE_COLOUR)
        f[:, : 2 + 2 * i] = rgb(WALL_COLOUR)  # a wall edge that moves: no two frames alike
        f[40:44, 10:60] = rgb(PATH_COLOUR)
        if i == 7:
            f[10:20, 70:90] = rgb(RAY_COLOURS[2])  # a ray that hit the goal, in this frame only
        frames.append(f)
    path = save_gif(frames, tmp_path / "f.gif")
    with Image.open(path) as im:
        assert im.n_frames == 40
        for i in (0, 7, 39):
            im.seek(i)
            assert np.array_equal(np.asarray(im.convert("RGB")), frames[i]), i
    with pytest.raises(ValueError, match="one size"):
        save_gif([frames[0], frames[0][:32]], tmp_path / "g.gif")


def test_frame_drawer__blitted_frames_are_the_pixels_of_a_whole_draw():
    """Frames drawn over the saved background (room, goal) equal a whole redraw of the figure:
    across episodes, a short title, one long enough to wrap onto two lines, and none."""
    from quicknav_core.env.render import FrameDrawer

    cfg = EnvConfig(grid_size=8, train_rooms=4)
    env = QuickNavNumpyEnv(cfg)
    rng = np.random.default_rng(0)
    titles = [lambda t: f"episode 1  t={t}", lambda t: "a title far too long to fit on one line " * 2 + str(t),
              lambda t: None]  # fmt: skip
    with FrameDrawer(cfg, size_px=160) as drawer:
        for episode, title in enumerate(titles):
            env.reset(seed=episode)
            path = []
            for t in range(4):
                snap = env.snapshot()
                path.append(snap["pos"])
                frame = drawer.draw(snap, np.array(path), title=title(t))
                drawer.fig.canvas.draw()  # the whole figure, as every frame was drawn before
                whole = np.asarray(drawer.fig.canvas.buffer_rgba())[..., :3]
                assert np.array_equal(frame, whole), (episode, t)
                env.step(rng.uniform(-1, 1, 2))


def test_frame_drawer__draws_the_plan_boxes_and_people_where_they_are():
    """The global plan (dashed), a box and a person at their places, in their colours; frames
    over the saved background equal a whole draw with them too, and a frame without them after
    one with them shows none."""
    from matplotlib.colors import to_rgb

    from quicknav_core.env.render import BOX_COLOUR, PERSON_COLOUR, PLAN_COLOUR, FrameDrawer

    cfg = EnvConfig(grid_size=8, room_size=4.0, train_rooms=4, obstacles={"static": 1, "moving": 1})
    walls = np.zeros((8, 8), bool)
    walls[0], walls[-1], walls[:, 0], walls[:, -1] = True, True, True, True
    size = 200
    pixel = lambda x, y: (int(size - (0.02 + 0.96 * y / 4.0) * size), int((0.02 + 0.96 * x / 4.0) * size))  # noqa: E731
    colour = lambda frame, x, y: frame[pixel(x, y)] / 255.0  # noqa: E731
    snap = {"walls": walls, "pos": np.array([0.9, 3.1]), "theta": 0.0, "goal": np.array([3.1, 3.1]),
            "plan": np.array([[0.75, 0.75], [3.25, 0.75], [3.25, 3.1]]),
            "boxes": np.array([[1.5, 2.0, 0.25]]), "people": np.array([[2.5, 2.0, 0.25]])}  # fmt: skip
    with FrameDrawer(cfg, size_px=size) as drawer:
        frame = drawer.draw(snap)
        drawer.fig.canvas.draw()
        assert np.array_equal(frame, np.asarray(drawer.fig.canvas.buffer_rgba())[..., :3])
        np.testing.assert_allclose(colour(frame, 1.5, 2.0), to_rgb(BOX_COLOUR), atol=0.02)
        np.testing.assert_allclose(colour(frame, 2.5, 2.0), to_rgb(PERSON_COLOUR), atol=0.02)
        # the dashed line, antialiased over two rows of pixels: some of its pixels near its colour
        near_plan = lambda f, x: np.linalg.norm(colour(f, x, 0.75) - to_rgb(PLAN_COLOUR)) < 0.25  # noqa: E731
        assert sum(near_plan(frame, x) for x in np.linspace(1.0, 3.0, 40)) >= 10
        bare = drawer.draw({k: snap[k] for k in ("walls", "pos", "theta", "goal")})
        for x, y in ((1.5, 2.0), (2.5, 2.0)):
            assert not np.allclose(colour(bare, x, y), to_rgb(BOX_COLOUR), atol=0.1)
            assert not np.allclose(colour(bare, x, y), to_rgb(PERSON_COLOUR), atol=0.1)
        assert not any(near_plan(bare, x) for x in np.linspace(1.0, 3.0, 40))


def test_as_snapshot__a_twin_state_gives_its_plan_and_obstacles():
    """A NumPy twin's snapshot (plan as a field, obstacles as arrays) becomes what the drawer
    draws: the plan's points from the robot to the goal, the boxes and people present."""
    from quicknav_core.env.render import as_snapshot

    cfg = EnvConfig(rooms="floorplan", grid_size=16, room_size=8.0, train_rooms=8, test_rooms=4,
                    observe_plan=True, obstacles={"static": 4, "moving": 3})  # fmt: skip
    env = QuickNavNumpyEnv(cfg)
    env.reset(seed=1)
    state = env.snapshot()
    snap = as_snapshot(state, cfg)
    np.testing.assert_allclose(snap["plan"][0], state["pos"], atol=1e-5)
    np.testing.assert_allclose(snap["plan"][-1], state["goal"], atol=1e-5)
    # the plan's cells go down the twin's field one neighbour at a time
    cells = np.floor(snap["plan"][1:-1][:, ::-1] / cfg.cell_size).astype(int)
    values = state["plan"][cells[:, 0], cells[:, 1]]
    assert np.all(np.diff(values) < 0) and np.abs(np.diff(cells, axis=0)).max() <= 1
    radius = state["obstacles"]["radius"]
    assert len(snap["boxes"]) == (radius[:4] > 0).sum() and len(snap["people"]) == (radius[4:] > 0).sum()
    assert len(snap["boxes"]) + len(snap["people"]) > 0
    assert "plan" not in as_snapshot(state)  # without the config, no cell size: not drawn
