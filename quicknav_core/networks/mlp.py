"""MLP policy, optionally with the paper's memory head."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from quicknav_core.networks.common import ActorCriticHeads, PolicyOutput, reset_where


class MLPPolicy(nn.Module):
    """ReLU MLP torso shared by actor and critic.

    With ``memory_size > 0`` (the paper's memory MLP) a memory vector ``tanh(Dense(h))`` is produced
    every step and fed back with the next observation; it is zero at an episode start. With
    ``memory_size == 0`` the carry is empty and this is the plain memoryless MLP. Dropout (if
    ``dropout_rate > 0``) is active only when called with ``deterministic=False`` and a ``dropout``
    rng.
    """

    action_dim: int = 2
    hidden_sizes: Sequence[int] = (128, 128)
    memory_size: int = 0
    dropout_rate: float = 0.0
    learned_log_std: bool = False
    init_log_std: float = -0.5

    def initial_carry(self, batch_size: int):
        if self.memory_size == 0:
            return ()
        return jnp.zeros((batch_size, self.memory_size), jnp.float32)

    @nn.compact
    def __call__(self, carry, obs: jax.Array, start: jax.Array, deterministic: bool = True):
        x = obs
        if self.memory_size:
            memory = reset_where(start, self.initial_carry(obs.shape[0]), carry)
            x = jnp.concatenate([obs, memory], axis=-1)
        for i, size in enumerate(self.hidden_sizes):
            x = nn.relu(
                nn.Dense(size, kernel_init=nn.initializers.orthogonal(2**0.5), name=f"dense_{i}")(x)
            )
            if self.dropout_rate > 0:
                x = nn.Dropout(self.dropout_rate)(x, deterministic=deterministic)
        out: PolicyOutput = ActorCriticHeads(
            self.action_dim, self.learned_log_std, self.init_log_std
        )(x)
        new_carry = (
            jnp.tanh(nn.Dense(self.memory_size, name="memory")(x)) if self.memory_size else ()
        )
        return new_carry, out
