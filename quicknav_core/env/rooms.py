"""Procedural rooms: random-walk carving on a grid, and pre-generated room banks.

A carver starts at the centre cell of an all-wall grid and walks: each step it moves one cell in one
of four directions chosen uniformly (a move into the outer ring is refused, so the ring stays wall),
and with probability ``return_prob`` it first jumps back to where it returns to (the paper: the
centre). Every cell it stands on is free. It stops when ``carve_target`` cells are free or after
``carve_step_cap`` steps. A step either moves to a neighbour of the last cell or starts from a cell
already free, so every free cell is reachable from the centre through free cells: every room is
connected.

``EnvConfig.carver`` says how the walk draws its random numbers and where a return lands:

  paper   one PRNG key per step, ``fold_in(room key, step)``, returns to the centre: the paper's
          walk, and bit for bit the rooms of generator version 1 (eight threefry calls a step)
  centre  the same walk from the centre, its random numbers drawn a block of ``CARVE_BLOCK``
          steps at a time from a counter hash (``env.rng.counter_bits``, one 32-bit word a step):
          the same look, other rooms, about 4x cheaper
  carved  like ``centre``, but a return lands on a uniformly random cell carved before the current
          block instead of the centre. A walk that keeps going back to the centre almost never gets
          across a large grid (grid 48 at return_prob 0.05: ~10^6 steps a room, grid 64: ~10^8);
          restarting anywhere in the carved blob lets it grow to the walls in ~20 steps a cell at
          grid 128, and the room still looks like a blob carved around the centre
  auto    (the default) ``paper`` while a room needs few steps, else ``centre`` while that stays
          cheap, else ``carved``; ``env.carving.choose_carver`` decides from the walk's estimate

Rooms are generated in banks so that a reset only picks a room by index. A bank is carved all rooms
at once (vmapped), ``CARVE_BLOCK`` steps per iteration of one ``while_loop``: the walker's positions
for a block are a scan of integer arithmetic (they do not depend on the walls), then one scatter
stamps every cell with the block step of its first visit, and a running count of first visits finds
the step at which the target is met. The room stops exactly there, so blocks change the speed, never
the rooms. On a CPU the bank is split over the cores, one thread each.

The ``train`` and ``test`` banks use different PRNG streams, and test rooms that happen to equal a
train room are dropped, so evaluation is on rooms never seen in training.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.carving import CARVERS
from quicknav_core.env.constants import CARVE_MOVES, SPLIT_STREAM
from quicknav_core.env.rng import counter_bits, key_word

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig, Split

# Steps per while-loop iteration. A cell's stamp is its first-visit step in the block plus one, in a
# uint8 grid where 0 = free and 255 = never visited, so a block has at most 254 steps.
CARVE_BLOCK = 240
_FREE, _UNVISITED = 0, 255
_COUNT_RUN = 16  # steps per run of ``_running_count``; divides CARVE_BLOCK
# The block carvers' return test: the top 30 bits of a step's word below return_prob * 2^30 (the
# low two bits pick the direction).
_RETURN_BITS = 30
# On a CPU a bank is carved in parts of this many rooms, the parts spread over the cores: a part
# is one compiled program for the train and the test bank alike, and in a smaller part the rooms
# wait less for the slowest one (they all run until it is done).
CARVE_PART = 128
_MAX_THREADS = 8  # past a few cores the parts of a default bank run out


@partial(jax.jit, static_argnames=("grid_size", "target", "step_cap", "carver"))
def carve_bank_steps(
    keys: jax.Array,
    grid_size: int,
    target: int,
    step_cap: int,
    return_prob: float | jax.Array,
    carver: str = "paper",
) -> tuple[jax.Array, jax.Array]:
    """Carve one room per key: ``(walls (n, grid, grid) bool, carving steps used (n,) int32)``."""
    if carver not in CARVERS:
        raise ValueError(f"carver={carver!r}: allowed values are {', '.join(CARVERS)}")
    if carver == "carved" and target >= 2**16:
        raise ValueError(f"target={target}: the carved carver draws indices below 2^16")
    n, g, block = keys.shape[0], grid_size, CARVE_BLOCK
    cells, centre = g * g, (g // 2) * g + g // 2
    rows = jnp.arange(n)[:, None]
    t = jnp.arange(block, dtype=jnp.int32)
    stamp = (t + 1).astype(jnp.uint8)
    threshold = jnp.round(jnp.asarray(return_prob, jnp.float32) * 2.0**_RETURN_BITS)
    threshold = threshold.astype(jnp.uint32)
    words = jax.vmap(key_word)(keys)  # the block carvers' streams: one word per room
    # the carved cells (flat) in carving order: where a ``carved`` return may land
    n_listed = target if carver == "carved" else 1
    listed = jnp.full((n, n_listed), centre, jnp.int16 if cells <= 2**15 else jnp.int32)

    def paper_draws(key, step0):
        def one(step):  # exactly the draws of generator version 1
            k_ret, k_dir = jax.random.split(jax.random.fold_in(key, step))
            return jax.random.uniform(k_ret) < return_prob, jax.random.randint(k_dir, (), 0, 4)

        return jax.vmap(one)(step0 + t)

    def draws(taken):
        """(block, n) return flags and directions (the index of ``CARVE_MOVES``)."""
        if carver == "paper":
            return jax.vmap(paper_draws, out_axes=1)(keys, taken)
        # even counters: return test (the top bits) and direction (the low two); odd: the index
        bits = counter_bits(words, 2 * (taken + t[:, None]))
        return (bits >> (32 - _RETURN_BITS)) < threshold, (bits & 3).astype(jnp.int32)

    def homes(free, taken, listed):
        """(block, n) flat cell a return lands on."""
        if carver != "carved":
            return jnp.full((block, n), centre, jnp.int32)
        more = counter_bits(words[:, None], 2 * (taken[:, None] + t) + 1)
        f = free[:, None].astype(jnp.uint32)
        # the high half of more * free (exact for free < 2^16): a uniform index below ``free``
        i = ((more >> 16) * f + (((more & 0xFFFF) * f) >> 16)) >> 16
        return jnp.take_along_axis(listed, i.astype(jnp.int32), axis=1).T.astype(jnp.int32)

    def walk(pos, x):
        """One step of every room: return, then move unless the move leaves the inner square."""
        back, home, d = x
        r = jnp.where(back, home // g, pos[0]) + _move(d, 0)
        col = jnp.where(back, home % g, pos[1]) + _move(d, 1)
        r, col = jnp.clip(r, 1, g - 2), jnp.clip(col, 1, g - 2)
        return (r, col), r * g + col

    def carving(state):
        _, _, free, taken, _ = state
        return (free < target) & (taken < step_cap)

    def one_block(state):
        grid, pos, free, taken, listed = state
        active = carving(state)
        back, d = draws(taken)
        _, at = jax.lax.scan(walk, pos, (back, homes(free, taken, listed), d))
        at = at.T  # (n, block): the flat cell of each step
        # stamp first visits: a free cell keeps 0, a wall takes the smallest block step + 1
        grid = grid.at[rows, jnp.where(active[:, None], at, cells)].min(stamp, mode="drop")
        first = (jnp.take_along_axis(grid, at, axis=1) == stamp) & active[:, None]
        count = _running_count(first)
        reached = count >= (target - free)[:, None]
        steps = jnp.where(reached.any(axis=1), jnp.argmax(reached, axis=1) + 1, block)
        steps = jnp.where(active, jnp.minimum(steps, step_cap - taken), 0)
        kept = first & (t < steps[:, None])  # steps past the stop are not taken: stay wall
        grid = grid.at[rows, jnp.where(kept, at, cells)].set(_FREE, mode="drop")
        if carver == "carved":
            slot = jnp.where(kept, free[:, None] + count - 1, n_listed)
            listed = listed.at[rows, slot].set(at.astype(listed.dtype), mode="drop")
        last = jnp.maximum(steps - 1, 0)[:, None]
        moved = steps > 0
        at_last = jnp.take_along_axis(at, last, axis=1)[:, 0]
        pos = (jnp.where(moved, at_last // g, pos[0]), jnp.where(moved, at_last % g, pos[1]))
        free = free + jnp.where(moved, jnp.take_along_axis(count, last, axis=1)[:, 0], 0)
        return grid, pos, free, taken + steps, listed

    grid = jnp.full((n, cells), _UNVISITED, jnp.uint8).at[:, centre].set(_FREE)
    start = jnp.full((n,), g // 2, jnp.int32)
    state = (grid, (start, start), jnp.ones((n,), jnp.int32), jnp.zeros((n,), jnp.int32), listed)
    grid, _, _, taken, _ = jax.lax.while_loop(lambda s: carving(s).any(), one_block, state)
    return (grid != _FREE).reshape(n, g, g), taken


def _move(d: jax.Array, axis: int) -> jax.Array:
    """Row (``axis`` 0) or column step of direction ``d`` in ``CARVE_MOVES``, as selects (a scan
    step stays one fused loop; a table lookup would be a gather)."""
    return sum(jnp.where(d == k, jnp.int32(v), 0) for k, v in enumerate(CARVE_MOVES[:, axis]))


def _running_count(flags: jax.Array) -> jax.Array:
    """Cumulative count of ``flags`` (n, block) along the block, as int32.

    Counts within runs of ``_COUNT_RUN`` steps are one small matrix product with a triangle of
    ones (exact in float32: counts stay below 2^24); XLA's cumsum on a CPU is about twice as slow.
    """
    n, block = flags.shape
    runs = flags.astype(jnp.float32).reshape(n, block // _COUNT_RUN, _COUNT_RUN)
    within = runs @ jnp.triu(jnp.ones((_COUNT_RUN, _COUNT_RUN), jnp.float32))
    before = jnp.cumsum(within[..., -1], axis=1) - within[..., -1]
    return (within + before[..., None]).reshape(n, block).astype(jnp.int32)


def carve_bank(
    keys: jax.Array, grid_size: int, target: int, step_cap: int, return_prob: float | jax.Array,
    carver: str = "paper",
) -> jax.Array:  # fmt: skip
    """Carve one room per key. Returns (n, grid, grid) bool, ``True`` = wall."""
    return carve_bank_steps(keys, grid_size, target, step_cap, return_prob, carver)[0]


def carve_room(
    key: jax.Array, grid_size: int, target: int, step_cap: int, return_prob: float | jax.Array,
    carver: str = "paper",
) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """Carve one room. Returns ``(walls (grid, grid) bool, number of carving steps used)``."""
    walls, steps = carve_bank_steps(key[None], grid_size, target, step_cap, return_prob, carver)
    return walls[0], steps[0]


def _threads() -> int:
    """Threads that carve a bank side by side: one per core on a CPU (XLA runs a while loop on
    one core), one on an accelerator (a bank's rooms already fill it)."""
    if jax.default_backend() != "cpu":
        return 1
    return max(1, min(os.cpu_count() or 1, _MAX_THREADS))


def _carve_numbered(config: EnvConfig, split: Split, start: int, count: int) -> np.ndarray:
    """Rooms ``start .. start+count-1`` of a split's stream; room i always has the same layout."""
    base = jax.random.fold_in(jax.random.PRNGKey(config.room_seed), SPLIT_STREAM[split])
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(start, start + count))
    size = min(count, CARVE_PART) if jax.default_backend() == "cpu" else count
    parts = -(-count // size)
    # equal parts (the last padded with copies of its last key) share one compiled program
    keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], parts * size - count, axis=0)])
    carver = config.resolved_carver

    def carve(part: int) -> np.ndarray:
        walls = carve_bank(keys[part * size : (part + 1) * size], config.grid_size,
                           config.carve_target, config.carve_step_cap, config.return_prob,
                           carver)  # fmt: skip
        return np.asarray(walls)

    if parts == 1:
        return carve(0)[:count]
    with ThreadPoolExecutor(min(parts, _threads())) as pool:
        return np.concatenate(list(pool.map(carve, range(parts))))[:count]


def carve_first_rooms(config: EnvConfig, split: Split, count: int,
                      skip: set[bytes] | None = None) -> np.ndarray:
    """The first ``count`` rooms of a split's stream that reached the carve target (and are not
    in ``skip``). A room the walk left short (it ran into the step cap) is passed over, so a bank
    is the same whenever every room makes it; ``EnvConfig`` refuses configs where many would not."""
    kept: list[np.ndarray] = []
    # a test bank skips train layouts: carve a few more than it keeps
    start, batch = 0, count if skip is None else max(64, count)
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
            f" the carve target ({config.carve_target} free cells); raise carve_max_steps, lower"
            " return_prob or use carver='carved' (a walker that returns to the centre rarely gets"
            " far on large grids)"
        )
    return np.stack(kept)
