"""Pictures of a map show the map, not the square grid it lies in: a map is laid at the lower left
of the smallest square grid that holds it (the rest of the square is wall), so a picture of the
whole square would be mostly wall. ``render.map_view`` is the free cells' bounding box with the
ring of wall around it; the GIF frames and the trajectories picture show that, generated rooms
whole. (The browser's replay does the same in JavaScript: tests/service/test_web_maps_browser.py
holds it to ``map_view``.)"""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgb

from quicknav_core.config import EnvConfig
from quicknav_core.env import render
from quicknav_core.env.maps import map_room
from tests.journeys.readme import ROOT

OFFICE = ROOT / "examples/maps/office.yaml"  # 21.2 m x 13.2 m


def test_map_view__the_free_cells_bounding_box_and_the_wall_ring_around_it():
    walls = np.ones((10, 10), dtype=bool)
    walls[2:5, 3:8] = False  # rows 2-4 (y 2-5 m), columns 3-7 (x 3-8 m), 1 m cells
    assert render.map_view(walls, 10.0) == (2.0, 9.0, 1.0, 6.0)
    walls[:] = False  # free up to the edge: nothing beyond the grid
    assert render.map_view(walls, 10.0) == (0.0, 10.0, 0.0, 10.0)
    walls[:] = True  # no free cell: the whole room
    assert render.map_view(walls, 10.0) == (0.0, 10.0, 0.0, 10.0)


def test_room_view__a_map_is_shown_by_its_extent_a_generated_room_whole():
    walls = map_room(OFFICE, 0.5, 64)  # 43 x 27 cells of map in a 64 x 64 grid
    free_rows = np.flatnonzero((~walls).any(axis=1))
    free_cols = np.flatnonzero((~walls).any(axis=0))
    on_map = EnvConfig(rooms="maps", maps={"train": [str(OFFICE)]}, grid_size=64, room_size=32.0)
    x0, x1, y0, y1 = render.room_view(walls, on_map)
    assert (x0, x1) == ((free_cols[0] - 1) * 0.5, (free_cols[-1] + 2) * 0.5)
    assert (y0, y1) == ((free_rows[0] - 1) * 0.5, (free_rows[-1] + 2) * 0.5)
    assert x1 - x0 <= 21.2 + 1.0 and y1 - y0 <= 13.2 + 1.0  # the map's size and the ring
    caves = EnvConfig(grid_size=64, room_size=32.0)
    assert render.room_view(walls, caves) == (0.0, 32.0, 0.0, 32.0)


