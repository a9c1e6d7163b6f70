"""Room sources: the objects an env is given to fill its room banks (as jumanji's environments take
a generator). ``EnvConfig.rooms`` names one; ``room_source(config, runtime)`` builds it:

    carved      random-walk caves, the paper's (``env.rooms``: JAX, vmapped)
    floorplan   generated rooms, doors and a corridor (``env.floorplan``: NumPy)
    maps        maps of real buildings (``env.maps``: ROS map_server YAML + PGM, or PNG/PGM)

A source answers ``bank(split)``: (rooms, grid, grid) bool, True = wall, ``train_rooms`` or
``test_rooms`` of them. Banks are kept in the runtime (in memory, and on disk when it names a
``bank_folder``) under a digest of everything they depend on (``key``). The env never asks which
source it has; a new source is a subclass here and an entry in ``ROOM_SOURCES``.

This module imports NumPy only: the JAX carver is imported when a carved bank is built, so the
NumPy twin reads its rooms from here without JAX.

Splits. ``carved`` and ``floorplan``: the train and test banks are drawn from different streams and
test rooms that equal a train room are dropped (held out by layout). ``maps``: by map when
``maps.test`` names held-out maps (the question "does it work in a building it never saw");
otherwise by episode, both banks holding the train maps and evaluation drawing its own fixed-seed
starts and goals (the question "how well does it drive in *this* building"). A map bank holds
``train_rooms`` / ``test_rooms`` entries either way: the maps are repeated in order to fill it, so
every map is picked equally often and the shapes (and memory estimates) are the config's.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from quicknav_core.env.constants import SPLIT_STREAM, check_split
from quicknav_core.runtime import Runtime, runtime_or_new

if TYPE_CHECKING:  # pragma: no cover - the sources read their config's fields, never import it
    from quicknav_core.config import EnvConfig, Split

# bumped whenever a source changes what a config's bank holds (2: ``EnvConfig.carver``; the
# ``paper`` carver's banks are those of version 1, bit for bit; 3: one key layout for every source)
GENERATOR_VERSION = 3


class RoomSource:
    """Where a config's rooms come from; ``bank(split)`` gives them, built once per runtime."""

    name: ClassVar[str] = ""
    # the test bank drops layouts of the train bank (so it needs the train bank first)
    test_skips_train: ClassVar[bool] = True

    def __init__(self, config: EnvConfig, runtime: Runtime | None = None):
        self.config = config
        self.runtime = runtime_or_new(runtime)

    # ------------------------------------------------------------------ what a source defines
    def generate(self, split: Split, train: np.ndarray | None) -> np.ndarray:
        """The ``split`` bank, built (``train``: the train bank, for a test bank that skips it)."""
        raise NotImplementedError

    def own_key(self, split: Split) -> list[Any]:
        """What the bank depends on beyond the grid, seed and bank sizes (JSON-able)."""
        return []

    def check(self) -> None:
        """Refuse a source that cannot give rooms (a ValueError naming the field and the fix)
        before anything compiles; cheap checks only (building the bank says the rest)."""

    def twin_room(self, split: Split, index: int) -> np.ndarray:
        """Room ``index`` as the NumPy twin draws it (the bank's, unless a source says otherwise)."""
        return self.bank(split)[index]

    # ------------------------------------------------------------------ banks
    def count(self, split: Split) -> int:
        return self.config.train_rooms if split == "train" else self.config.test_rooms

    def first(self, n: int) -> RoomSource:
        """This source over the first ``n`` rooms of each bank (all of a bank with fewer): what a
        door that does not build the env checks a wide robot against (``clearance.check_fit``).
        Room ``i`` is drawn from its own index, so room ``i`` of a bank of ``n`` is room ``i`` of
        any longer one (the test bank, which drops the train bank's layouts, may hold a layout
        the full train bank has further on: still a room of the same generator)."""
        c = self.config
        if c.train_rooms <= n and c.test_rooms <= n:
            return self
        fewer = c.model_copy(update={"train_rooms": min(c.train_rooms, n), "test_rooms": min(c.test_rooms, n)})
        return type(self)(fewer, self.runtime)

    def key(self, split: Split) -> str:
        """What the ``split`` bank depends on, as a file-name-safe digest."""
        c = self.config
        # a non-square grid adds its shape (a square one keeps the keys banks were stored under)
        shape = [list(c.grid_shape)] if c.grid_shape != (c.grid_size, c.grid_size) else []
        parts = [GENERATOR_VERSION, self.name, check_split(split), c.grid_size, *shape, c.room_seed,
                 c.train_rooms, c.test_rooms, *self.own_key(split)]  # fmt: skip
        return hashlib.sha256(json.dumps(parts).encode()).hexdigest()[:32]

    def bank(self, split: Split) -> np.ndarray:
        """The ``split`` bank: (rooms, rows, cols) bool (``EnvConfig.grid_shape``), True = wall
        (built once per runtime)."""
        key = self.key(split)
        return self.runtime.banks.get(("bank", key), lambda: self._load_or_build(split, key))

    def _load_or_build(self, split: Split, key: str) -> np.ndarray:
        path = self._disk_path(split, key)
        bank = _read_bank(path, (self.count(split), *self.config.grid_shape)) if path is not None else None
        if bank is None:
            train = self.bank("train") if split == "test" and self.test_skips_train else None
            bank = np.ascontiguousarray(self.generate(split, train), dtype=bool)
            if path is not None:
                _write_bank(path, bank)
        bank.setflags(write=False)  # shared by every env of this runtime
        return bank

    def _disk_path(self, split: Split, key: str) -> Path | None:
        folder = self.runtime.bank_folder
        if folder is None:
            return None
        return folder / f"bank-{self.config.grid_size}-{split}-{key}.npz"


