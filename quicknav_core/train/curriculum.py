"""The curriculum's episode pool: train episodes binned by the oracle's shortest-path length.

``make_pool`` draws ``episodes_per_room`` (start cell, goal cell) pairs for every room of a bank
with the env's spawn rule (a uniformly chosen free start cell; the goal the farthest of
``goal_candidates`` other free cells), measures each pair's shortest path with the oracle planner's
distance field on the cell grid (8-connected cell centres, no corner cutting, less the goal
radius; the eval's reference length uses the same planner on a 5x finer grid) and sorts the pool by that length. ``with_pool`` puts it in
``EnvParams``; resets then draw from the first ``pool_count`` episodes, the curriculum's level.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.config import CurriculumConfig, EnvConfig
from quicknav_core.env.room_sources import free_cell_table
from quicknav_core.env.types import EnvParams

PLANNER_K = 1  # planner nodes per cell side for the pool (a pool has ~10^4-10^5 episodes)
_BATCH = 4096  # episodes measured per compiled call


@dataclass(frozen=True)
class EpisodePool:
    room: np.ndarray  # (P,) int32
    start: np.ndarray  # (P,) int32 flat cell
    goal: np.ndarray  # (P,) int32 flat cell
    length: np.ndarray  # (P,) float32 metres, ascending
    level_counts: tuple[int, ...]  # episodes in use at each level; the last is the whole pool

    def __len__(self) -> int:
        return int(self.room.size)

    def level_of(self, count: int) -> int:
        """The level whose episode count is ``count`` (the first one that large)."""
        for level, c in enumerate(self.level_counts):
            if count <= c:
                return level
        return len(self.level_counts) - 1

    def max_length(self, level: int) -> float:
        """The longest path in use at ``level``, metres (0 if the level is empty)."""
        c = self.level_counts[level]
        return float(self.length[c - 1]) if c else 0.0


def draw_episodes(rooms: np.ndarray, config: EnvConfig, per_room: int, seed: int):
    """(room, start cell, goal cell) for ``per_room`` episodes of every room, by the spawn rule."""
    from quicknav_core.env.clearance import spawn_regions

    rng = np.random.default_rng(seed)
    free, counts = free_cell_table(~spawn_regions(rooms, config.cell_size, config.spawn_radius))
    g = rooms.shape[-1]
    n_rooms = rooms.shape[0]
    room = np.repeat(np.arange(n_rooms, dtype=np.int32), per_room)
    n = counts[room].astype(np.int64)
    s = np.minimum((rng.random(room.size) * n).astype(np.int64), n - 1)
    k = config.goal_candidates
    j = np.minimum((rng.random((room.size, k)) * (n - 1)[:, None]).astype(np.int64), (n - 2)[:, None])
    j = j + (j >= s[:, None])
    start = free[room, s]
    cand = free[room[:, None], j]
    d2 = (cand // g - (start // g)[:, None]) ** 2 + (cand % g - (start % g)[:, None]) ** 2
    goal = cand[np.arange(room.size), np.argmax(d2, axis=1)]
    return room, start.astype(np.int32), goal.astype(np.int32)


def path_lengths(params: EnvParams, room, start, goal, grid: tuple[int, int], reach: int = 0
                 ) -> np.ndarray:  # fmt: skip
    """The oracle planner's shortest path (metres) from each start cell's centre to its goal
    cell's centre, less the goal radius: its distance field (``env.plan.distance_field``)
    on the cell grid (``grid``: (rows, cols)), seeded at the goal cell alone."""
    from quicknav_core.env.plan import distance_field, usable_nodes

    rows, cols = grid
    cell = float(params.room_size) / max(rows, cols)

    def one(row_bits, s, g_):
        usable = usable_nodes(row_bits, params.room_size, params.robot_radius, PLANNER_K, reach, cols)
        seeds = jnp.full((rows, cols), 1e9).at[g_ // cols, g_ % cols].set(0.0)
        field = distance_field(usable, seeds, cell)
        return jnp.maximum(field[s // cols, s % cols] - params.goal_radius, 0.0)

    measure = jax.jit(lambda bits, r, s, g_: jax.vmap(one)(bits[r], s, g_))
    out = []
    for i in range(0, room.size, _BATCH):
        sl = slice(i, i + _BATCH)
        r, s, g_ = (np.asarray(a[sl]) for a in (room, start, goal))
        pad = _BATCH - r.size  # one compiled shape for every batch
        r, s, g_ = (np.pad(a, (0, pad), mode="edge") for a in (r, s, g_))
        out.append(np.asarray(measure(params.room_row_bits, r, s, g_))[: _BATCH - pad])
    return np.concatenate(out).astype(np.float32)


def make_pool(params: EnvParams, config: EnvConfig, curriculum: CurriculumConfig, seed: int) -> EpisodePool:
    """The sorted pool of a bank (``params.rooms``) and its level counts."""
    rooms = np.asarray(params.rooms)
    room, start, goal = draw_episodes(rooms, config, curriculum.episodes_per_room, seed)
    length = path_lengths(params, room, start, goal, rooms.shape[1:], config.collision_reach)
    order = np.argsort(length, kind="stable")
    length = length[order]
    counts = [int(np.searchsorted(length, f * config.room_size, side="left")) for f in curriculum.levels]
    return EpisodePool(room[order], start[order], goal[order], length, (*counts, int(length.size)))


def with_pool(params: EnvParams, pool: EpisodePool, count: int) -> EnvParams:
    """``params`` whose resets draw from the first ``count`` episodes of ``pool``."""
    return params.replace(
        pool_room=jnp.asarray(pool.room), pool_start=jnp.asarray(pool.start),
        pool_goal=jnp.asarray(pool.goal), pool_count=jnp.int32(count),
    )  # fmt: skip


def first_level(pool: EpisodePool) -> int:
    """The first level with any episode in it."""
    return next(i for i, c in enumerate(pool.level_counts) if c > 0)
