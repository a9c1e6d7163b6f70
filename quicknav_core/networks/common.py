"""Pieces shared by the networks: outputs, heads, carry resets, Gaussian helpers."""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class PolicyOutput:
    """What every network returns besides its carry."""

    mean: jax.Array  # (B, action_dim) pre-clip action mean
    log_std: jax.Array  # (B, action_dim)
    value: jax.Array  # (B,)


def reset_where(start: jax.Array, fresh, carry):
    """Carry with every leaf replaced by ``fresh`` where ``start`` (B,) is true."""

    def pick(f, c):
        mask = start.reshape(start.shape + (1,) * (c.ndim - start.ndim))
        if c.dtype == jnp.bool_:  # as logic: a select of booleans has no ONNX Runtime kernel
            return (mask & f) | (~mask & c)
        return jnp.where(mask, f, c)

    return jax.tree.map(pick, fresh, carry)


class ActorCriticHeads(nn.Module):
    """Gaussian action head (state-independent or learned log std) and value head."""

    action_dim: int
    learned_log_std: bool = False
    init_log_std: float = -0.5

    @nn.compact
    def __call__(self, features: jax.Array) -> PolicyOutput:
        small = nn.initializers.orthogonal(0.01)
        mean = nn.Dense(self.action_dim, kernel_init=small, name="mean")(features)
        if self.learned_log_std:
            log_std = nn.Dense(
                self.action_dim, kernel_init=small,
                bias_init=nn.initializers.constant(self.init_log_std), name="log_std",
            )(features)  # fmt: skip
        else:
            log_std = self.param(
                "log_std", nn.initializers.constant(self.init_log_std), (self.action_dim,)
            )
            log_std = jnp.broadcast_to(log_std, mean.shape)
        log_std = jnp.clip(log_std, -5.0, 2.0)
        value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0), name="value")(features)
        return PolicyOutput(mean=mean, log_std=log_std, value=value[..., 0])


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, x: jax.Array) -> jax.Array:
    """Log density of a diagonal Gaussian, summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z * z - log_std - 0.5 * math.log(2.0 * math.pi), axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """Entropy of a diagonal Gaussian, summed over the last axis."""
    return jnp.sum(log_std + 0.5 * (1.0 + math.log(2.0 * math.pi)), axis=-1)