@pytest.mark.parametrize("rooms", ["maps", "carved"])
def test_frames__show_the_rooms_view_and_draw_the_robot_inside_it(rooms):
    walls = map_room(OFFICE, 0.5, 64)
    on = {"rooms": "maps", "maps": {"train": [str(OFFICE)]}} if rooms == "maps" else {}
    cfg = EnvConfig(grid_size=64, room_size=32.0, robot_radius=0.5, **on)  # a robot of a few pixels
    free = np.argwhere(~walls)
    r, c = free[len(free) // 2]
    pos = np.array([(c + 0.5) * 0.5, (r + 0.5) * 0.5])
    snap = {"walls": walls, "pos": pos, "theta": np.float32(0.0), "goal": pos + 0.5}
    with render.FrameDrawer(cfg, 320) as drawer:
        frame = drawer.draw(snap)
        x0, x1, y0, y1 = render.room_view(walls, cfg)
        assert drawer.ax.get_xlim() == pytest.approx((x0, x1)) and drawer.ax.get_ylim() == pytest.approx((y0, y1))
        # the robot's pixel: where the axes put it, in the frame's pixels (y down), behind its
        # centre (its heading, drawn white over it, points along +x)
        px, py = drawer.ax.transData.transform(pos - [0.25, 0.0])
    robot = np.array([int(v * 255) for v in to_rgb(render.ROBOT_COLOUR)])
    assert np.abs(frame[frame.shape[0] - round(py), round(px)].astype(int) - robot).max() <= 2
    # a map fills the frame's width (the office is wider than tall); a whole 32 m room does not
    # leave the map most of it: the share of the frame's columns the map's light floor reaches
    floor = np.array([int(v * 255) for v in to_rgb(render.FREE_COLOUR)])
    columns = (np.abs(frame.astype(int) - floor).max(axis=2) <= 2).any(axis=0).mean()
    assert columns > 0.8 if rooms == "maps" else columns < 0.7, columns


def test_saved_pictures__cut_the_rows_a_wide_map_leaves_blank_and_keep_a_square_room_whole(tmp_path):
    from PIL import Image

    walls = map_room(OFFICE, 0.5, 64)  # wider than tall: its view sits at the top of the frame
    free = np.argwhere(~walls)
    r, c = free[len(free) // 2]
    pos = np.array([(c + 0.5) * 0.5, (r + 0.5) * 0.5])
    shown = {}
    for rooms in ("maps", "carved"):
        on = {"rooms": "maps", "maps": {"train": [str(OFFICE)]}} if rooms == "maps" else {}
        cfg = EnvConfig(grid_size=64, room_size=32.0, **on)
        snaps = [{"walls": walls, "pos": pos + np.array([0.1 * t, 0.0]), "theta": np.float32(0.0), "goal": pos + 1.0}
                 for t in range(3)]  # fmt: skip
        frames = render.episode_frames(snaps, cfg, title=rooms, size_px=320)
        with Image.open(render.save_gif(frames, tmp_path / f"{rooms}.gif")) as im:
            assert im.n_frames == 3
            shown[rooms] = im.size
            im.seek(2)
            # what is kept is the frame's top, pixel for pixel (up to the GIF's palette)
            kept = np.asarray(im.convert("RGB")).astype(int)
            assert np.abs(kept - frames[2][: kept.shape[0]].astype(int)).mean() < 2.0
        png = np.asarray(Image.open(render.save_png(frames[-1], tmp_path / f"{rooms}.png")).convert("RGB"))
        assert png.shape[:2] == shown[rooms][::-1]
    assert shown["carved"] == (320, 320)  # a whole room, drawn down to its margin: as it was
    # the office is 21.2 m x 13.2 m: the frame keeps its title and the map, and about 2 % below
    width, height = shown["maps"]
    assert width == 320 and 0.6 * 320 < height < 0.8 * 320, shown


def test_gif_frames__follow_a_long_narrow_maps_shape():
    """``gif_frame_size``: a square frame for rooms and maps of any shape up to twice as long as
    wide; a tall frame (at most as wide as the square) for views all at least twice as tall, a
    wide one for views all at least twice as wide; and a frame of that size draws the tall map
    filling its height."""
    assert render.gif_frame_size([(0.0, 8.0, 0.0, 8.0)], 320) == (320, 320)
    assert render.gif_frame_size([(0.0, 21.2, 0.0, 13.2)], 320) == (320, 320)  # the office
    assert render.gif_frame_size([(0.0, 16.0, 0.0, 2.0)] * 3, 320) == (560, 560)  # cut by save_gif
    width, height = render.gif_frame_size([(0.0, 5.5, 0.0, 31.0)] * 3, 320)  # a corridor
    assert height == 560 and 200 <= width < 320, (width, height)
    assert render.gif_frame_size([(0.0, 5.5, 0.0, 31.0), (0.0, 8.0, 0.0, 8.0)], 320) == (320, 320)
    walls = np.ones((32, 32), dtype=bool)
    walls[1:31, 1:5] = False  # 2 m x 15 m of floor at 0.5 m cells
    cfg = EnvConfig(rooms="maps", maps={"train": [str(OFFICE)]}, grid_size=32, room_size=16.0)
    view = render.room_view(walls, cfg)
    size = render.gif_frame_size([view], 320)
    snap = {"walls": walls, "pos": np.array([1.0, 3.0]), "theta": np.float32(0.0), "goal": np.array([1.5, 12.0])}
    with render.FrameDrawer(cfg, size) as drawer:
        frame = drawer.draw(snap, title="a corridor")
    assert frame.shape[:2] == (size[1], size[0])
    floor = np.array([int(v * 255) for v in to_rgb(render.FREE_COLOUR)])
    rows = (np.abs(frame.astype(int) - floor).max(axis=2) <= 2).any(axis=1).mean()
    assert rows > 0.75, rows  # the floor reaches down most of the frame's height
