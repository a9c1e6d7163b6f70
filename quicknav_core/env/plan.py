"""Shortest collision-free paths for the robot's disc on a room's wall grid (JAX, jit-able, vmappable):
the global planner of the oracle, of the eval's reference lengths and of the curriculum's pool.

The free space of the disc is sampled on a refined grid: every cell is split into ``k x k`` nodes at
the sub-cell centres, and a node is usable when a disc of ``radius`` there overlaps no wall (the
env's own collision test). Nodes connect 8-ways; a diagonal step needs both orthogonal neighbours
usable (no corner cutting). Distances to the goal are found by relaxing every node against its
neighbours until nothing changes (Bellman-Ford on the grid graph, a ``while_loop``: jit-able and
vmappable across rooms). Paths on an 8-connected grid are octile paths, at most ~8 % longer than
the true shortest path; with k = 5 (10 cm nodes on the default room; an odd k puts a node on every cell's centre line, so one-cell corridors keep their full clearance) that is the reference length
used for SPL, minus the goal radius (an episode succeeds on entering the goal disc).

A room's grid may be non-square (rows x cols, ``EnvConfig.grid_shape``); its cells are square and
``room_size`` is its longer side, so a cell is ``room_size / max(rows, cols)``. The packed rows do
not say how many columns a row has: ``cols`` does (None: as many as rows, a square).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from quicknav_core.env.bits import unpack_rows

INF = 1e9
# 8 neighbours (d_row, d_col), orthogonal first
_NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


def _shape(grid: int | tuple[int, int]) -> tuple[int, int]:
    return (grid, grid) if isinstance(grid, int) else (int(grid[0]), int(grid[1]))


def node_positions(grid: int | tuple[int, int], room_size: float | jax.Array, k: int) -> jax.Array:
    """(rows * k, cols * k, 2) x, y of every node (``grid``: a square's side or (rows, cols))."""
    rows, cols = _shape(grid)
    h = room_size / (max(rows, cols) * k)
    xs, ys = jnp.meshgrid((jnp.arange(cols * k, dtype=jnp.float32) + 0.5) * h,
                          (jnp.arange(rows * k, dtype=jnp.float32) + 0.5) * h)  # fmt: skip
    return jnp.stack([xs, ys], axis=-1)  # xs varies along columns


def usable_nodes(row_bits: jax.Array, room_size, radius, k: int, reach: int = 0,
                 cols: int | None = None) -> jax.Array:  # fmt: skip
    """(rows * k, cols * k) bool: the disc fits at the node (``disc_overlaps_wall_bits`` at every
    node, same arithmetic). Computed on the unpacked grid with whole-array gathers: per-node reads
    of the packed rows would hold a (nodes, g, words) selection at once, gigabytes on a large map."""
    g = row_bits.shape[0]
    cols = g if cols is None else cols
    cell = room_size / max(g, cols)
    pad = max(reach, 1)
    # columns beyond the grid read as free (as ``read_bit`` past the row's bits); rows beyond it
    # repeat the nearest row (as the clipped row index does)
    walls = jnp.pad(unpack_rows(row_bits, cols), ((0, 0), (pad, pad)), constant_values=False)
    pts = node_positions((g, cols), room_size, k)
    x, y = pts[..., 0], pts[..., 1]

    def wall(r, c):
        return walls[jnp.clip(r, 0, g - 1), jnp.clip(c, -pad, cols - 1 + pad) + pad]

    if reach:
        col, row = jnp.floor(x / cell).astype(jnp.int32), jnp.floor(y / cell).astype(jnp.int32)
        hit = jnp.zeros(x.shape, bool)
        for dy in range(-reach, reach + 1):
            r = row + dy
            gap_y = jnp.maximum(jnp.maximum(r * cell - y, y - (r + 1) * cell), 0.0)
            for dx in range(-reach, reach + 1):
                c = col + dx
                gap_x = jnp.maximum(jnp.maximum(c * cell - x, x - (c + 1) * cell), 0.0)
                hit = hit | (wall(r, c) & (gap_x * gap_x + gap_y * gap_y < radius * radius))
        return ~hit
    rx, ry = x / cell, y / cell
    fx, fy = jnp.floor(rx), jnp.floor(ry)
    col, row = fx.astype(jnp.int32), fy.astype(jnp.int32)
    frac_x, frac_y = rx - fx, ry - fy
    step_x = jnp.where(frac_x >= 0.5, 1, -1).astype(jnp.int32)
    step_y = jnp.where(frac_y >= 0.5, 1, -1).astype(jnp.int32)
    gap_x = jnp.where(frac_x >= 0.5, 1.0 - frac_x, frac_x) * cell
    gap_y = jnp.where(frac_y >= 0.5, 1.0 - frac_y, frac_y) * cell
    near_col, near_row = col + step_x, row + step_y
    hit = (
        wall(row, col)
        | (wall(row, near_col) & (gap_x < radius))
        | (wall(near_row, col) & (gap_y < radius))
        | (wall(near_row, near_col) & (gap_x * gap_x + gap_y * gap_y < radius * radius))
    )
    return ~hit


def _shift(a: jax.Array, dr: int, dc: int, fill) -> jax.Array:
    """out[r, c] = a[r + dr, c + dc] (``fill`` outside)."""
    n, m = a.shape
    padded = jnp.pad(a, 1, constant_values=fill)
    return jax.lax.dynamic_slice(padded, (1 + dr, 1 + dc), (n, m))


def distance_field(usable: jax.Array, seeds: jax.Array, step: float | jax.Array) -> jax.Array:
    """Shortest 8-connected path length (no corner cutting) from every node to the seeded nodes.

    ``seeds`` (n, n) float: initial distances (INF where not a seed). Unreachable nodes stay >= INF.
    """
    diag = step * math.sqrt(2.0)
    moves = []
    for dr, dc in _NEIGHBOURS:
        ok = usable & _shift(usable, dr, dc, False)
        if dr and dc:  # diagonal: both orthogonal intermediates must be usable
            ok = ok & _shift(usable, dr, 0, False) & _shift(usable, 0, dc, False)
        moves.append((dr, dc, ok, diag if dr and dc else step))

    def relax(d):
        best = d
        for dr, dc, ok, w in moves:
            best = jnp.minimum(best, jnp.where(ok, _shift(d, dr, dc, INF) + w, INF))
        return best

    def cond(carry):
        return carry[1]

    def body(carry):
        d, _ = carry
        new = relax(d)
        return new, jnp.any(new < d)

    d0 = jnp.where(usable, seeds, INF)
    d, _ = jax.lax.while_loop(cond, body, (d0, jnp.bool_(True)))
    return d


def nearest_nodes(pos, n: int | tuple[int, int], h) -> tuple[jax.Array, jax.Array]:
    """The 3x3 block of node indices around ``pos`` (rows (9,), cols (9,)), clipped to the
    (n_rows, n_cols) nodes (``n``: a square's side)."""
    n_rows, n_cols = _shape(n)
    rc = jnp.floor(pos[::-1] / h).astype(jnp.int32)
    off = jnp.array([-1, 0, 1], jnp.int32)
    rows = jnp.repeat(jnp.clip(rc[0] + off, 0, n_rows - 1), 3)
    cols = jnp.tile(jnp.clip(rc[1] + off, 0, n_cols - 1), 3)
    return rows, cols


def goal_field(row_bits, goal, room_size, radius, k: int, reach: int = 0, cols: int | None = None
               ) -> tuple[jax.Array, jax.Array]:  # fmt: skip
    """(distance field to the goal point (rows * k, cols * k), usable (the same))."""
    g = row_bits.shape[0]
    cols = g if cols is None else cols
    h = room_size / (max(g, cols) * k)
    usable = usable_nodes(row_bits, room_size, radius, k, reach, cols)
    nodes = node_positions((g, cols), room_size, k)
    rows, cs = nearest_nodes(goal, usable.shape, h)
    dist = jnp.linalg.norm(nodes[rows, cs] - goal, axis=-1)
    seeds = jnp.full(usable.shape, INF).at[rows, cs].min(jnp.where(usable[rows, cs], dist, INF))
    return distance_field(usable, seeds, h), usable


def path_length_from(field: jax.Array, pos, room_size, k: int) -> jax.Array:
    """Shortest path length from a point: best of the nearby nodes (straight hop + their distance)."""
    h = room_size / max(field.shape)
    rows, cols = nearest_nodes(pos, field.shape, h)
    centres = (jnp.stack([cols, rows], axis=-1).astype(jnp.float32) + 0.5) * h
    return jnp.min(jnp.linalg.norm(centres - pos, axis=-1) + field[rows, cols])


def shortest_path_length(
    row_bits, start, goal, room_size, radius, goal_radius, k: int = 5, reach: int = 0,
    cols: int | None = None,
) -> jax.Array:
    """Reference length of an episode: shortest disc path from ``start`` into the goal disc.

    Returns INF-sized values (>= 1e8) if the goal cannot be reached.
    """
    field, _ = goal_field(row_bits, goal, room_size, radius, k, reach, cols)
    return jnp.maximum(path_length_from(field, start, room_size, k) - goal_radius, 0.0)


def greedy_path(field: jax.Array, usable: jax.Array, start_node: tuple[int, int], max_len: int):
    """Node sequence obtained by always stepping to the neighbour with the smallest distance."""
    n_rows, n_cols = field.shape

    def step(node, _):
        r, c = node
        best = (field[r, c], r, c)
        cand = []
        for dr, dc in _NEIGHBOURS:
            rr, cc = jnp.clip(r + dr, 0, n_rows - 1), jnp.clip(c + dc, 0, n_cols - 1)
            ok = usable[rr, cc]
            if dr and dc:
                ok = ok & usable[rr, c] & usable[r, cc]
            cand.append((jnp.where(ok, field[rr, cc], INF), rr, cc))
        for d, rr, cc in cand:
            better = d < best[0]
            best = (
                jnp.where(better, d, best[0]),
                jnp.where(better, rr, best[1]),
                jnp.where(better, cc, best[2]),
            )
        nxt = (best[1], best[2])
        return nxt, jnp.stack(nxt)

    _, nodes = jax.lax.scan(
        step, (jnp.int32(start_node[0]), jnp.int32(start_node[1])), None, max_len
    )
    return nodes


# --------------------------------------------------------------------------- the env's global plan
def disc_fits(walls: jax.Array, cell, radius, reach: int) -> jax.Array:
    """(rows, cols) bool: free cells whose centre holds the disc clear of every wall cell (all free cells
    for a robot narrower than a cell, ``reach`` 0); ``clearance.disc_fits`` in JAX."""
    fits = ~walls
    if reach == 0:
        return fits
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            gy, gx = max(abs(dy) - 0.5, 0.0), max(abs(dx) - 0.5, 0.0)  # cells to the neighbour
            near = (gy * gy + gx * gx) * cell * cell < radius * radius
            fits = fits & ~(near & _shift(walls, dy, dx, True))
    return fits


def cell_field(usable: jax.Array, goal_rc: jax.Array) -> jax.Array:
    """(rows, cols) float32: the shortest 8-connected path (no corner cutting) from every usable cell to
    the goal's cell, in cells (``INF``-sized where the goal cannot be reached)."""
    seeds = jnp.full(usable.shape, INF, jnp.float32).at[goal_rc[0], goal_rc[1]].set(0.0)
    return distance_field(usable, seeds, 1.0)


def plan_waypoints(field: jax.Array, usable: jax.Array, rc: jax.Array, goal: jax.Array, cell,
                   lookahead: int, count: int) -> jax.Array:  # fmt: skip
    """(count, 2) x, y of the plan's waypoints: the cell reached after ``i * lookahead`` steps down
    the field from the robot's cell ``rc`` (row, col), i = 1..count, its centre; the goal itself
    once the path has reached the goal's cell."""
    nodes = greedy_path(field, usable, (rc[0], rc[1]), lookahead * count)  # (L*count, 2) row, col
    picked = nodes[lookahead - 1 :: lookahead]  # (count, 2)
    centres = (picked[:, ::-1].astype(jnp.float32) + 0.5) * cell
    at_goal = field[picked[:, 0], picked[:, 1]] <= 0.0
    return jnp.where(at_goal[:, None], goal[None, :], centres)


def plan_features(pos, theta, waypoints, field, rc, cell, lookahead: int, path_scale: float) -> jax.Array:
    """The plan's observation: per waypoint (forward, left) in the robot's frame divided by the
    farthest it can lie, then tanh(path length left in metres / ``path_scale``)."""
    count = waypoints.shape[0]
    rel = waypoints - pos[None, :]
    c, s = jnp.cos(theta), jnp.sin(theta)
    fwd = c * rel[:, 0] + s * rel[:, 1]
    left = c * rel[:, 1] - s * rel[:, 0]
    # i * lookahead steps of at most sqrt(2) cells, and half a cell's diagonal at either end
    reach = (jnp.arange(1, count + 1, dtype=jnp.float32) * lookahead + 1.0) * math.sqrt(2.0) * cell
    points = jnp.clip(jnp.stack([fwd, left], axis=-1) / reach[:, None], -1.0, 1.0).reshape(-1)
    left_m = jnp.minimum(field[rc[0], rc[1]], 1e6) * cell
    return jnp.concatenate([points, jnp.tanh(left_m / path_scale)[None]]).astype(jnp.float32)
