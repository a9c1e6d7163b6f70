"""Rooms besides caves: generated floor plans and maps of buildings (ROS map_server YAML + PGM).

Checked against independent references: a BFS on the grid for connectivity, the pixels the test
itself drew for the map reader, the oracle driving every plan, and the NumPy twin for the env's
semantics on these rooms.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from quicknav_core.config import EnvConfig
from quicknav_core.env.floorplan import floorplan_bank
from quicknav_core.env.maps import MapError, load_map, to_cells
from quicknav_core.env.room_sources import room_source


def bfs_component(walls: np.ndarray) -> set[tuple[int, int]]:
    """Free cells reachable from the first free cell (4-neighbour), by a plain BFS."""
    free = list(zip(*np.nonzero(~walls), strict=True))
    seen = {free[0]}
    todo = deque([free[0]])
    while todo:
        r, c = todo.popleft()
        for nr, nc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if not walls[nr, nc] and (nr, nc) not in seen:
                seen.add((nr, nc))
                todo.append((nr, nc))
    return seen


# --------------------------------------------------------------------------- floor plans
FLOOR = EnvConfig(rooms="floorplan", grid_size=24, room_size=12.0, train_rooms=64, test_rooms=32)


def test_floorplan__connected_walled_and_held_out():
    rooms = room_source(FLOOR)
    train, test = rooms.bank("train"), rooms.bank("test")
    assert train.shape == (64, 24, 24) and test.shape == (32, 24, 24)
    keys = {r.tobytes() for r in train}
    assert not any(r.tobytes() in keys for r in test)  # held out by layout
    assert len(keys) > 60  # plans differ
    for walls in (*train, *test):
        assert walls[0].all() and walls[-1].all() and walls[:, 0].all() and walls[:, -1].all()
        free = int((~walls).sum())
        assert len(bfs_component(walls)) == free  # every free cell reachable
    # the same config gives the same plans (seeded by room_seed, split and index)
    assert np.array_equal(train, room_source(FLOOR).bank("train"))
    other = room_source(FLOOR.model_copy(update={"room_seed": 1})).bank("train")
    assert not np.array_equal(train, other)


@pytest.mark.parametrize("grid,floorplan", [
    (24, {"door_width": 1, "door_width_max": 2, "corridor_width": 2}),  # the building preset's
    (16, {}),
    (32, {"door_width": 2, "door_width_max": 4, "corridor_width": 0, "loop_prob": 1.0}),
    (20, {"door_width": 3, "corridor_width": 3, "loop_prob": 0.0, "min_room": 3}),
])
def test_floorplan__doors_are_those_found_cell_by_cell(monkeypatch, grid, floorplan):
    """The door search works on whole arrays; the plain search (every wall cell, every width,
    ``tests/core/env/reference.py``) with the same random draws gives the same plans, so banks
    stay what they were."""
    import quicknav_core.env.floorplan as plans
    from tests.core.env.reference import open_doors_cell_by_cell

    cfg = FLOOR.model_copy(update={"grid_size": grid, "room_size": grid / 2,
                                   "floorplan": FLOOR.floorplan.model_copy(update=floorplan)})
    fast = floorplan_bank(cfg, "train", 48)
    monkeypatch.setattr(plans, "_open_doors", open_doors_cell_by_cell)
    plain = floorplan_bank(cfg, "train", 48)
    assert np.array_equal(fast, plain)
    monkeypatch.setattr(plans, "_open_doors", lambda walls, fp, rng: None)
    assert (~fast).sum() > (~floorplan_bank(cfg, "train", 48)).sum()  # doors were opened


def test_floorplan__rooms_doors_and_a_corridor_look_like_a_floor():
    cfg = FLOOR.model_copy(update={"grid_size": 40, "room_size": 20.0})
    bank = floorplan_bank(cfg, "train", 32)
    from scipy import ndimage

    for walls in bank:
        # rooms: wall lines cut the floor into several rectangles; doors are short openings
        interior = (~walls).sum() / (38 * 38)
        assert 0.55 < interior < 0.95
        # a corridor: a free run spanning most of the floor with the given width
        runs = [max(len(r) for r in "".join("1" if v else "0" for v in line).split("1"))
                for line in np.concatenate([~walls, (~walls).T])]  # fmt: skip
        assert max(runs) >= 20
        assert ndimage.label(~walls)[1] == 1
    # with its doors closed (free cells between two walls), a plan without a corridor falls apart
    # into rooms no smaller than min_room x min_room
    plain = cfg.model_copy(update={"floorplan": cfg.floorplan.model_copy(update={"corridor_width": 0})})
    for walls in floorplan_bank(plain, "train", 16):
        inner = walls[1:-1, 1:-1]
        door = ~inner & ((walls[:-2, 1:-1] & walls[2:, 1:-1]) | (walls[1:-1, :-2] & walls[1:-1, 2:]))
        closed = walls.copy()
        closed[1:-1, 1:-1] |= door
        labels, n = ndimage.label(~closed)
        sizes = np.bincount(labels.ravel())[1:]
        assert n >= 3 and sizes.min() >= plain.floorplan.min_room ** 2, (n, sorted(sizes))
    # door_width reaches the generator (the plans change with it)
    wide = cfg.model_copy(update={"floorplan": cfg.floorplan.model_copy(update={"door_width": 2})})
    assert not np.array_equal(floorplan_bank(wide, "train", 4), bank[:4])


def test_floorplan__config_refuses_what_it_cannot_honour():
    with pytest.raises(ValidationError, match=r"env\.floorplan applies only"):
        EnvConfig(floorplan={"door_width": 2})
    with pytest.raises(ValidationError, match="carve_fraction"):
        EnvConfig(rooms="floorplan", carve_fraction=0.5)
    with pytest.raises(ValidationError, match="maps"):
        EnvConfig(rooms="maps")
    with pytest.raises(ValidationError, match="min_room"):
        EnvConfig(rooms="floorplan", floorplan={"min_room": 3, "max_room": 2})


def test_floorplan__the_oracle_solves_every_plan(optimized):
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import run_eval

    env = FLOOR.model_copy(update={"max_steps": 300})
    cfg = EvalConfig(policy="oracle", env=env, episodes=64, split="test", seed=3)
    result, _ = run_eval(cfg)
    assert result["metrics"]["success_rate"] >= 0.98, result["metrics"]


def test_floorplan__numpy_twin_matches_the_jax_env():
    from tests.core.env.test_parity import assert_parity_on

    assert_parity_on(FLOOR.model_copy(update={"train_rooms": 16, "test_rooms": 8}))


# --------------------------------------------------------------------------- maps
def write_pgm(path: Path, grey: np.ndarray) -> None:
    """A binary (P5) PGM, written by hand as map_server's map_saver does."""
    h, w = grey.shape
    path.write_bytes(f"P5\n# CREATOR: test\n{w} {h}\n255\n".encode() + grey.astype(np.uint8).tobytes())


