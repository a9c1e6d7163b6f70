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
) -> dict[str, jax.Array]:
    """Each term of r_t (already signed); their sum is the reward."""
    step_size = params.max_wheel_speed * params.dt
    progress_sign = jnp.sign(dist_prev - dist)
    progress_linear = (dist_prev - dist) / step_size
    # potential-based shaping (Ng, Harada & Russell 1999): F = γ·Φ(s') − Φ(s), Φ = −distance in
    # steps, Φ = 0 once the goal is reached (the episode ends there)
    dist_after = jnp.where(goal_reached, 0.0, dist)
    progress_potential = (dist_prev - params.potential_gamma * dist_after) / step_size
    progress = jnp.select(
        [params.progress_mode == 1, params.progress_mode == 2],
        [progress_linear, progress_potential], progress_sign,
    )  # fmt: skip
    return {
        "step": -jnp.asarray(params.step_penalty, jnp.float32),
        "collision": -collided.astype(jnp.float32) * params.collision_penalty,
        "cycle": -jnp.minimum(cycle_count, params.cycle_cap).astype(jnp.float32)
        * params.cycle_penalty,
        "progress": progress.astype(jnp.float32) * params.progress_reward,
        "goal": goal_reached.astype(jnp.float32) * params.goal_reward,
        "exploration": jnp.asarray(new_cell, jnp.float32) * params.exploration_reward,
    }


def total_reward(terms: dict[str, jax.Array]) -> jax.Array:
    """Sum of the reward terms, float32 ()."""
    total = terms["step"] + terms["collision"] + terms["cycle"] + terms["progress"] + terms["goal"]
    return (total + terms["exploration"]).astype(jnp.float32)
