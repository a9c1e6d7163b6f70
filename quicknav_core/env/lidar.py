"""2-D lidar by grid ray casting: every beam tests only the grid lines it crosses.

Two formulations with identical results (tests hold both to a brute-force caster and the NumPy
twin), chosen by ``EnvConfig.lidar_method``:

- ``crossings`` (below): every crossing of every beam at once, walls read from bit-packed rows and
  columns; fixed work of 2(g-1) crossings per beam on grids up to 32 cells, and above them only the
  lines within range of the robot (``lidar_window``), each crossed by the one beam of a pair that
  meets it (``_first_walls_near``). Tuned on CPU.
- ``dda``: each beam walks cell by cell (Amanatides & Woo) and stops at its first wall or at
  ``max_range``; work is the distance travelled, one row-word gather per step. Written for GPUs.

``auto`` picks the faster one for the backend by the figures in ``FASTEST_LIDAR``.

For a beam from ``pos`` along unit direction ``(dx, dy)`` the cells it passes through are exactly
the cells entered at its crossings with the vertical lines ``x = k*c`` and the horizontal lines
``y = k*c`` (k = 1 .. grid-1; the outer ring is wall, so every beam stops inside the room). All
crossings of a beam are computed at once, in cell units; whether the entered cell is a wall is read
from the room's bit-packed columns and rows (``bits.py``), so the inner loop is a multiply-add, a
floor, a shift and a compare: no gathers and no loop over wall cells. The nearest wall crossing and
the beam's entry into the goal disc compete; beyond ``max_range`` the beam reports nothing.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from quicknav_core.env.bits import pack_rows, read_bit
from quicknav_core.env.constants import BIG as _BIG
from quicknav_core.env.constants import HIT_GOAL, HIT_NONE, HIT_WALL, beam_angles, beam_offsets

__all__ = [
    "FASTEST_LIDAR", "LIDAR_METHODS", "beam_angles", "cast_lidar", "cast_lidar_bits",
    "cast_lidar_dda", "cast_lidar_packed", "cast_lidar_window", "lidar_is_paired", "lidar_window",
    "ray_disc", "resolve_lidar_method", "side_words", "uses_window", "window_bits",
]  # fmt: skip

LIDAR_METHODS = ("crossings", "dda")
# The faster method per JAX backend, as measured by benchmarks/gpu_suite.py (stage env+lidar, whole
# observation consumed, 4,096 envs). cpu: crossings, dda at 0.17-0.22x of its steps/s (grid 16 and
# 32, 16 and 64 beams; 2-core Intel Xeon VM, benchmarks/results/gpu-suite-cpu-cpu.json). gpu: not
# measured yet (no GPU lent so far): crossings until a GPU run of the suite says otherwise.
FASTEST_LIDAR = {"cpu": "crossings", "gpu": "crossings", "tpu": "crossings"}


def resolve_lidar_method(method: str, backend: str | None = None) -> str:
    """The method ``auto`` stands for on ``backend`` (default: JAX's default backend)."""
    if method != "auto":
        if method not in LIDAR_METHODS:
            raise ValueError(f"lidar_method={method!r}: allowed 'auto', " + ", ".join(
                repr(m) for m in LIDAR_METHODS))  # fmt: skip
        return method
    return FASTEST_LIDAR.get(backend or jax.default_backend(), "crossings")


def _entered_bits(origin_a: jax.Array, line_bits: jax.Array) -> jax.Array:
    """Packed walls of the cell a beam enters when it crosses line ``k`` (k = 1..g-1), per line.

    A beam that reaches line k at t >= 0 moves towards it, so it enters cell k when the line lies on
    the far side of the origin (k > origin) and cell k-1 otherwise, whatever its direction: one
    choice per line and env, shared by every beam. Returns (g-1, W).
    """
    g = line_bits.shape[0]
    ahead = jnp.arange(1, g, dtype=jnp.float32) > origin_a
    return jnp.where(ahead[:, None], line_bits[1:], line_bits[:-1])


def _crossings(
    origin_a: jax.Array,
    origin_b: jax.Array,
    dir_a: jax.Array,
    dir_b: jax.Array,
    entered: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """Signed distances to the lines ``a = k`` (cell units) and whether the cell entered there is wall.

    dir_* are (B,) unit-vector components; ``entered`` is ``_entered_bits`` (g-1, W). Returns
    (t (B, g-1), wall (B, g-1)); ``wall`` is meaningful where the crossing is ahead (t >= 0), and,
    for the opposite beam, where t < 0: the same crossing point seen from the other side.
    """
    t, idx = _crossing_points(origin_a, origin_b, dir_a, dir_b, 1.0, entered.shape[0])
    return t, read_bit(entered[None, :, :], idx)


def _crossing_points(origin_a, origin_b, dir_a, dir_b, k0, lines: int):
    """Signed distances (B, lines) to the lines ``a = k0 .. k0 + lines - 1`` and the cell index
    along ``b`` of each crossing. The index leaves [0, g) only where the crossing lies outside the
    room, i.e. beyond the outer wall ring that every beam hits first; whatever such a crossing
    reads cannot win the min."""
    k = k0 + jnp.arange(lines, dtype=jnp.float32)
    inv = 1.0 / jnp.where(jnp.abs(dir_a) < 1e-12, 1e-12, dir_a)
    t = (k[None, :] - origin_a) * inv[:, None]
    return t, jnp.floor(origin_b + t * dir_b[:, None]).astype(jnp.int32)


def beam_directions(theta: jax.Array, num_beams: int, fov_deg: float, first: int | None = None):
    """Unit directions (dx, dy), each (B,), of the first ``first`` beams (default all): the
    heading rotated by the beams' offsets (``constants.beam_offsets``), one sine and cosine."""
    ca, sa = beam_offsets(num_beams, fov_deg)
    ca, sa = ca[:first], sa[:first]
    ct, st = jnp.cos(theta), jnp.sin(theta)
    return ct * ca - st * sa, st * ca + ct * sa


def _first_walls(
    origin_a: jax.Array, origin_b: jax.Array, dir_a: jax.Array, dir_b: jax.Array, entered: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """For each beam and its opposite: distance (cell units) to the first wall crossing of the
    lines ``a = k``, BIG if none; the same crossings and walls as ``_crossings``.

    The walls a beam pair meets on these lines are gathered into one bit mask per beam (bit k: the
    cell entered at line k is a wall). The beam moving towards +a meets the lines k > origin in
    increasing order, its opposite the lines k <= origin in decreasing order, so each one's first
    wall is the lowest set bit above the origin, or the highest at or below it: two bit scans
    instead of a masked minimum over every line. Grids up to 32 cells (31 lines, one word)."""
    g1 = entered.shape[0]
    u32 = jnp.uint32
    k = jnp.arange(1, g1 + 1, dtype=jnp.float32)
    inv = 1.0 / jnp.where(jnp.abs(dir_a) < 1e-12, 1e-12, dir_a)
    t = (k[None, :] - origin_a) * inv[:, None]
    idx = jnp.floor(origin_b + t * dir_b[:, None]).astype(jnp.int32)
    wall = read_bit(entered[None, :, :], idx).astype(u32)  # (B, g-1)
    mask = jnp.sum(jnp.left_shift(wall, jnp.arange(1, g1 + 1, dtype=u32)), axis=-1, dtype=u32)
    low = jnp.left_shift(u32(1), (jnp.floor(origin_a).astype(jnp.int32) + 1).astype(u32)) - u32(1)
    above, below = mask & ~low, mask & low  # lines k > origin, lines k <= origin
    k_above = (31 - jax.lax.clz(above & (~above + u32(1)))).astype(jnp.float32)  # lowest set bit
    k_below = (31 - jax.lax.clz(below)).astype(jnp.float32)  # highest set bit
    t_above = jnp.where(above != 0, (k_above - origin_a) * inv, _BIG)
    t_below = jnp.where(below != 0, (k_below - origin_a) * inv, _BIG)
    towards_plus = dir_a > 0
    forward = jnp.where(towards_plus, t_above, jnp.where(below != 0, t_below, _BIG))
    backward = jnp.where(towards_plus, jnp.where(below != 0, -t_below, _BIG), jnp.where(
        above != 0, -t_above, _BIG))  # fmt: skip
    parallel = jnp.abs(dir_a) < 1e-12  # never meets these lines
    return jnp.where(parallel, _BIG, forward), jnp.where(parallel, _BIG, backward)


def ray_disc(
    pos: jax.Array, dx: jax.Array, dy: jax.Array, centre: jax.Array, radius: jax.Array | float
) -> jax.Array:
    """Distance along each unit ray to where it enters a disc (0 if it starts inside, BIG if never)."""
    fx = centre[0] - pos[0]
    fy = centre[1] - pos[1]
    proj = fx * dx + fy * dy
    perp2 = fx * fx + fy * fy - proj * proj
    half = jnp.sqrt(jnp.maximum(radius * radius - perp2, 0.0))
    meets = (perp2 <= radius * radius) & (proj + half >= 0.0)
    return jnp.where(meets, jnp.maximum(proj - half, 0.0), _BIG)


def lidar_is_paired(num_beams: int, fov_deg: float) -> bool:
    """A 360° lidar with an even beam count has opposite beams that share every line crossing."""
    return fov_deg >= 360.0 and num_beams % 2 == 0


def cast_lidar_bits(
    pos: jax.Array,
    theta: jax.Array,
    goal: jax.Array,
    col_bits: jax.Array,
    row_bits: jax.Array,
    num_beams: int,
    fov_deg: float,
    cell: jax.Array | float,
    max_range: jax.Array | float,
    goal_radius: jax.Array | float,
    lines: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Cast all beams over packed walls. Returns (ranges (B,) float32 metres, hits (B,) int32).

    ``col_bits[c]`` packs column c (bit r = walls[r, c]); ``row_bits[r]`` packs row r.
    ``num_beams`` and ``fov_deg`` are static. With a 360° lidar and an even beam count, beam i and
    beam i + B/2 point in opposite directions and meet each grid line at the same point, so each
    crossing is computed once for the pair (about a third less work).

    ``lines`` (static; ``lidar_window``) bounds the work by the lidar's range instead of the
    grid: only that many lines per axis around the robot are crossed, the window that holds every
    line within ``max_range`` (a wall beyond it is out of range, so the result is the same). None:
    every line of the grid.
    """
    g = max(row_bits.shape[0], col_bits.shape[0])  # a non-square room: its longer side
    if uses_window(g, lines):  # the window, laid out for this one room
        return cast_lidar_window(pos, theta, goal, window_bits(col_bits, lines)[None],
                                 window_bits(row_bits, lines)[None], 0, num_beams, fov_deg, cell,
                                 max_range, goal_radius, lines)  # fmt: skip
    inv_cell = 1.0 / cell
    px, py = pos[0] * inv_cell, pos[1] * inv_cell
    enter_x = _entered_bits(px, col_bits)
    enter_y = _entered_bits(py, row_bits)
    paired = lidar_is_paired(num_beams, fov_deg)
    half = num_beams // 2 if paired else num_beams
    dx, dy = beam_directions(theta, num_beams, fov_deg, half)
    if g <= 32:  # one word of lines per axis: the bit-scan search
        fwd_v, back_v = _first_walls(px, py, dx, dy, enter_x)
        fwd_h, back_h = _first_walls(py, px, dy, dx, enter_y)
        t_wall = jnp.minimum(fwd_v, fwd_h)
        if paired:
            t_wall = jnp.concatenate([t_wall, jnp.minimum(back_v, back_h)])
            dx, dy = jnp.concatenate([dx, -dx]), jnp.concatenate([dy, -dy])
        return _with_goal(jnp.where(t_wall < _BIG, t_wall * cell, _BIG), pos, dx, dy, goal,
                          max_range, goal_radius)  # fmt: skip
    t_v, wall_v = _crossings(px, py, dx, dy, enter_x)
    t_h, wall_h = _crossings(py, px, dy, dx, enter_y)
    t = jnp.concatenate([t_v, t_h], axis=-1)
    wall = jnp.concatenate([wall_v, wall_h], axis=-1)
    t_wall = jnp.min(jnp.where(wall & (t >= 0.0), t, _BIG), axis=-1)
    if paired:
        t_back = jnp.min(jnp.where(wall & (t < 0.0), -t, _BIG), axis=-1)
        t_wall = jnp.concatenate([t_wall, t_back])
        dx, dy = jnp.concatenate([dx, -dx]), jnp.concatenate([dy, -dy])
    return _with_goal(t_wall * cell, pos, dx, dy, goal, max_range, goal_radius)


def lidar_window(grid_size: int, cell: float, max_range: float) -> int:
    """Grid lines per axis the caster must cross to see ``max_range`` from anywhere in a cell:
    those within ``ceil(max_range / cell)`` of the robot's cell on either side, one more each way
    for rounding, at most the grid's ``g - 1`` (a window of 2 * reach + 3 lines: the windowed
    caster takes the reach + 1 on each side of the robot's cell). Grids up to 32 cells always take
    all their lines (the bit-scan search over one word), so a range changes nothing compiled
    there."""
    if grid_size <= 32:
        return grid_size - 1
    reach = math.ceil(max_range / cell - 1e-9)
    return min(grid_size - 1, 2 * reach + 3)


def side_words(lines: int) -> int:
    """Words per side of the robot that hold every cell a crossing within range can enter along
    the other axis: the window's ``(lines - 1) / 2`` lines a side (a reach and one more for
    rounding) and the robot's own cell, 32 cells a word (one word up to a reach of 30 cells)."""
    return -(-((lines - 1) // 2 + 1) // 32)


def uses_window(grid_size: int, lines: int | None) -> bool:
    """Whether the caster crosses only a window of ``lines`` lines per axis (grids above 32 cells
    whose lidar range is shorter than the grid), reading it from ``window_bits``."""
    return lines is not None and grid_size > 32 and lines < grid_size - 1


def window_bits(line_bits: jax.Array, lines: int) -> jax.Array:
    """(..., g, W) packed lines -> (..., g + 2h, W + 2m), h = (lines - 1) // 2, m =
    ``side_words(lines)``: the lines with h free lines before and after them and m free words on
    either side, so that the window of any robot's cell is one slice, the same for every cell
    (``EnvParams.room_col_window``). Bit q of a padded line is cell q - 32m."""
    half, m = (lines - 1) // 2, side_words(lines)
    pad = [(0, 0)] * (line_bits.ndim - 2) + [(half, half), (m, m)]
    return jnp.pad(line_bits, pad)


def _side_words(window: jax.Array, origin_b: jax.Array, m: int):
    """Each line's cells next to the origin along the other axis, ``m`` words a side: ``up``
    (lines, m) holds cells f .. f + 32m - 1 (bit i of the whole: cell f + i), ``down`` cells
    f - 32m + 1 .. f (bit i: cell f - 32m + 1 + i), where f = floor(origin_b); ``window`` is
    (lines, 2m + 1): a padded line's words j .. j + 2m (``window_bits``), j = (f + 1) // 32.
    Returns (up, down, f).

    A beam whose component along the other axis is >= 0 enters, within range, only cells
    f .. f + reach, and one whose component is negative only cells f - reach .. f: either reads
    each of its crossings from its own side's words by a shift (and, beyond a reach of 30 cells,
    a choice of word)."""
    f = jnp.floor(origin_b).astype(jnp.int32)
    j = (f + 1) // 32
    r = ((f + 1) % 32).astype(jnp.uint32)

    def funnel(lo: jax.Array, hi: jax.Array, shift: jax.Array) -> jax.Array:  # 32 bits of hi:lo from bit shift
        return jnp.right_shift(lo, shift) | jnp.left_shift(hi, jnp.uint32(32) - shift)  # 32: 0

    # down word w: cells from f - 32m + 1 + 32w, padded bit f + 1 + 32w: word j + w, bit r
    down = [funnel(window[:, w], window[:, w + 1], r) for w in range(m)]
    # up word w: cells from f + 32w, padded bit f + 32(m + w): word j + m + w - 1 or j + m + w
    q = f + 32 * m
    up_r = (q % 32).astype(jnp.uint32)
    late = (q // 32 - j) - m  # -1 or 0
    up = []
    for w in range(m):
        part = window[:, m + w - 1:m + w + 2]  # words m + w - 1 .. m + w + 1 of the slice
        lo = jnp.where(late < 0, part[:, 0], part[:, 1])
        hi = jnp.where(late < 0, part[:, 1], part[:, 2])
        up.append(funnel(lo, hi, up_r))
    return jnp.stack(up, axis=1), jnp.stack(down, axis=1), f


def _side_bit(words: jax.Array, bit: jax.Array) -> jax.Array:
    """Bit ``bit`` (B, lines) of each line's side words (lines, m), m small: where it lies in
    [0, 32m) (a crossing within range), what the word holds; beyond, whatever (out of range)."""
    m = words.shape[-1]
    word = words[None, :, 0]
    for w in range(1, m):
        word = jnp.where(bit >= 32 * w, words[None, :, w], word)
    return (jnp.right_shift(word, (bit & 31).astype(jnp.uint32)) & jnp.uint32(1)) != 0


def _first_walls_near(origin_a, origin_b, dir_a, dir_b, padded, room, half: int, m: int):
    """The first wall each beam's two movers meet on the lines ``a = k`` within ``half`` lines
    of the origin: (ahead (B,), behind (B,)) distances in cell units, BIG if none. ``padded`` is
    a bank of ``window_bits`` (rooms, g + 2 * half, W + 2m), ``room`` the room's index in it.

    A beam along (dir_a, dir_b) and its opposite meet every line at the same point; the one that
    moves towards +a meets the lines ahead of the origin (k > origin), entering cell k, the other
    the lines behind it (k <= origin), entering cell k - 1. So the lines are taken in two halves of
    ``half`` lines, ahead and behind, each crossed once per beam by the mover that meets it, at
    the distance ``|k - origin| / |dir_a|``: every crossing is ahead of its mover and the first
    wall is a plain minimum (no test of the crossing's side, no second pass for the opposite beam).
    Both halves are one slice of the padded lines (rows fa - half .. fa + half); lines off the grid
    read as free (beyond the outer wall ring, they cannot change what a beam reports)."""
    fa = jnp.floor(origin_a).astype(jnp.int32)
    j = (jnp.floor(origin_b).astype(jnp.int32) + 1) // 32
    # padded row fa + i holds cell row fa - half + i; the window is rows fa - half .. fa + half
    window = jax.lax.dynamic_slice(padded, (room, fa, j), (1, 2 * half + 1, 2 * m + 1))[0]
    inv = 1.0 / jnp.where(jnp.abs(dir_a) < 1e-12, 1e-12, jnp.abs(dir_a))
    # the b-component of the beam's mover towards +a
    b_ahead = dir_b * jnp.where(dir_a < 0, -1.0, 1.0)
    i = jnp.arange(half, dtype=jnp.int32)
    found = []
    for rows, k, sign, b in (
        (window[half + 1:], fa + 1 + i, 1.0, b_ahead),  # lines fa+1 .. fa+half enter cells k
        (window[:half], fa - half + 1 + i, -1.0, -b_ahead),  # lines fa-half+1 .. fa enter k - 1
    ):
        t = (sign * (k.astype(jnp.float32)[None, :] - origin_a)) * inv[:, None]  # (B, half)
        idx = jnp.floor(origin_b + t * b[:, None]).astype(jnp.int32)
        up, down, fb = _side_words(rows, origin_b, m)
        going_up = (b >= 0)[:, None]
        if m == 1:
            word = jnp.where(going_up, up[None, :, 0], down[None, :, 0])
            bit = jnp.where(going_up, idx - fb, idx - (fb - 31))  # in [0, 32) within range
            wall = (jnp.right_shift(word, (bit & 31).astype(jnp.uint32)) & jnp.uint32(1)) != 0
        else:
            down_bit = idx - (fb - 32 * m + 1)
            wall = jnp.where(going_up, _side_bit(up, idx - fb), _side_bit(down, down_bit))
        found.append(jnp.min(jnp.where(wall, t, _BIG), axis=-1))
    return found[0], found[1]


def cast_lidar_window(
    pos: jax.Array,
    theta: jax.Array,
    goal: jax.Array,
    col_window: jax.Array,
    row_window: jax.Array,
    room: jax.Array | int,
    num_beams: int,
    fov_deg: float,
    cell: jax.Array | float,
    max_range: jax.Array | float,
    goal_radius: jax.Array | float,
    lines: int,
) -> tuple[jax.Array, jax.Array]:
    """``cast_lidar_bits`` over the lines within range of the robot (``lidar_window``), from a
    bank of rooms laid out for it (``window_bits`` of the column- and row-packed walls, room
    ``room``): ``(lines - 1) / 2`` lines on each side of its cell per axis
    (``_first_walls_near``). Exactly the whole grid's result (a crossing beyond range reads
    whatever, and cannot change what the beam reports), at about half the work of crossing the
    window's lines with both beams of a pair."""
    half, m = (lines - 1) // 2, side_words(lines)
    inv_cell = 1.0 / cell
    px, py = pos[0] * inv_cell, pos[1] * inv_cell
    paired = lidar_is_paired(num_beams, fov_deg)
    dx, dy = beam_directions(theta, num_beams, fov_deg, num_beams // 2 if paired else num_beams)
    ahead_x, behind_x = _first_walls_near(px, py, dx, dy, col_window, room, half, m)
    ahead_y, behind_y = _first_walls_near(py, px, dy, dx, row_window, room, half, m)
    t_wall = jnp.minimum(jnp.where(dx > 0, ahead_x, behind_x), jnp.where(dy > 0, ahead_y, behind_y))
    if paired:
        t_back = jnp.minimum(jnp.where(dx > 0, behind_x, ahead_x), jnp.where(dy > 0, behind_y, ahead_y))
        t_wall = jnp.concatenate([t_wall, t_back])
        dx, dy = jnp.concatenate([dx, -dx]), jnp.concatenate([dy, -dy])
    return _with_goal(jnp.where(t_wall < _BIG, t_wall * cell, _BIG), pos, dx, dy, goal, max_range,
                      goal_radius)  # fmt: skip


def _with_goal(t_wall, pos, dx, dy, goal, max_range, goal_radius):
    """Ranges and hit types from the wall distance (metres, BIG if none) and the goal disc."""
    t_goal = ray_disc(pos, dx, dy, goal, goal_radius)
    t_near = jnp.minimum(t_wall, t_goal)
    in_range = t_near <= max_range
    hits = jnp.where(in_range, jnp.where(t_goal < t_wall, HIT_GOAL, HIT_WALL), HIT_NONE)
    ranges = jnp.where(in_range, t_near, max_range).astype(jnp.float32)
    return ranges, hits.astype(jnp.int32)


def cast_lidar_dda(
    pos: jax.Array,
    theta: jax.Array,
    goal: jax.Array,
    col_bits: jax.Array,
    row_bits: jax.Array,
    num_beams: int,
    fov_deg: float,
    cell: jax.Array | float,
    max_range: jax.Array | float,
    goal_radius: jax.Array | float,
    lines: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """``cast_lidar_bits`` by a cell walk per beam (same arguments, same results).

    In cell units, a beam's next vertical line is ``lx`` (integer) at ``t = (lx - px) / dx``, its
    next horizontal line ``ly`` likewise: the nearer one is crossed, the cell on its far side
    entered and read (one row word gathered, one bit); the walk ends at the first wall or past
    ``max_range``. Distances are computed from the line index each time, as the crossings method
    does, so no error accumulates along the walk. ``col_bits`` is not read.
    """
    rows, cols = row_bits.shape[0], col_bits.shape[0]
    del col_bits, lines  # only its shape: the walk ends at max_range by itself
    inv_cell = 1.0 / cell
    px, py = pos[0] * inv_cell, pos[1] * inv_cell
    dx, dy = beam_directions(theta, num_beams, fov_deg)
    # a beam parallel to an axis never meets that axis' lines: their distance stays BIG
    flat_x, flat_y = jnp.abs(dx) < 1e-12, jnp.abs(dy) < 1e-12
    inv_x = 1.0 / jnp.where(flat_x, 1.0, dx)
    inv_y = 1.0 / jnp.where(flat_y, 1.0, dy)
    step_x = jnp.where(dx > 0, 1, -1).astype(jnp.int32)
    step_y = jnp.where(dy > 0, 1, -1).astype(jnp.int32)
    cx0 = jnp.floor(px).astype(jnp.int32)
    cy0 = jnp.floor(py).astype(jnp.int32)
    # the next line ahead: the cell's far side in the direction of travel
    lx0 = (cx0 + (dx > 0)).astype(jnp.float32) * jnp.ones_like(dx)
    ly0 = (cy0 + (dy > 0)).astype(jnp.float32) * jnp.ones_like(dy)
    limit = max_range * inv_cell
    n = num_beams

    def cond(carry):
        return jnp.any(~carry[-1])

    def body(carry):
        cx, cy, lx, ly, t_hit, done = carry
        tx = jnp.where(flat_x, _BIG, (lx - px) * inv_x)
        ty = jnp.where(flat_y, _BIG, (ly - py) * inv_y)
        take_x = tx < ty
        t = jnp.where(take_x, tx, ty)
        cx = jnp.where(take_x & ~done, cx + step_x, cx)
        cy = jnp.where(~take_x & ~done, cy + step_y, cy)
        lx = jnp.where(take_x & ~done, lx + step_x, lx)
        ly = jnp.where(~take_x & ~done, ly + step_y, ly)
        words = row_bits[jnp.clip(cy, 0, rows - 1)]  # (B, W): the row word(s) of the entered cell
        wall = read_bit(words, jnp.clip(cx, 0, cols - 1))
        beyond = t > limit
        hit_now = wall & ~done & ~beyond
        t_hit = jnp.where(hit_now, t, t_hit)
        return cx, cy, lx, ly, t_hit, done | hit_now | beyond

    init = (
        jnp.broadcast_to(cx0, (n,)), jnp.broadcast_to(cy0, (n,)), lx0, ly0,
        jnp.full((n,), _BIG, jnp.float32), jnp.zeros((n,), bool),
    )  # fmt: skip
    *_, t_hit, _ = jax.lax.while_loop(cond, body, init)
    t_wall = jnp.where(t_hit < _BIG, t_hit * cell, _BIG)
    return _with_goal(t_wall, pos, dx, dy, goal, max_range, goal_radius)


def cast_lidar_packed(method: str):
    """The caster for a resolved method name (``crossings`` or ``dda``)."""
    return {"crossings": cast_lidar_bits, "dda": cast_lidar_dda}[resolve_lidar_method(method)]


def cast_lidar(
    pos: jax.Array,
    theta: jax.Array,
    goal: jax.Array,
    walls: jax.Array,
    num_beams: int,
    fov_deg: float,
    cell: jax.Array | float,
    max_range: jax.Array | float,
    goal_radius: jax.Array | float,
    method: str = "auto",
    lines: int | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Cast all beams in a (rows, cols) bool wall grid (packs it first; see ``cast_lidar_bits``)."""
    walls = jnp.asarray(walls, bool)
    return cast_lidar_packed(method)(
        pos, theta, goal, pack_rows(walls.T), pack_rows(walls), num_beams, fov_deg, cell,
        max_range, goal_radius, lines,
    )  # fmt: skip
