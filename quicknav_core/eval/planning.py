"""The oracle controller: it drives the real differential drive along the planner's shortest path
(``env.plan``): pure pursuit of a point a few nodes down the distance field (planned with a small
safety margin), turning in place when the point is far off the heading.
"""

from __future__ import annotations

import jax.numpy as jnp

from quicknav_core.env.dynamics import wrap_angle
from quicknav_core.env.plan import (  # noqa: F401 (the planner's names, as eval used them)
    INF,
    goal_field,
    greedy_path,
    nearest_nodes,
    node_positions,
    shortest_path_length,
)


# --------------------------------------------------------------------------- oracle controller
def oracle_plan(row_bits, goal, room_size, radius, k: int = 5, margin: float = 0.06, reach: int = 0,
                cols: int | None = None):  # fmt: skip
    """What the oracle controller needs for one episode.

    Two distance fields: one planned with a safety ``margin`` added to the radius (the path the
    controller prefers, away from walls) and one with the exact radius (used where the margin
    closes a passage). Returns ((field, usable), (field, usable)). A wide robot (``reach`` >= 1)
    checks one cell further for the margin. ``cols``: the grid's columns (None: a square).
    """
    return (
        goal_field(row_bits, goal, room_size, radius + margin, k, reach + 1 if reach else 0, cols),
        goal_field(row_bits, goal, room_size, radius, k, reach, cols),
    )


def _pursuit_target(field, usable, pos, room_size, lookahead: int):
    h = room_size / max(field.shape)  # room_size: the grid's longer side
    rows, cols = nearest_nodes(pos, field.shape, h)
    centres = (jnp.stack([cols, rows], axis=-1).astype(jnp.float32) + 0.5) * h
    score = jnp.where(
        usable[rows, cols], field[rows, cols] + jnp.linalg.norm(centres - pos, axis=-1), INF
    )
    i = jnp.argmin(score)
    path = greedy_path(field, usable, (rows[i], cols[i]), lookahead)
    target = (path[-1][::-1].astype(jnp.float32) + 0.5) * h
    return target, score[i] < INF


def oracle_action(plan, pos, theta, goal, room_size, goal_radius, lookahead: int = 4):
    """Pure pursuit along the planned distance field: (left, right) wheel command in [-1, 1]."""
    (f_safe, u_safe), (f_exact, u_exact) = plan
    h = room_size / max(f_safe.shape)
    t_safe, ok_safe = _pursuit_target(f_safe, u_safe, pos, room_size, lookahead)
    t_exact, ok_exact = _pursuit_target(f_exact, u_exact, pos, room_size, lookahead)
    target = jnp.where(ok_safe, t_safe, jnp.where(ok_exact, t_exact, goal))
    near_goal = jnp.linalg.norm(goal - pos) < goal_radius + lookahead * h
    target = jnp.where(near_goal, goal, target)
    aim = target - pos
    err = wrap_angle(jnp.arctan2(aim[1], aim[0]) - theta)
    forward = jnp.where(jnp.abs(err) < 0.6, jnp.cos(err) ** 2, 0.0)
    turn = jnp.clip(2.0 * err, -1.0, 1.0)
    left = jnp.clip(forward - 0.5 * turn, -1.0, 1.0)
    right = jnp.clip(forward + 0.5 * turn, -1.0, 1.0)
    return jnp.stack([left, right])
