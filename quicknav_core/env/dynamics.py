"""Differential drive, disc-versus-wall collision, and sliding along walls."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from quicknav_core.env.bits import pack_rows, read_bit


def wheel_command(action: jax.Array) -> jax.Array:
    """Sanitise an action: NaN counts as 0, then clip to [-1, 1]. (2,) float32 (left, right)."""
    action = jnp.asarray(action, jnp.float32).reshape(2)
    return jnp.clip(jnp.where(jnp.isnan(action), 0.0, action), -1.0, 1.0)


def wrap_angle(theta: jax.Array) -> jax.Array:
    """Wrap an angle to [-pi, pi)."""
    return jnp.mod(theta + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def drive(
    theta: jax.Array,
    action: jax.Array,
    max_wheel_speed: jax.Array | float,
    wheel_base: jax.Array | float,
    dt: jax.Array | float,
) -> tuple[jax.Array, jax.Array]:
    """Unicycle update of a differential drive (midpoint heading). Returns (delta (2,), new theta)."""
    left, right = action[0] * max_wheel_speed, action[1] * max_wheel_speed
    v = 0.5 * (left + right)
    omega = (right - left) / wheel_base
    mid = theta + 0.5 * omega * dt
    delta = jnp.stack([v * dt * jnp.cos(mid), v * dt * jnp.sin(mid)])
    return delta, wrap_angle(theta + omega * dt)


def _row_word(row_bits: jax.Array, row: jax.Array) -> jax.Array:
    """Packed words of one row: (W,). Up to 32 cells a side selected by a one-hot mask (no gather
    under vmap, over a few words); larger grids gather the row (a mask over a 128-cell grid's rows
    cost more than the rest of the step)."""
    g = row_bits.shape[0]
    if row_bits.shape[1] > 1:
        return row_bits[row]
    pick = (jnp.arange(g, dtype=jnp.int32) == row)[:, None]
    return jnp.sum(jnp.where(pick, row_bits, jnp.uint32(0)), axis=0, dtype=jnp.uint32)


def disc_overlaps_wall_bits(
    pos: jax.Array, row_bits: jax.Array, cell: jax.Array | float, radius: jax.Array | float,
    reach: int = 0,
) -> jax.Array:
    """Whether a disc at ``pos`` overlaps a wall of a row-packed grid.

    ``reach=0``: the radius is below half a cell, so the disc can only reach its own cell, the
    neighbour across the nearer vertical side, the neighbour across the nearer horizontal side, and
    the diagonal cell between those two: four cells, not the whole grid. A wider robot
    (``reach`` >= 1, ``clearance.reach_cells``: how many cells away its disc can reach) checks the
    square of cells ``reach`` around its own. Touching (distance == radius) is not an overlap.
    """
    if reach:
        return _disc_overlaps_window(pos, row_bits, cell, radius, reach)
    g = row_bits.shape[0]
    rel = pos / cell
    cell_xy = jnp.floor(rel)
    frac = rel - cell_xy  # position inside the cell, in cell units, [0, 1)
    col, row = cell_xy.astype(jnp.int32)
    step = jnp.where(frac >= 0.5, 1, -1).astype(jnp.int32)  # towards the nearer side, per axis
    gap = jnp.where(frac >= 0.5, 1.0 - frac, frac) * cell  # distance to that side, metres
    near_col, near_row = col + step[0], row + step[1]
    own_row = _row_word(row_bits, jnp.clip(row, 0, g - 1))
    side_row = _row_word(row_bits, jnp.clip(near_row, 0, g - 1))
    own = read_bit(own_row, col)
    across_x = read_bit(own_row, near_col)
    across_y = read_bit(side_row, col)
    diagonal = read_bit(side_row, near_col)
    r2 = radius * radius
    return (
        own
        | (across_x & (gap[0] < radius))
        | (across_y & (gap[1] < radius))
        | (diagonal & (gap[0] * gap[0] + gap[1] * gap[1] < r2))
    )


def _disc_overlaps_window(pos, row_bits, cell, radius, reach: int) -> jax.Array:
    """A disc against every wall cell up to ``reach`` cells from its own (a wide robot)."""
    g = row_bits.shape[0]
    col, row = jnp.floor(pos / cell).astype(jnp.int32)
    hit = jnp.zeros((), bool)
    for dy in range(-reach, reach + 1):
        r = row + dy
        # a row beyond the grid repeats the outer ring: wall, and farther than the ring itself
        words = _row_word(row_bits, jnp.clip(r, 0, g - 1))
        gap_y = jnp.maximum(jnp.maximum(r * cell - pos[1], pos[1] - (r + 1) * cell), 0.0)
        for dx in range(-reach, reach + 1):
            c = col + dx
            gap_x = jnp.maximum(jnp.maximum(c * cell - pos[0], pos[0] - (c + 1) * cell), 0.0)
            hit = hit | (read_bit(words, c) & (gap_x * gap_x + gap_y * gap_y < radius * radius))
    return hit


def disc_overlaps_wall(
    pos: jax.Array, walls: jax.Array, cell: jax.Array | float, radius: jax.Array | float,
    reach: int = 0,
) -> jax.Array:
    """``disc_overlaps_wall_bits`` for a (rows, cols) bool wall grid."""
    return disc_overlaps_wall_bits(pos, pack_rows(jnp.asarray(walls, bool)), cell, radius, reach)


def wall_distance(pos: jax.Array, row_bits: jax.Array, cell: jax.Array | float) -> jax.Array:
    """Metres from ``pos`` to the nearest wall cell of the 3x3 cells around its own (farther walls
    are at least a cell away: ``cell`` if none is near)."""
    g, w = row_bits.shape
    rc = jnp.floor(pos[::-1] / cell).astype(jnp.int32)
    off = jnp.array([-1, 0, 1], jnp.int32)
    rows = jnp.clip(rc[0] + off, 0, g - 1)
    # the robot is inside the outer ring, so its neighbours are on the grid; columns are kept to
    # the packed row's bits (the row does not say how many of them are the room's)
    cols = jnp.clip(rc[1] + off, 0, 32 * w - 1)
    walls = jax.vmap(lambda r: read_bit(_row_word(row_bits, r), cols))(rows)  # (3, 3)
    y0, x0 = rows.astype(jnp.float32) * cell, cols.astype(jnp.float32) * cell
    gap_y = jnp.maximum(jnp.maximum(y0 - pos[1], pos[1] - (y0 + cell)), 0.0)
    gap_x = jnp.maximum(jnp.maximum(x0 - pos[0], pos[0] - (x0 + cell)), 0.0)
    dist = jnp.sqrt(gap_y[:, None] ** 2 + gap_x[None, :] ** 2)
    return jnp.min(jnp.where(walls, dist, cell))


def move_with_sliding(
    pos: jax.Array,
    delta: jax.Array,
    row_bits: jax.Array,
    cell: jax.Array | float,
    radius: jax.Array | float,
    reach: int = 0,
) -> tuple[jax.Array, jax.Array]:
    """Apply a translation; on a wall collision keep the feasible axis of the move, or stay.

    ``row_bits`` is the row-packed wall grid. Returns (new pos (2,), collided ()). When both
    single-axis moves are feasible (a corner), the axis with the larger displacement wins (x on a tie).
    """
    full = pos + delta
    only_x = pos + jnp.stack([delta[0], 0.0])
    only_y = pos + jnp.stack([0.0, delta[1]])
    hit_full = disc_overlaps_wall_bits(full, row_bits, cell, radius, reach)
    ok_x = ~disc_overlaps_wall_bits(only_x, row_bits, cell, radius, reach)
    ok_y = ~disc_overlaps_wall_bits(only_y, row_bits, cell, radius, reach)
    prefer_x = jnp.abs(delta[0]) >= jnp.abs(delta[1])
    slide = jnp.where(
        ok_x & ok_y,
        jnp.where(prefer_x, only_x, only_y),
        jnp.where(ok_x, only_x, jnp.where(ok_y, only_y, pos)),
    )
    return jnp.where(hit_full, slide, full), hit_full
