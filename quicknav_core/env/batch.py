"""A batch of QuickNav envs held on the device and stepped from the host, one call per step.

For serving environments to remote agents: the whole batch steps in one jit-compiled call with
auto-reset, compiled once per (env config, batch size) in the runtime it is given and shared by
every holder of that shape there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.rng import step_keys
from quicknav_core.runtime import Runtime, runtime_or_new

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig, Split

__all__ = ["BatchedEnv", "StepResult", "batched_step", "env_and_params", "step_keys"]


@dataclass
class StepResult:
    """One batched step, as numpy arrays (``final_obs`` only for the envs that just ended)."""

    obs: np.ndarray  # (n, obs_dim) float32, already reset where done
    reward: np.ndarray  # (n,) float32
    terminated: np.ndarray  # (n,) bool
    truncated: np.ndarray  # (n,) bool
    collision: np.ndarray  # (n,) bool
    done_indices: np.ndarray  # (k,) int32
    final_obs: np.ndarray  # (k, obs_dim) float32


def batched_step(env, keys, state, action, params, reset_capacity: int | None = None):
    """``vmap(env.step)`` with auto-reset and final observations, casting the lidar ~once per env.

    ``env.step`` under vmap casts the lidar twice for every env (the pre-reset pose for the final
    observation, the kept pose for the next one), and with ``observe_plan`` plans for every env,
    because a per-env branch becomes a select. At the batch level only the envs that just ended
    need a fresh episode: their fresh states are gathered ``reset_capacity`` at a time, planned
    and cast, and scattered back, until none is left (a step in which many end, a synchronised
    truncation, takes a few rounds). The result equals ``vmap(env.step)`` exactly.
    Returns (obs, state, reward, info, final_obs).
    """
    n = action.shape[0]
    k = min(n, reset_capacity if reset_capacity is not None else max(8, n // 32))
    moved, reward, info = jax.vmap(env.transition, in_axes=(0, 0, 0, None))(
        keys, state, action, params
    )
    done = info["terminated"] | info["truncated"]
    moved = jax.vmap(env.with_lidar, in_axes=(0, None))(moved, params)
    final = jax.vmap(env.get_obs, in_axes=(0, None))(moved, params)

    def start(key):  # a fresh episode: room, poses, plan and first scan
        return env.with_lidar(env.with_plan(env.spawn(key, params), params), params)

    def round_(carry):
        kept, todo = carry
        idx = jnp.nonzero(todo, size=k, fill_value=-1)[0]
        idx = jnp.where(idx < 0, idx[0], idx)  # padding repeats a pending env: written twice, same
        part = jax.vmap(start)(keys[idx])
        kept = jax.tree.map(lambda full, p: full.at[idx].set(p), kept, part)
        return kept, todo.at[idx].set(False)

    # only the ended envs' rooms are gathered and written (a grid per env: at grid 128 a select
    # over every env's walls cost more than the step itself)
    kept, _ = jax.lax.while_loop(lambda c: jnp.any(c[1]), round_, (moved, done))
    obs = jax.vmap(env.get_obs, in_axes=(0, None))(kept, params)
    return obs, kept, reward, info, final


def _compiled(env, num_envs: int, sharding, runtime: Runtime):
    """(reset, step) for this env, batch size and device layout, jit-compiled once per runtime."""

    def reset(rng, params):
        keys = jax.random.split(rng, num_envs)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
        if sharding is not None:
            state = jax.lax.with_sharding_constraint(state, sharding)
        return state, obs

    def step(counter, state, action, params):
        keys = step_keys(counter, num_envs)
        obs, state, reward, info, final = batched_step(env, keys, state, action, params)
        counter = counter.at[1].add(jnp.uint32(1))
        return (counter, state, obs, reward, info["terminated"], info["truncated"],
                info["collision"], final)  # fmt: skip

    return runtime.program(("batched-env", env, num_envs, sharding),
                           lambda: (jax.jit(reset), jax.jit(step, donate_argnums=(0, 1))))  # fmt: skip


def env_and_params(config: EnvConfig, split: Split, runtime: Runtime | None = None):
    """The env and its params for a config and split, built once per runtime (streams that start
    the same config at once wait for one build instead of each carving)."""
    runtime = runtime_or_new(runtime)
    # final observations are part of the protocol, whatever the config says
    config = config.model_copy(update={"final_obs": True})
    key = ("env-and-params", config.model_dump_json(), split)  # a config with maps holds lists
    return runtime.program(key, lambda: config.build(split, runtime))


@jax.jit
def _take_rows(x: jax.Array, idx: jax.Array) -> jax.Array:
    return jnp.take(x, idx, axis=0)


def gather_rows(x: jax.Array, idx: np.ndarray, width: int) -> np.ndarray:
    """``x[idx]`` as numpy, gathered on x's device so only those rows are copied to the host.

    The index is padded to a power of two (at least 8) so a handful of compiled gathers serve
    every count of finished episodes."""
    n = int(idx.size)
    if n == 0:
        return np.zeros((0, width), np.float32)
    size = max(8, 1 << (n - 1).bit_length())
    padded = np.zeros(size, np.int32)
    padded[:n] = idx
    return np.asarray(_take_rows(x, padded))[:n]


class BatchedEnv:
    """``num_envs`` auto-resetting envs on the device; ``step`` takes and returns numpy."""

    def __init__(self, config: EnvConfig, num_envs: int, seed: int = 0, split: Split = "train",
                 runtime: Runtime | None = None):  # fmt: skip
        runtime = runtime_or_new(runtime)
        self.config = config
        self.num_envs = int(num_envs)
        self.env, self.params = env_and_params(config, split, runtime)
        # Large batches are split over the local devices (several CPU devices when XLA is told
        # to expose one per core, several GPUs); small ones stay on one device.
        ndev = jax.local_device_count()
        self._sharding = None
        if ndev > 1 and self.num_envs % ndev == 0 and self.num_envs >= 256 * ndev:
            mesh = jax.sharding.Mesh(np.asarray(jax.local_devices()), ("envs",))
            self._sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("envs"))
        self._reset, self._step = _compiled(self.env, self.num_envs, self._sharding, runtime)
        self._rng = jax.random.PRNGKey(seed)
        self._counter = None
        self.state = None
        self.obs_dim = config.obs_dim

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start a fresh episode in every env; returns the first observations."""
        if seed is not None:
            self._rng = jax.random.PRNGKey(seed)
        self._rng, sub, word = jax.random.split(self._rng, 3)
        # the step counter: (a word drawn from the session's key stream, steps since reset)
        self._counter = jnp.stack([jax.random.bits(word, (), jnp.uint32), jnp.uint32(0)])
        self.state, obs = self._reset(sub, self.params)
        return np.asarray(obs)

    def step(self, actions: np.ndarray) -> StepResult:
        """One step of every env with (num_envs, 2) float32 actions."""
        actions = np.asarray(actions, np.float32)
        if self._sharding is not None:
            actions = jax.device_put(actions, self._sharding)
        out = self._step(self._counter, self.state, actions, self.params)
        self._counter, self.state, obs, reward, term, trunc, coll, final = out
        term, trunc = np.asarray(term), np.asarray(trunc)
        done_idx = np.flatnonzero(term | trunc).astype(np.int32)
        # only the rows of envs whose episode ended cross to the host, gathered on the device
        final_obs = gather_rows(final, done_idx, self.obs_dim)
        return StepResult(np.asarray(obs), np.asarray(reward), term, trunc, np.asarray(coll),
                          done_idx, final_obs)  # fmt: skip