def _read_bank(path: Path, shape: tuple[int, int, int]) -> np.ndarray | None:
    if not path.exists():
        return None
    try:
        with np.load(path) as data:
            bits, stored = data["bits"], tuple(int(v) for v in data["shape"])
        bank = np.unpackbits(bits, count=int(np.prod(stored))).reshape(stored).astype(bool)
    except (OSError, ValueError, KeyError):
        return None  # damaged: build it again
    return bank if bank.shape == shape else None


def _write_bank(path: Path, bank: np.ndarray) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.savez(f, bits=np.packbits(bank.reshape(-1)), shape=np.asarray(bank.shape))
        os.replace(tmp, path)
    except OSError:
        pass  # a cache that cannot be written (a full disk) only costs a rebuild


# --------------------------------------------------------------------------- carved
class CarvedRooms(RoomSource):
    """Random-walk caves (``env.rooms``), carved in JAX; the twin carves its own with NumPy."""

    name = "carved"

    def own_key(self, split):
        c = self.config
        return [c.carve_fraction, c.return_prob, c.carve_step_cap, c.resolved_carver]

    def generate(self, split, train):
        from quicknav_core.env.rooms import carve_first_rooms

        skip = {room.tobytes() for room in train} if train is not None else None
        return carve_first_rooms(self.config, split, self.count(split), skip=skip)

    def twin_room(self, split, index):
        from quicknav_core.env.carving import carve_room_np

        c = self.config
        rng = np.random.default_rng([c.room_seed, SPLIT_STREAM[split], index])
        return carve_room_np(rng, c.grid_size, c.carve_target, c.carve_step_cap, c.return_prob,
                             to_carved=c.resolved_carver == "carved")  # fmt: skip


# --------------------------------------------------------------------------- floor plans
class FloorplanRooms(RoomSource):
    """Generated floor plans (``env.floorplan``)."""

    name = "floorplan"

    def own_key(self, split):
        return [self.config.floorplan.model_dump(mode="json")]

    def generate(self, split, train):
        from quicknav_core.env.floorplan import floorplan_bank

        skip = {room.tobytes() for room in train} if train is not None else None
        return floorplan_bank(self.config, split, self.count(split), skip=skip)


