"""A classic local planner to compare the learned one with: the dynamic window approach (Fox,
Burgard & Thrun 1997), as ROS 2 Navigation's DWB controller runs it, following the oracle's global
plan (``planning.oracle_plan``) and avoiding what the lidar sees.

Every control step it rolls out a grid of wheel commands held for ``HORIZON_S`` with the robot's
own differential drive, drops those whose footprint comes within ``MIN_CLEARANCE_M`` of a lidar
return, and drives the cheapest of the rest. The critics, as DWB names them: goal distance (how
close the rollout ends to a carrot on the plan), goal alignment (the heading left to it),
obstacle cost (clearance below ``SAFE_CLEARANCE_M``) and oscillation-free forward speed. The robot
has no acceleration limit in QuickNav, so the window is every wheel command. With no admissible
command it turns in place towards the carrot (DWB's recovery: rotate).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.constants import HIT_WALL, beam_offsets
from quicknav_core.env.dynamics import drive, wrap_angle
from quicknav_core.eval.planning import _pursuit_target

WHEEL_LEVELS = 9  # per wheel, in [-1, 1]: 81 commands
HORIZON_S = 1.0  # rollout length
CARROT_NODES = 8  # the carrot: this many planner nodes (0.1 m each by default) down the plan
MIN_CLEARANCE_M = 0.02  # closer than this to a return: inadmissible
SAFE_CLEARANCE_M = 0.25  # the obstacle critic's reach
WEIGHTS = {"goal": 1.0, "align": 0.3, "obstacle": 0.6, "speed": 0.2}


def commands() -> jax.Array:
    """(WHEEL_LEVELS**2, 2) left, right wheel commands in [-1, 1]."""
    levels = np.linspace(-1.0, 1.0, WHEEL_LEVELS, dtype=np.float32)
    left, right = np.meshgrid(levels, levels, indexing="ij")
    return jnp.asarray(np.stack([left.ravel(), right.ravel()], axis=-1))


def dwa_action(plan, pos, theta, goal, ranges, hits, *, beams: int, fov_deg: float, room_size,
               goal_radius, radius, max_wheel_speed, wheel_base, dt, max_range) -> jax.Array:  # fmt: skip
    """The DWA's (left, right) command in [-1, 1] for one robot."""
    (f_safe, u_safe), (f_exact, u_exact) = plan
    t_safe, ok_safe = _pursuit_target(f_safe, u_safe, pos, room_size, CARROT_NODES)
    t_exact, ok_exact = _pursuit_target(f_exact, u_exact, pos, room_size, CARROT_NODES)
    carrot = jnp.where(ok_safe, t_safe, jnp.where(ok_exact, t_exact, goal))
    near_goal = jnp.linalg.norm(goal - pos) < goal_radius + CARROT_NODES * room_size / max(f_safe.shape)
    carrot = jnp.where(near_goal, goal, carrot)

    # the lidar's returns (walls and the obstacles the map does not show) as points
    ca, sa = beam_offsets(beams, fov_deg)
    c, s = jnp.cos(theta), jnp.sin(theta)
    dx, dy = c * ca - s * sa, s * ca + c * sa
    seen = (hits == HIT_WALL) & (ranges < max_range)
    points = pos[None, :] + ranges[:, None] * jnp.stack([dx, dy], axis=-1)  # (B, 2)

    steps = max(1, round(HORIZON_S / float(dt)))  # dt: the config's number (static)
    cmds = commands()

    def rollout(cmd):
        def step(carry, _):
            p, th = carry
            delta, th = drive(th, cmd, max_wheel_speed, wheel_base, dt)
            p = p + delta
            return (p, th), p

        (end, th_end), path = jax.lax.scan(step, (pos, theta), None, steps)
        return end, th_end, path

    ends, th_ends, paths = jax.vmap(rollout)(cmds)  # (K, 2), (K,), (K, T, 2)
    gaps = jnp.linalg.norm(paths[:, :, None, :] - points[None, None, :, :], axis=-1)  # (K, T, B)
    clearance = jnp.min(jnp.where(seen[None, None, :], gaps, jnp.inf), axis=(1, 2)) - radius
    admissible = clearance > MIN_CLEARANCE_M

    to_carrot = carrot - pos
    reach = jnp.linalg.norm(to_carrot) + 1e-6
    goal_cost = jnp.linalg.norm(carrot[None, :] - ends, axis=-1) / reach
    aim = carrot[None, :] - ends
    align_cost = jnp.abs(wrap_angle(jnp.arctan2(aim[:, 1], aim[:, 0]) - th_ends)) / jnp.pi
    obstacle_cost = jnp.clip((SAFE_CLEARANCE_M - clearance) / SAFE_CLEARANCE_M, 0.0, 1.0)
    speed = 0.5 * (cmds[:, 0] + cmds[:, 1])
    cost = (WEIGHTS["goal"] * goal_cost + WEIGHTS["align"] * align_cost
            + WEIGHTS["obstacle"] * obstacle_cost - WEIGHTS["speed"] * speed)  # fmt: skip
    best = jnp.argmin(jnp.where(admissible, cost, jnp.inf))
    # nothing admissible: rotate in place towards the carrot
    err = wrap_angle(jnp.arctan2(to_carrot[1], to_carrot[0]) - theta)
    turn = jnp.where(err >= 0, 1.0, -1.0) * 0.5
    rotate = jnp.stack([-turn, turn])
    return jnp.where(jnp.any(admissible), cmds[best], rotate)
