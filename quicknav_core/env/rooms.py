"""Procedural rooms: random-walk carving on a grid, and pre-generated room banks.

A carver starts at the centre cell of an all-wall grid and walks: each step it moves one cell in one
of four directions chosen uniformly (a move into the outer ring is refused, so the ring stays wall),
and with probability ``return_prob`` it first jumps back to the centre. Every cell it stands on is
free. It stops when ``carve_target`` cells are free or after ``carve_step_cap`` steps. Every free
cell is reachable from the centre through free cells, so every room is connected.

Rooms are generated in banks (vmapped, jit-compiled) so that a reset only picks a room by index.
The ``train`` and ``test`` banks use different PRNG streams, and test rooms that happen to equal a
train room are dropped, so evaluation is on rooms never seen in training.
"""

from __future__ import annotations

import hashlib
import json
import os
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.constants import CARVE_MOVES, SPLIT_STREAM, check_split

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig, Split


@partial(jax.jit, static_argnames=("grid_size", "target", "step_cap"))
def carve_room(
    key: jax.Array, grid_size: int, target: int, step_cap: int, return_prob: float | jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Carve one room. Returns ``(walls (grid, grid) bool, number of carving steps used)``."""
    centre = jnp.array([grid_size // 2, grid_size // 2], dtype=jnp.int32)
    walls = jnp.ones((grid_size, grid_size), dtype=bool).at[centre[0], centre[1]].set(False)
    moves = jnp.asarray(CARVE_MOVES)

    def cond(carry):
        _, _, free, step = carry
        return (free < target) & (step < step_cap)

    def body(carry):
        walls, pos, free, step = carry
        k_ret, k_dir = jax.random.split(jax.random.fold_in(key, step))
        pos = jnp.where(jax.random.uniform(k_ret) < return_prob, centre, pos)
        nxt = pos + moves[jax.random.randint(k_dir, (), 0, 4)]
        inside = jnp.all((nxt >= 1) & (nxt <= grid_size - 2))
        pos = jnp.where(inside, nxt, pos)
        newly = walls[pos[0], pos[1]]
        walls = walls.at[pos[0], pos[1]].set(False)
        return walls, pos, free + newly.astype(jnp.int32), step + 1

    walls, _, _, steps = jax.lax.while_loop(cond, body, (walls, centre, jnp.int32(1), jnp.int32(0)))
    return walls, steps


@partial(jax.jit, static_argnames=("grid_size", "target", "step_cap"))
def carve_bank(
    keys: jax.Array, grid_size: int, target: int, step_cap: int, return_prob: float | jax.Array
) -> jax.Array:
    """Carve one room per key, vmapped. Returns (n, grid, grid) bool."""
    walls, _ = jax.vmap(carve_room, in_axes=(0, None, None, None, None))(
        keys, grid_size, target, step_cap, return_prob
    )
    return walls


def _carve_numbered(config: EnvConfig, split: Split, start: int, count: int) -> np.ndarray:
    """Rooms ``start .. start+count-1`` of a split's stream; room i always has the same layout."""
    base = jax.random.fold_in(jax.random.PRNGKey(config.room_seed), SPLIT_STREAM[split])
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(start, start + count))
    walls = carve_bank(
        keys, config.grid_size, config.carve_target, config.carve_step_cap, config.return_prob
    )
    return np.asarray(walls)


def _first_rooms(config: EnvConfig, split: Split, count: int, skip: set[bytes] | None = None,
                 batch: int | None = None) -> np.ndarray:  # fmt: skip
    """The first ``count`` rooms of a split's stream that reached the carve target (and are not
    in ``skip``). A room the walk left short (it ran into the step cap) is passed over, so a bank
    is the same whenever every room makes it; ``EnvConfig`` refuses configs where many would not."""
    kept: list[np.ndarray] = []
    start, batch = 0, batch or count
    short = repeated = 0
    while len(kept) < count and start < 2 * count + 256:
        for room in _carve_numbered(config, split, start, batch):
            if (~room).sum() < config.carve_target:
                short += 1
            elif skip is not None and room.tobytes() in skip:
                repeated += 1
            else:
                kept.append(room)
                if len(kept) == count:
                    break
        start += batch
    if len(kept) < count:
        if repeated >= short:
            raise ValueError(
                f"grid_size={config.grid_size} with carve_fraction={config.carve_fraction} has too"
                f" few distinct layouts for {config.test_rooms} held-out test rooms disjoint from"
                f" the {config.train_rooms} train rooms (found {len(kept)}); use a larger"
                " grid_size, a lower carve_fraction, or fewer train_rooms/test_rooms"
            )
        raise ValueError(
            f"carve_max_steps={config.carve_step_cap} stopped {short} of {start} room(s) short of"
            f" the carve target ({config.carve_target} free cells); raise carve_max_steps or lower"
            " return_prob (the walker rarely gets far from the centre on large grids)"
        )
    return np.stack(kept)