# --------------------------------------------------------------------------- maps
class MapRooms(RoomSource):
    """Maps of buildings (``env.maps``): each map one room, repeated to fill the bank. A
    ``map:<id>`` name is read through the runtime's ``map_resolver`` (a service's uploaded maps)."""

    name = "maps"
    test_skips_train = False

    IMAGE_ONLY: ClassVar[tuple[str, ...]] = ("resolution", "occupied_thresh", "free_thresh", "negate")

    def files(self, split: Split) -> list[str]:
        m = self.config.maps
        return list(m.test) if split == "test" and m.test else list(m.train)

    def path(self, name: str) -> Path:
        """The local file a map name stands for (a stored map's through the resolver)."""
        from quicknav_core.env.maps import map_path

        return map_path(name, self.runtime.map_resolver)

    def read_options(self) -> dict[str, Any]:
        return self.config.maps.load_options()

    def own_key(self, split):
        from quicknav_core.env.maps import is_map_id, map_parts

        digests = []
        for name in self.files(split):
            if is_map_id(name):  # a stored map never changes: its id is a digest of its files
                digests.append(name)
                continue
            h = hashlib.sha256()
            for part in map_parts(self.path(name)):
                h.update(part.read_bytes() if part.is_file() else b"missing:" + str(part).encode())
            digests.append(h.hexdigest()[:16])
        return [self.config.cell_size, self.config.maps.model_dump(exclude={"train", "test"}), digests]

    def rooms(self, split: Split) -> list[np.ndarray]:
        """Each map of the split as one room (errors name the file and the fix)."""
        from quicknav_core.env.maps import YAML_SUFFIXES, MapError, is_map_id, map_room

        m = self.config.maps
        image_only = [f for f in self.IMAGE_ONLY if getattr(m, f) != type(m).model_fields[f].default]
        # a stored map (`map:<id>`) is a map_server .yaml too
        yamls = [n for n in self.files(split)
                 if is_map_id(n) or Path(n).suffix.lower() in YAML_SUFFIXES]  # fmt: skip
        if image_only and yamls:
            # a map_server YAML names its own scale and thresholds: these would be ignored for it
            raise MapError(f"{yamls[0]}: env.maps.{', env.maps.'.join(image_only)} apply to plain"
                           " .png/.pgm images only; a map_server .yaml names its own (edit the"
                           " .yaml instead)")  # fmt: skip
        out = []
        for name in self.files(split):
            path = self.path(name)
            try:
                out.append(map_room(path, self.config.cell_size, self.config.grid_shape,
                                    **self.read_options()))  # fmt: skip
            except MapError as e:  # name a stored map by its id, not by the file it was read from
                raise MapError(str(e).replace(str(path), name)) if str(path) != name else e from None
        return out

    def generate(self, split, train):
        rooms = self.rooms(split)
        return np.stack([rooms[i % len(rooms)] for i in range(self.count(split))])

    def check(self) -> None:
        for split in ("train", "test") if self.config.maps.test else ("train",):
            self.rooms(split)

    def first(self, n: int) -> RoomSource:
        # every map at least once: the banks repeat the maps, so these are all their rooms
        m = self.config.maps
        return super().first(max(n, len(m.train), len(m.test or [])))


ROOM_SOURCES: MappingProxyType[str, type[RoomSource]] = MappingProxyType(
    {cls.name: cls for cls in (CarvedRooms, FloorplanRooms, MapRooms)}
)


def room_source(config: EnvConfig, runtime: Runtime | None = None) -> RoomSource:
    """The room source ``config.rooms`` names, reading through ``runtime``."""
    return ROOM_SOURCES[config.rooms](config, runtime)


def make_room_bank(config: EnvConfig, split: Split, runtime: Runtime | None = None) -> np.ndarray:
    """The ``split`` bank of a config's room source: (rooms, rows, cols) bool, True = wall."""
    return room_source(config, runtime).bank(check_split(split))


def check_rooms(config: EnvConfig, runtime: Runtime | None = None) -> None:
    """Refuse a config whose rooms cannot be used (a ValueError naming the field and the fix): a
    map that cannot be read or does not fit the grid, a robot wider than every room's passages.
    Before anything compiles or trains; every door runs it."""
    from quicknav_core.env.clearance import check_fit

    source = room_source(config, runtime)
    source.check()
    check_fit(config, source)


def free_cell_table(rooms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (row * cols + col) of the free cells of every room, padded: ((n, rows*cols)
    int32, (n,) int32 counts)."""
    n, rows, cols = rooms.shape
    flat_free = ~rooms.reshape(n, rows * cols)
    counts = flat_free.sum(axis=1).astype(np.int32)
    # Stable argsort puts free cells (key 0) first in increasing index order.
    order = np.argsort(~flat_free, axis=1, kind="stable").astype(np.int32)
    return order, counts