def write_map(folder: Path, blocked_top_down: np.ndarray, resolution: float, origin=(0.0, 0.0),
              negate: bool = False, unknown: np.ndarray | None = None) -> Path:  # fmt: skip
    """A map_server map (YAML + PGM) of the given occupied pixels (top row first, as drawn)."""
    occupied, free = (0, 254) if not negate else (255, 1)
    grey = np.where(blocked_top_down, occupied, free).astype(np.uint8)
    if unknown is not None:
        grey[unknown] = 205
    write_pgm(folder / "map.pgm", grey)
    yaml_path = folder / "map.yaml"
    yaml_path.write_text(
        f"image: map.pgm\nresolution: {resolution}\norigin: [{origin[0]}, {origin[1]}, 0.0]\n"
        f"negate: {int(negate)}\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    return yaml_path


def test_map__round_trip_cells_are_the_occupied_pixels(tmp_path):
    rng = np.random.default_rng(0)
    drawn = rng.random((10, 14)) < 0.2  # top row first
    path = write_map(tmp_path, drawn, resolution=0.5, origin=(-3.0, 2.5))
    m = load_map(path)
    assert m.resolution == 0.5 and m.origin == (-3.0, 2.5) and m.blocked.shape == (10, 14)
    # y up: the picture's bottom row is row 0
    assert np.array_equal(m.blocked, drawn[::-1])
    cells = to_cells(m, cell=0.5, grid=16)  # one pixel per cell
    assert np.array_equal(cells[1:11, 1:15], drawn[::-1])
    assert cells[0].all() and cells[11:].all() and cells[:, 15].all()  # the ring and the padding


def test_map__negated_and_unknown_pixels_are_read_the_right_way(tmp_path):
    drawn = np.zeros((6, 6), dtype=bool)
    drawn[2, 3] = True
    unknown = np.zeros((6, 6), dtype=bool)
    unknown[0, 0] = True
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    plain = load_map(write_map(tmp_path / "a", drawn, 0.5, unknown=unknown))
    negated = load_map(write_map(tmp_path / "b", drawn, 0.5, negate=True))
    expect = drawn.copy()
    expect[0, 0] = True  # unknown counts as wall
    assert np.array_equal(plain.blocked, expect[::-1])
    assert np.array_equal(negated.blocked, drawn[::-1])
    free = load_map(tmp_path / "a" / "map.yaml", unknown_free=True)
    assert np.array_equal(free.blocked, drawn[::-1])


def nav2_reads(pixel: tuple[int, ...], mode: str, negate: bool = False, occ_th: float = 0.65,
               free_th: float = 0.196) -> str:
    """Nav2 map_server's reading of one pixel (map_io's loop, written out): the pixel's red,
    green and blue (a grey pixel's three equal), with its alpha (255 = opaque) as a fourth in
    trinary mode; in scale mode a pixel that is not opaque is unknown."""
    rgb, alpha = list(pixel[:3]), (pixel[3] if len(pixel) == 4 else None)
    channels = rgb + ([alpha] if mode == "trinary" and alpha is not None else [])
    shade = sum(channels) / len(channels) / 255.0
    occ = shade if negate else 1.0 - shade
    if mode == "scale" and alpha is not None and alpha != 255:
        return "unknown"
    return "occupied" if occ > occ_th else "free" if occ < free_th else "unknown"


@pytest.mark.parametrize("image_mode,mode", [("RGB", "trinary"), ("RGBA", "trinary"), ("RGBA", "scale"),
                                             ("LA", "trinary"), ("LA", "scale"), ("P", "trinary")])  # fmt: skip
def test_map__colour_and_alpha_pixels_are_read_as_nav2_reads_them(tmp_path, image_mode, mode):
    """A PNG in colour or with alpha is read by Nav2 map_server's rule (the mean of the channels,
    alpha averaged in for trinary maps, a see-through pixel unknown in scale maps), not by a grey
    conversion's weights: green (0, 255, 0) is occupied to map_server, and the usual unknown grey
    205, opaque in an RGBA picture, is free in trinary mode."""
    from PIL import Image

    rgb = [(0, 0, 0), (254, 254, 254), (205, 205, 205), (0, 255, 0), (255, 255, 0), (0, 0, 255),
           (120, 200, 60), (255, 255, 255), (100, 100, 100), (170, 170, 170)]  # fmt: skip
    alphas = [255, 255, 255, 0, 128, 255, 254, 0, 255, 40]
    if image_mode == "LA":
        pixels = [(r, a) for (r, _, _), a in zip(rgb, alphas, strict=True)]
        seen = [(v, v, v, a) for v, a in pixels]
    elif image_mode == "RGBA":
        pixels = [(*c, a) for c, a in zip(rgb, alphas, strict=True)]
        seen = pixels
    else:
        pixels = seen = rgb
    im = Image.new(image_mode if image_mode != "P" else "RGB", (len(pixels), 1))
    im.putdata(pixels)
    if image_mode == "P":
        im = im.convert("P", palette=Image.Palette.ADAPTIVE, colors=16)
        # the palette's colours, as map_server sees them (one row: a list of RGB tuples)
        seen = [tuple(int(c) for c in px) for px in np.asarray(im.convert("RGB"))[0]]
    im.save(tmp_path / "map.png")
    (tmp_path / "map.yaml").write_text(f"image: map.png\nmode: {mode}\nresolution: 0.5\norigin: [0, 0, 0]\n"
                                       "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n")  # fmt: skip
    expected = [nav2_reads(px, mode) for px in seen]
    assert {"occupied", "free", "unknown"} <= set(expected)  # the row tries every outcome
    m = load_map(tmp_path / "map.yaml")
    got = ["unknown" if u else "occupied" if b else "free" for b, u in zip(m.blocked[0], m.unknown[0], strict=True)]
    assert got == expected, list(zip(seen, got, expected, strict=True))
    free = load_map(tmp_path / "map.yaml", unknown_free=True)
    assert free.blocked[0].tolist() == [e == "occupied" for e in expected]


def test_map__fine_pixels_are_laid_on_cells_conservatively(tmp_path):
    # 0.1 m pixels, 0.5 m cells: one occupied pixel walls exactly the cells it overlaps
    drawn = np.zeros((40, 40), dtype=bool)
    drawn[40 - 1 - 7, 12] = True  # x in [1.2, 1.3), y in [0.7, 0.8): cell (row 1, col 2)
    drawn[40 - 1 - 4, 9] = True  # x in [0.9, 1.0), y in [0.4, 0.5): cell (row 0, col 1)
    cells = to_cells(load_map(write_map(tmp_path, drawn, 0.1)), cell=0.5, grid=10)
    inner = cells[1:9, 1:9]
    assert set(zip(*np.nonzero(inner), strict=True)) == {(1, 2), (0, 1)}
    # a pixel straddling two cells walls both: 0.3 m pixels on 0.5 m cells
    drawn = np.zeros((4, 4), dtype=bool)
    drawn[3, 1] = True  # x in [0.3, 0.6): cells 0 and 1
    cells = to_cells(load_map(write_map(tmp_path, drawn, 0.3)), cell=0.5, grid=6)
    assert cells[1, 1] and cells[1, 2] and not cells[1, 3]


def test_map__as_rooms_of_an_env_unreachable_space_is_walled(tmp_path):
    drawn = np.zeros((12, 12), dtype=bool)
    drawn[:, 6] = True  # a wall splits the map: a big left part and a smaller right part
    drawn[:, 9:] = False
    drawn[:, 6] = True
    path = write_map(tmp_path, drawn[:, :10], 0.5)
    env = EnvConfig(rooms="maps", maps={"train": [str(path)]}, grid_size=16, room_size=8.0,
                    train_rooms=4, test_rooms=2)  # fmt: skip
    bank = room_source(env).bank("train")
    assert bank.shape == (4, 16, 16) and all(np.array_equal(bank[0], b) for b in bank)
    free = ~bank[0]
    assert free[1:13, 1:7].all() and not free[:, 8:].any()  # only the larger side is kept
    assert len(bfs_component(bank[0])) == free.sum()


def test_map__bad_files_are_refused_naming_the_file_and_the_fix(tmp_path):
    good = write_map(tmp_path, np.zeros((8, 8), dtype=bool), 0.5)
    cases = {
        "not a PGM": (tmp_path / "bad.pgm", b"hello, not an image", "not a PGM or PNG"),
        "no resolution": (tmp_path / "nores.yaml", b"image: map.pgm\norigin: [0, 0, 0]\n", "'resolution' is missing"),
        "rotated": (tmp_path / "rot.yaml", b"image: map.pgm\nresolution: 0.5\norigin: [0, 0, 0.3]\n", "yaw 0.3"),
        "bad thresholds": (tmp_path / "th.yaml", b"image: map.pgm\nresolution: 0.5\norigin: [0, 0, 0]\nfree_thresh: 0.9\n", "free_thresh"),
        "missing image": (tmp_path / "noimg.yaml", b"image: nope.pgm\nresolution: 0.5\norigin: [0, 0, 0]\n", "noimg.yaml: its image 'nope.pgm' is not there"),
        # hostile files: refused by rule, cheaply, with nothing of the input echoed at length
        "truncated PGM": (tmp_path / "cut.pgm", b"P2\n40 40\n255\n255 255\n", "truncated"),
        "huge header": (tmp_path / "huge.pgm", b"P5\n100000 100000\n255\n" + bytes(64), "more than the 64,000,000"),
        "5000 digits": (tmp_path / "digits.yaml", b"image: map.pgm\norigin: [0, 0, 0]\nresolution: 1" + b"0" * 5000, "5,001 characters"),
        "deep": (tmp_path / "deep.yaml", b"image: map.pgm\nx: " + b"[" * 5000 + b"]" * 5000, "nested more than"),
        "aliases": (tmp_path / "alias.yaml", b"a: &a [1, 1, 1]\nb: &b [*a, *a, *a]\nimage: *b\n", "aliases"),
        "image not a name": (tmp_path / "list.yaml", b"image: [1, 2]\nresolution: 0.5\norigin: [0, 0, 0]\n", "file name"),
        "resolution 1e300": (tmp_path / "coarse.yaml", b"image: map.pgm\nresolution: 1e300\norigin: [0, 0, 0]\n", "<= 100"),
    }  # fmt: skip
    for what, (path, data, message) in cases.items():
        path.write_bytes(data)
        with pytest.raises(MapError, match=message) as e:
            load_map(path, resolution=0.5 if path.suffix == ".pgm" else None)
        assert path.name in str(e.value) or "nope.pgm" in str(e.value), what
        assert len(str(e.value)) < 600, what
    with pytest.raises(MapError, match=r"maps\.resolution"):
        load_map(tmp_path / "map.pgm")  # a plain image without its scale
    big = load_map(good)
    with pytest.raises(MapError, match="grid_size >= 10"):
        to_cells(big, cell=0.5, grid=8)  # 4 m x 4 m needs 8 cells + the ring
    # a plain-image field with a map_server YAML would be ignored: refused, naming it
    env = EnvConfig(rooms="maps", maps={"train": [str(good)], "resolution": 0.1}, grid_size=16,
                    room_size=8.0)  # fmt: skip
    with pytest.raises(MapError, match=r"env\.maps\.resolution apply to plain"):
        room_source(env).bank("train")
    walled = write_map(tmp_path, np.ones((8, 8), dtype=bool), 0.5)
    env = EnvConfig(rooms="maps", maps={"train": [str(walled)]}, grid_size=16, room_size=8.0)
    with pytest.raises(MapError, match="no free cell"):
        room_source(env).bank("train")


def test_map__numpy_twin_matches_the_jax_env(tmp_path):
    from tests.core.env.test_parity import assert_parity_on

    rng = np.random.default_rng(1)
    drawn = rng.random((14, 14)) < 0.12
    path = write_map(tmp_path, drawn, 0.5)
    assert_parity_on(EnvConfig(rooms="maps", maps={"train": [str(path)]}, grid_size=16,
                               room_size=8.0, train_rooms=4, test_rooms=2))  # fmt: skip


def test_map__the_shipped_office_map_loads_and_the_oracle_drives_it(optimized):
    from quicknav_core.config import EvalConfig
    from quicknav_core.env.room_sources import check_rooms
    from quicknav_core.eval.evaluate import run_eval

    office = str(Path(__file__).resolve().parents[3] / "examples" / "maps" / "office.yaml")
    env = EnvConfig(rooms="maps", maps={"train": [office]}, grid_size=48, room_size=24.0,
                    max_steps=600, train_rooms=4, test_rooms=4)  # fmt: skip
    check_rooms(env)
    with pytest.raises(MapError, match="Set grid_size >= 45"):
        check_rooms(env.model_copy(update={"grid_size": 16, "room_size": 8.0}))
    result, _ = run_eval(EvalConfig(policy="oracle", env=env, episodes=48, split="test", seed=5))
    assert result["metrics"]["success_rate"] >= 0.98, result["metrics"]


# --------------------------------------------------------------------------- a door's sample
@pytest.mark.parametrize("rooms", ["carved", "floorplan"])
def test_first__rooms_are_the_first_rooms_of_the_full_banks(rooms):
    """A door that does not build the env checks a wide robot against ``first(n)`` of a source:
    room i is drawn from its own index, so those are the full bank's first rooms (train exactly;
    the test bank drops the train bank's layouts, which a short train bank may not hold)."""
    env = EnvConfig(rooms=rooms, grid_size=16, room_size=8.0, train_rooms=48, test_rooms=40)
    full, first = room_source(env), room_source(env).first(12)
    assert (first.count("train"), first.count("test")) == (12, 12)
    train = first.bank("train")
    assert train.shape == (12, 16, 16) and np.array_equal(train, full.bank("train")[:12])
    test = first.bank("test")
    in_full = {r.tobytes() for r in full.bank("test")} | {r.tobytes() for r in full.bank("train")}
    assert all(r.tobytes() in in_full for r in test)
    assert room_source(env).first(64).count("train") == 48  # a bank with fewer: all of it


def test_first__of_maps_keeps_every_map(tmp_path):
    """A map bank repeats its maps: its first rooms are every map, however few are asked for."""
    a, b = np.zeros((8, 8), bool), np.zeros((8, 8), bool)
    a[3, :5] = b[:5, 4] = True
    paths = []
    for name, room in (("a", a), ("b", b)):
        from PIL import Image

        Image.fromarray(np.where(room, 0, 254).astype(np.uint8)).save(tmp_path / f"{name}.png")
        paths.append(str(tmp_path / f"{name}.png"))
    env = EnvConfig(rooms="maps", maps={"train": paths, "resolution": 1.0}, grid_size=10,
                    room_size=10.0, train_rooms=1000, test_rooms=1000)  # fmt: skip
    first = room_source(env).first(1)
    assert first.count("train") == 2
    bank = first.bank("train")
    assert not np.array_equal(bank[0], bank[1])  # both maps
    assert np.array_equal(bank, room_source(env).bank("train")[:2])
