"""Stacked LSTM policy (Flax's OptimizedLSTMCell)."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from quicknav_core.networks.common import ActorCriticHeads, reset_where


class LSTMPolicy(nn.Module):
    """``num_layers`` LSTM layers of ``hidden_size``, then dense action and value heads.

    The carry is a tuple of ``(c, h)`` per layer, zero at an episode start.
    """

    action_dim: int = 2
    num_layers: int = 2
    hidden_size: int = 15
    learned_log_std: bool = False
    init_log_std: float = -0.5

    def initial_carry(self, batch_size: int):
        zeros = jnp.zeros((batch_size, self.hidden_size), jnp.float32)
        return tuple((zeros, zeros) for _ in range(self.num_layers))

    @nn.compact
    def __call__(self, carry, obs: jax.Array, start: jax.Array, deterministic: bool = True):
        carry = reset_where(start, self.initial_carry(obs.shape[0]), carry)
        x = obs
        new_carry = []
        for i in range(self.num_layers):
            layer_carry, x = nn.OptimizedLSTMCell(self.hidden_size, name=f"lstm_{i}")(carry[i], x)
            new_carry.append(layer_carry)
        out = ActorCriticHeads(self.action_dim, self.learned_log_std, self.init_log_std)(x)
        return tuple(new_carry), out
