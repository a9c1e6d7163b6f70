"""The paper's reward, term by term, from the traced reward weights in ``EnvParams``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from quicknav_core.env.types import EnvParams


def reward_terms(
    collided: jax.Array,
    cycle_count: jax.Array,
    dist_prev: jax.Array,
    dist: jax.Array,
    goal_reached: jax.Array,
    params: EnvParams,
    new_cell: jax.Array | bool = False,
    path_prev: jax.Array | None = None,
    path: jax.Array | None = None,
    clearance: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """Each term of r_t (already signed); their sum is the reward. ``path_prev``, ``path``: the
    planned path's length to the goal before and after the step (``observe_plan``), which the
    ``path`` progress pays for (the straight-line distances otherwise). ``clearance``: metres from
    the robot's edge to the nearest wall or obstacle after the step (None: not measured)."""
    step_size = params.max_wheel_speed * params.dt
    progress_sign = jnp.sign(dist_prev - dist)
    progress_linear = (dist_prev - dist) / step_size
    # potential-based shaping (Ng, Harada & Russell 1999): F = γ·Φ(s') − Φ(s), Φ = −distance in
    # steps, Φ = 0 once the goal is reached (the episode ends there)
    dist_after = jnp.where(goal_reached, 0.0, dist)
    progress_potential = (dist_prev - params.potential_gamma * dist_after) / step_size
    # along the plan: a step towards a goal behind a wall is progress only if the path shortens
    progress_path = (
        progress_linear if path is None else (path_prev - jnp.where(goal_reached, 0.0, path)) / step_size
    )
    progress = jnp.select(
        [params.progress_mode == 1, params.progress_mode == 2, params.progress_mode == 3],
        [progress_linear, progress_potential, progress_path], progress_sign,
    )  # fmt: skip
    return {
        "step": -jnp.asarray(params.step_penalty, jnp.float32),
        "collision": -collided.astype(jnp.float32) * params.collision_penalty,
        "cycle": -jnp.minimum(cycle_count, params.cycle_cap).astype(jnp.float32)
        * params.cycle_penalty,
        "progress": progress.astype(jnp.float32) * params.progress_reward,
        "goal": goal_reached.astype(jnp.float32) * params.goal_reward,
        "exploration": jnp.asarray(new_cell, jnp.float32) * params.exploration_reward,
        "proximity": jnp.float32(0.0) if clearance is None else -jnp.clip(
            1.0 - clearance / params.proximity_m, 0.0, 1.0).astype(jnp.float32) * params.proximity_penalty,
    }


def total_reward(terms: dict[str, jax.Array]) -> jax.Array:
    """Sum of the reward terms, float32 ()."""
    total = terms["step"] + terms["collision"] + terms["cycle"] + terms["progress"] + terms["goal"]
    return (total + terms["exploration"] + terms["proximity"]).astype(jnp.float32)
