"""Obstacles the map does not show (``EnvConfig.obstacles``): static boxes and moving people, seen
only by the lidar; the global plan (``env.plan``) runs through them as a map-based planner does.

At every spawn an env places ``static`` + ``moving`` discs, each at the centre of a free cell drawn
uniformly from the room's spawn cells, with its radius drawn from its range:

- a cell is taken only if it is *open* (its eight neighbours are free: an obstacle never fills a
  door or a one-cell corridor, so every goal stays reachable around it) and the disc keeps
  ``clearance_m`` from the start and from the goal; an obstacle whose cell fails is absent this
  episode (radius 0, far outside the room), so the counts are upper bounds (a density);
- a moving obstacle (a person) walks straight at a speed drawn from ``speed_mps`` in a random
  direction, and turns back where its next position would overlap a wall or the robot (it yields);
  static ones never move.

The robot collides with an obstacle as with a wall (counted, penalised), but it does not slide
along a disc: a move that would overlap one is not made. The lidar sees the discs as walls (a real
lidar reports no kind of return). Every draw is a word of the spawn's hash (``constants.OBSTACLE_WORDS``
per obstacle); the NumPy twin places its own by the same rules, and takes the JAX env's (``load``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.bits import read_bit
from quicknav_core.env.constants import BIG, OBSTACLE_ABSENT, OBSTACLE_WORDS
from quicknav_core.env.dynamics import disc_overlaps_wall_bits
from quicknav_core.env.rng import uniform_from_bits
from quicknav_core.env.types import ObstacleRanges, Obstacles

ABSENT = OBSTACLE_ABSENT  # far outside every room, radius 0: it meets no beam and no robot
_DIRS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


def obstacle_numbers(config) -> ObstacleRanges | None:
    """The ``EnvParams.obstacles`` of an ``EnvConfig`` (None without obstacles)."""
    o = config.obstacles
    if o is None:
        return None
    f32 = np.float32
    return ObstacleRanges(
        static_radius=np.asarray(o.static_radius_m, f32), moving_radius=np.asarray(o.moving_radius_m, f32),
        speed=np.asarray(o.speed_mps, f32), clearance=f32(o.clearance_m),
    )  # fmt: skip


def place(ranges: ObstacleRanges, bits: jax.Array, n_static: int, n_moving: int,
          free_cells: jax.Array, n_free: jax.Array, row_bits: jax.Array, cell, start: jax.Array,
          goal: jax.Array, cols: int | None = None) -> Obstacles:  # fmt: skip
    """The obstacles of one episode from ``OBSTACLE_WORDS * (n_static + n_moving)`` random words
    (see the module doc); ``free_cells`` / ``n_free``: the room's spawn cells, flat indices
    ``row * cols + col`` (``cols`` None: as many as rows, a square)."""
    n = n_static + n_moving
    g = row_bits.shape[0]
    cols = g if cols is None else cols
    u = uniform_from_bits(bits).reshape(n, OBSTACLE_WORDS)
    pick = jnp.minimum(jnp.floor(u[:, 0] * n_free).astype(jnp.int32), n_free - 1)
    flat = free_cells[pick]
    r, c = flat // cols, flat % cols
    opened = jnp.ones((n,), bool)
    for dr, dc in _DIRS:
        rr, cc = jnp.clip(r + dr, 0, g - 1), jnp.clip(c + dc, 0, cols - 1)
        opened = opened & ~read_bit(row_bits[rr], cc)
    moving = jnp.arange(n) >= n_static
    lo = jnp.where(moving, ranges.moving_radius[0], ranges.static_radius[0])
    hi = jnp.where(moving, ranges.moving_radius[1], ranges.static_radius[1])
    radius = lo + u[:, 1] * (hi - lo)
    pos = (jnp.stack([c, r], axis=-1).astype(jnp.float32) + 0.5) * cell
    keep = radius + ranges.clearance
    apart = ((jnp.linalg.norm(pos - start[None, :], axis=-1) >= keep)
             & (jnp.linalg.norm(pos - goal[None, :], axis=-1) >= keep))  # fmt: skip
    present = opened & apart
    angle = u[:, 2] * (2.0 * math.pi)
    speed = jnp.where(moving, ranges.speed[0] + u[:, 3] * (ranges.speed[1] - ranges.speed[0]), 0.0)
    vel = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1) * speed[:, None]
    return Obstacles(
        pos=jnp.where(present[:, None], pos, ABSENT).astype(jnp.float32),
        vel=jnp.where(present[:, None], vel, 0.0).astype(jnp.float32),
        radius=jnp.where(present, radius, 0.0).astype(jnp.float32),
    )


def absent(n: int) -> Obstacles:
    """``n`` obstacles that are not there (an episode loaded by hand, without its obstacles)."""
    return Obstacles(pos=jnp.full((n, 2), ABSENT, jnp.float32), vel=jnp.zeros((n, 2), jnp.float32),
                     radius=jnp.zeros((n,), jnp.float32))  # fmt: skip


def overlaps(pos: jax.Array, radius, obstacles: Obstacles) -> jax.Array:
    """Whether a disc at ``pos`` overlaps any obstacle (touching is not an overlap)."""
    gap = jnp.linalg.norm(obstacles.pos - pos[None, :], axis=-1)
    return jnp.any((obstacles.radius > 0.0) & (gap < radius + obstacles.radius))


def move(obstacles: Obstacles, row_bits: jax.Array, cell, dt, robot_pos: jax.Array,
         robot_radius) -> Obstacles:  # fmt: skip
    """One step of the people: each walks on, or turns back where it would overlap a wall or the
    robot (and stays this step)."""

    def one(p, v, rad):
        nxt = p + v * dt
        blocked = disc_overlaps_wall_bits(nxt, row_bits, cell, rad) | (
            jnp.linalg.norm(nxt - robot_pos) < rad + robot_radius)  # fmt: skip
        still = jnp.all(v == 0.0)
        return jnp.where(blocked | still, p, nxt), jnp.where(blocked, -v, v)

    pos, vel = jax.vmap(one)(obstacles.pos, obstacles.vel, obstacles.radius)
    return obstacles.replace(pos=pos, vel=vel)


def ray_distances(pos: jax.Array, dx: jax.Array, dy: jax.Array, obstacles: Obstacles) -> jax.Array:
    """(B,) distance along each unit ray to the nearest obstacle it enters (BIG if none)."""
    fx = obstacles.pos[:, 0][None, :] - pos[0]
    fy = obstacles.pos[:, 1][None, :] - pos[1]
    proj = fx * dx[:, None] + fy * dy[:, None]
    perp2 = fx * fx + fy * fy - proj * proj
    r2 = (obstacles.radius * obstacles.radius)[None, :]
    half = jnp.sqrt(jnp.maximum(r2 - perp2, 0.0))
    meets = (obstacles.radius[None, :] > 0.0) & (perp2 <= r2) & (proj + half >= 0.0)
    return jnp.min(jnp.where(meets, jnp.maximum(proj - half, 0.0), BIG), axis=-1)