def make_room_bank(config: EnvConfig, split: Split) -> np.ndarray:
    """Generate the ``split`` room bank: (rooms, grid, grid) bool, ``True`` = wall.

    The test bank skips any layout that also occurs in the train bank; if the grid is so small that
    not enough distinct held-out layouts exist, a ``ValueError`` says so. With a bank cache set
    (``set_bank_cache``), a bank built once is read back instead of carved again.
    """
    check_split(split)
    cached = _cache_read(config, split)
    if cached is not None:
        return cached
    if split == "train":
        bank = _first_rooms(config, "train", config.train_rooms)
    else:
        train = make_room_bank(config, "train")
        seen = {room.tobytes() for room in train}
        bank = _first_rooms(config, "test", config.test_rooms, skip=seen,
                            batch=max(64, config.test_rooms))  # fmt: skip
    _cache_write(config, split, bank)
    return bank


# --------------------------------------------------------------------------- bank cache
_BANK_CACHE: Path | None = None
# bumped whenever carving changes what a config's bank holds
GENERATOR_VERSION = 1


def set_bank_cache(folder: Path | str | None) -> None:
    """Keep built room banks in ``folder`` (None: no disk cache). A process that serves many jobs
    or rollout sessions (the service's workers) sets it once; library code never does."""
    global _BANK_CACHE
    _BANK_CACHE = Path(folder) if folder is not None else None


def bank_key(config: EnvConfig, split: Split) -> str:
    """What a bank depends on, as a file-name-safe digest."""
    fields = ("grid_size", "carve_fraction", "return_prob", "carve_step_cap", "room_seed",
              "train_rooms", "test_rooms")  # fmt: skip
    text = json.dumps([GENERATOR_VERSION, split, *(getattr(config, f) for f in fields)])
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _cache_path(config: EnvConfig, split: Split) -> Path | None:
    if _BANK_CACHE is None:
        return None
    return _BANK_CACHE / f"bank-{config.grid_size}-{split}-{bank_key(config, split)}.npz"


def _cache_read(config: EnvConfig, split: Split) -> np.ndarray | None:
    path = _cache_path(config, split)
    if path is None or not path.exists():
        return None
    try:
        with np.load(path) as data:
            bits, shape = data["bits"], tuple(int(v) for v in data["shape"])
        bank = np.unpackbits(bits, count=int(np.prod(shape))).reshape(shape).astype(bool)
    except (OSError, ValueError, KeyError):
        return None  # damaged: carve it again
    g = config.grid_size
    expected = config.train_rooms if split == "train" else config.test_rooms
    return bank if bank.shape == (expected, g, g) else None


def _cache_write(config: EnvConfig, split: Split, bank: np.ndarray) -> None:
    path = _cache_path(config, split)
    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.savez(f, bits=np.packbits(bank.reshape(-1)), shape=np.asarray(bank.shape))
        os.replace(tmp, path)
    except OSError:
        pass  # a cache that cannot be written (a full disk) only costs a rebuild


def free_cell_table(rooms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the free cells of every room, padded: ((n, g*g) int32, (n,) int32 counts)."""
    n, g, _ = rooms.shape
    flat_free = ~rooms.reshape(n, g * g)
    counts = flat_free.sum(axis=1).astype(np.int32)
    # Stable argsort puts free cells (key 0) first in increasing index order.
    order = np.argsort(~flat_free, axis=1, kind="stable").astype(np.int32)
    return order, counts
