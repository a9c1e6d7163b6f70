"""Room sources besides the carver (``EnvConfig.rooms``): generated floor plans and loaded maps.

NumPy only (no JAX): the JAX env's bank (``rooms.make_room_bank``) and the NumPy twin build the
same rooms from here.

Splits. ``floorplan``: the train and test banks are drawn from different streams and test plans
that equal a train plan are dropped (held out by layout, as carved rooms are). ``maps``: by map
when ``maps.test`` names held-out maps (the question "does it work in a building it never saw");
otherwise by episode, both banks holding the train maps and evaluation drawing its own fixed-seed
starts and goals (the question "how well does it drive in *this* building", which is what a user
with one building asks). A bank holds ``train_rooms`` / ``test_rooms`` entries either way: the maps
are repeated in order to fill it, so every map is picked equally often and the shapes (and memory
estimates) are the config's.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig, Split


def map_files(config: EnvConfig, split: Split) -> list[str]:
    m = config.maps
    return list(m.test) if split == "test" and m.test else list(m.train)


def source_key(config: EnvConfig, split: Split) -> list:
    """What a floor-plan or map bank depends on beyond the grid (for the bank cache's key)."""
    if config.rooms == "floorplan":
        return ["floorplan", config.floorplan.model_dump()]
    from quicknav_core.env.maps import is_map_id, map_path

    digests = []
    for name in map_files(config, split):
        if is_map_id(name):  # a stored map never changes: its id is a digest of its files
            digests.append(name)
            continue
        h = hashlib.sha256()
        path = map_path(name)
        for part in _map_parts(path):
            h.update(part.read_bytes() if part.is_file() else b"missing:" + str(part).encode())
        digests.append(h.hexdigest()[:16])
    return ["maps", config.maps.model_dump(exclude={"train", "test"}), digests]


def _map_parts(path: Path) -> list[Path]:
    """The files a map is read from (a YAML and its image)."""
    if path.suffix.lower() in (".yaml", ".yml") and path.is_file():
        try:
            import yaml

            doc = yaml.safe_load(path.read_text())
            return [path, path.parent / str(doc["image"])]
        except Exception:  # a broken YAML: loading it says what is wrong
            return [path]
    return [path]


def map_rooms(config: EnvConfig, split: Split) -> list[np.ndarray]:
    """Each map of the split as one room (errors name the file and the fix)."""
    from quicknav_core.env.maps import YAML_SUFFIXES, MapError, is_map_id, map_path, map_room

    m = config.maps
    image_only = [f for f in ("resolution", "occupied_thresh", "free_thresh", "negate")
                  if getattr(m, f) != type(m).model_fields[f].default]  # fmt: skip
    # a stored map (`map:<id>`) is a map_server .yaml too
    yamls = [n for n in map_files(config, split)
             if is_map_id(n) or Path(n).suffix.lower() in YAML_SUFFIXES]  # fmt: skip
    if image_only and yamls:
        # a map_server YAML names its own scale and thresholds: these would be ignored for it
        raise MapError(f"{yamls[0]}: env.maps.{', env.maps.'.join(image_only)} apply to plain .png/.pgm"
                       " images only; a map_server .yaml names its own (edit the .yaml instead)")  # fmt: skip
    read = {"resolution": m.resolution, "occupied_thresh": m.occupied_thresh,
            "free_thresh": m.free_thresh, "negate": m.negate, "unknown_free": m.unknown == "free"}  # fmt: skip
    rooms = []
    for name in map_files(config, split):
        path = map_path(name)
        try:
            rooms.append(map_room(path, config.cell_size, config.grid_size, **read))
        except MapError as e:  # name a stored map by its id, not by the cache file it was read from
            raise MapError(str(e).replace(str(path), name)) if str(path) != name else e from None
    return rooms


def source_bank(config: EnvConfig, split: Split, train: np.ndarray | None = None) -> np.ndarray:
    """The ``split`` bank of a floor-plan or map config: (rooms, grid, grid) bool, True = wall.
    ``train``: the train bank, whose plans the test bank of floor plans skips."""
    count = config.train_rooms if split == "train" else config.test_rooms
    if config.rooms == "floorplan":
        from quicknav_core.env.floorplan import floorplan_bank

        skip = {room.tobytes() for room in train} if train is not None else None
        return floorplan_bank(config, split, count, skip=skip)
    rooms = map_rooms(config, split)
    return np.stack([rooms[i % len(rooms)] for i in range(count)])


def check_rooms(config: EnvConfig) -> None:
    """Read every map a config names and lay it on the grid, so a map that cannot be used is
    refused (MapError, naming the file and the fix) before anything compiles or trains."""
    if config.rooms == "maps":
        for split in ("train", "test"):
            map_rooms(config, split)
