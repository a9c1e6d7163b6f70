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

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.config import EnvConfig, Split

# Carving moves (d_row, d_col): up, down, left, right.
_MOVES = np.array([[1, 0], [-1, 0], [0, -1], [0, 1]], dtype=np.int32)

_SPLIT_STREAM = {"train": 0, "test": 1}


@partial(jax.jit, static_argnames=("grid_size", "target", "step_cap"))
def carve_room(
    key: jax.Array, grid_size: int, target: int, step_cap: int, return_prob: float | jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Carve one room. Returns ``(walls (grid, grid) bool, number of carving steps used)``."""
    centre = jnp.array([grid_size // 2, grid_size // 2], dtype=jnp.int32)
    walls = jnp.ones((grid_size, grid_size), dtype=bool).at[centre[0], centre[1]].set(False)
    moves = jnp.asarray(_MOVES)

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
    base = jax.random.fold_in(jax.random.PRNGKey(config.room_seed), _SPLIT_STREAM[split])
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(start, start + count))
    walls = carve_bank(
        keys, config.grid_size, config.carve_target, config.carve_step_cap, config.return_prob
    )
    walls = np.asarray(walls)
    free = (~walls).sum(axis=(1, 2))
    short = np.flatnonzero(free < config.carve_target)
    if short.size:
        raise ValueError(
            f"carve_max_steps={config.carve_step_cap} stopped {short.size} room(s) short of the"
            f" carve target ({config.carve_target} free cells); raise carve_max_steps or lower"
            " return_prob (the walker rarely gets far from the centre on large grids)"
        )
    return walls


def make_room_bank(config: EnvConfig, split: Split) -> np.ndarray:
    """Generate the ``split`` room bank: (rooms, grid, grid) bool, ``True`` = wall.

    The test bank skips any layout that also occurs in the train bank; if the grid is so small that
    not enough distinct held-out layouts exist, a ``ValueError`` says so.
    """
    if split == "train":
        return _carve_numbered(config, "train", 0, config.train_rooms)
    if split != "test":
        raise ValueError(f"split={split!r}: allowed values are 'train' and 'test'")
    seen = {room.tobytes() for room in _carve_numbered(config, "train", 0, config.train_rooms)}
    kept: list[np.ndarray] = []
    start, batch = 0, max(64, config.test_rooms)
    while len(kept) < config.test_rooms and start < 4 * config.test_rooms + 256:
        for room in _carve_numbered(config, "test", start, batch):
            if room.tobytes() not in seen:
                kept.append(room)
                if len(kept) == config.test_rooms:
                    break
        start += batch
    if len(kept) < config.test_rooms:
        raise ValueError(
            f"grid_size={config.grid_size} with carve_fraction={config.carve_fraction} has too few"
            f" distinct layouts for {config.test_rooms} held-out test rooms disjoint from the"
            f" {config.train_rooms} train rooms (found {len(kept)}); use a larger grid_size, a"
            " lower carve_fraction, or fewer train_rooms/test_rooms"
        )
    return np.stack(kept)


def free_cell_table(rooms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the free cells of every room, padded: ((n, g*g) int32, (n,) int32 counts)."""
    n, g, _ = rooms.shape
    flat_free = ~rooms.reshape(n, g * g)
    counts = flat_free.sum(axis=1).astype(np.int32)
    # Stable argsort puts free cells (key 0) first in increasing index order.
    order = np.argsort(~flat_free, axis=1, kind="stable").astype(np.int32)
    return order, counts
