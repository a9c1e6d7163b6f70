"""Episode statistics kept inside the env state, so any trainer (rejax's or ours) reports them."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment

from quicknav_core.env.quicknav import QuickNavEnv


@struct.dataclass
class EpisodeStats:
    """Per-env running episode counters and totals over episodes finished since the last read."""

    episode_return: jax.Array  # () float32, current episode so far
    episode_length: jax.Array  # () int32
    episode_collisions: jax.Array  # () int32
    finished: jax.Array  # () int32 episodes finished since the last reset of the totals
    return_sum: jax.Array  # () float32 sum of returns of finished episodes
    length_sum: jax.Array  # () float32
    success_sum: jax.Array  # () float32 finished episodes that reached the goal
    collision_sum: jax.Array  # () float32

    @classmethod
    def zeros(cls) -> EpisodeStats:
        f, i = jnp.float32(0.0), jnp.int32(0)
        return cls(f, i, i, i, f, f, f, f)

    def record(self, reward, done, goal_reached, collision) -> EpisodeStats:
        """Add one step's outcome; on ``done`` move the episode into the totals."""
        ret = self.episode_return + reward
        length = self.episode_length + 1
        coll = self.episode_collisions + collision.astype(jnp.int32)
        d = done.astype(jnp.float32)
        return EpisodeStats(
            episode_return=jnp.where(done, 0.0, ret),
            episode_length=jnp.where(done, 0, length),
            episode_collisions=jnp.where(done, 0, coll),
            finished=self.finished + done.astype(jnp.int32),
            return_sum=self.return_sum + d * ret,
            length_sum=self.length_sum + d * length.astype(jnp.float32),
            success_sum=self.success_sum + d * goal_reached.astype(jnp.float32),
            collision_sum=self.collision_sum + d * coll.astype(jnp.float32),
        )

    def clear_totals(self) -> EpisodeStats:
        z = jnp.zeros_like
        return self.replace(
            finished=z(self.finished), return_sum=z(self.return_sum), length_sum=z(self.length_sum),
            success_sum=z(self.success_sum), collision_sum=z(self.collision_sum),
        )  # fmt: skip


def summarize(stats: EpisodeStats) -> dict[str, float]:
    """Episode metrics over all envs (stats batched over envs) since the totals were cleared."""
    n = float(jnp.sum(stats.finished))
    if n == 0:
        nan = float("nan")
        return {"episodes": 0.0, "mean_return": nan, "success_rate": nan, "mean_length": nan,
                "collisions_per_episode": nan}  # fmt: skip
    return {
        "episodes": n,
        "mean_return": float(jnp.sum(stats.return_sum)) / n,
        "success_rate": float(jnp.sum(stats.success_sum)) / n,
        "mean_length": float(jnp.sum(stats.length_sum)) / n,
        "collisions_per_episode": float(jnp.sum(stats.collision_sum)) / n,
    }


@struct.dataclass
class StatsEnvState:
    env_state: Any
    stats: EpisodeStats
    pool_count: Any = 0  # curriculum: episodes of the pool resets draw from (see train.curriculum)


class StatsWrapper(environment.Environment):
    """QuickNav with episode statistics in its state (for trainers that do not report them)."""

    def __init__(self, env: QuickNavEnv):
        super().__init__()
        self.env = env

    def __hash__(self) -> int:
        return hash(("StatsWrapper", self.env))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StatsWrapper) and other.env == self.env

    @property
    def default_params(self):
        return self.env.default_params

    def reset(self, key, params=None):
        obs, state = self.env.reset(key, params)
        count = jnp.int32(0 if params is None else params.pool_count)
        return obs, StatsEnvState(state, EpisodeStats.zeros(), count)

    def reset_env(self, key, params):
        return self.reset(key, params)

    def step(self, key, state: StatsEnvState, action, params=None):
        if params is not None and params.pool_room is not None:
            # the curriculum's level travels in the state, so it changes without a recompile
            params = params.replace(pool_count=state.pool_count)
        obs, env_state, reward, done, info = self.env.step(key, state.env_state, action, params)
        stats = state.stats.record(reward, done, info["goal_reached"], info["collision"])
        return obs, StatsEnvState(env_state, stats, state.pool_count), reward, done, info

    def observation_space(self, params=None):
        return self.env.observation_space(params)

    def action_space(self, params=None):
        return self.env.action_space(params)

    @property
    def num_actions(self) -> int:
        return self.env.num_actions

    @property
    def name(self) -> str:
        return "QuickNavStats"
