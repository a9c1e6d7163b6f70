"""The maps that ship in ``examples/maps``: each loads and fits the ``building`` preset's policy (its
0.5 m cells) within the env's limits, as ``quicknav eval --map`` lays it; the real SLAM maps name
their source and licence."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import ndimage

from quicknav_core.config import get_preset
from quicknav_core.env.clearance import disc_fits
from quicknav_core.eval.map_fit import MAX_GRID, fit_map

ROOT = Path(__file__).resolve().parents[3]
MAPS = sorted((ROOT / "examples" / "maps").glob("**/*.yaml"))
SLAM = ROOT / "examples" / "maps" / "slam"


def test_shipped_maps__the_real_slam_maps_are_there():
    assert {p.name for p in MAPS if p.parent == SLAM} == {
        "depot.yaml", "small_warehouse.yaml", "warehouse.yaml"}  # fmt: skip


@pytest.mark.parametrize("path", MAPS, ids=lambda p: str(p.relative_to(ROOT / "examples" / "maps")))
def test_shipped_map__the_building_policy_can_drive_it(path):
    env = get_preset("building").env
    fit = fit_map(env, path)
    assert fit.cell_m == 0.5 and fit.grid_size <= MAX_GRID
    # the laid grid keeps most of the map's free space (a warning below 90 %, as the CLI prints)
    assert fit.free_kept >= 0.75, fit.free_kept
    # where the robot's disc fits: many cells, most of them in one region it can drive between
    usable = disc_fits(fit.walls, fit.cell_m, env.spawn_radius)
    labels, count = ndimage.label(usable, structure=np.ones((3, 3)))
    largest = np.bincount(labels.ravel())[1:].max()
    assert usable.sum() >= 300 and largest >= 0.9 * usable.sum(), (usable.sum(), largest, count)
    # the step limit covers the longest shortest path twice at full speed
    assert fit.max_steps >= 2 * fit.longest_path_m / (env.max_wheel_speed * env.dt)


def test_shipped_maps__every_slam_file_names_its_source_and_licence():
    readme = (SLAM / "README.md").read_text()
    rows = [line for line in readme.splitlines() if line.startswith("| `")]
    for path in (p for p in MAPS if p.parent == SLAM):
        image = yaml.safe_load(path.read_text())["image"]
        assert (SLAM / image).is_file(), image
        row = next((r for r in rows if f"`{path.name}`" in r and f"`{image}`" in r), None)
        assert row is not None, f"{path.name} and {image} have no row in {SLAM / 'README.md'}"
        assert re.search(r"github\.com/[\w.-]+/[\w.-]+", row), row
        assert re.search(r"Apache-2\.0|MIT-0", row), row
    assert "Apache License" in (SLAM / "LICENSE-Apache-2.0.txt").read_text()
    # nothing in the folder that the table does not account for
    named = {m for r in rows for m in re.findall(r"`([\w.]+\.(?:yaml|pgm|png))`", r)}
    files = {p.name for p in SLAM.iterdir() if p.suffix in (".yaml", ".pgm", ".png")}
    assert files == named, files ^ named


def test_map_eval_pictures__name_the_map_not_a_room_bank():
    from quicknav_core.config import EnvConfig
    from quicknav_core.eval.pictures import rooms_in_words

    on_map = EnvConfig(rooms="maps", maps={"train": ["examples/maps/slam/depot.yaml"]},
                       grid_size=63, room_size=31.5)  # fmt: skip
    assert rooms_in_words(on_map) == "map depot.yaml"
    held_out = EnvConfig(rooms="maps", maps={"train": ["map:4f2a"], "test": ["a.yaml", "b/b.yaml"]},
                         grid_size=63, room_size=31.5)  # fmt: skip
    assert rooms_in_words(held_out) == "2 maps (a.yaml, b.yaml)"
    assert rooms_in_words(held_out, "train") == "map map:4f2a"
    # an uploaded map by the name it was given (Runtime.map_name), as the browser's replay words it;
    # one the lookup does not know, or fails on, keeps its reference
    names = {"4f2a": "depot"}.get
    assert rooms_in_words(held_out, "train", names) == 'map "depot"'
    several = EnvConfig(rooms="maps", maps={"train": ["map:4f2a", "x/office.yaml", "map:0bad", "map:5e"]},
                        grid_size=63, room_size=31.5)  # fmt: skip
    assert rooms_in_words(several, "train", names) == '4 maps ("depot", office.yaml, map:0bad, ...)'

    def broken(_map_id):
        raise OSError("the store is unreachable")

    assert rooms_in_words(held_out, "train", broken) == "map map:4f2a"
    assert rooms_in_words(EnvConfig()) == "held-out test rooms"
    assert rooms_in_words(EnvConfig(), "train") == "training rooms"
