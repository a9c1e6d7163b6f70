"""Gated Transformer-XL (Parisotto et al. 2020) policy, one step at a time with a memory.

Each layer keeps a memory of its last ``memory_length`` inputs (the hidden states of past steps).
At every step the current hidden state attends over that memory and itself:

    y = MultiHeadAttention(LayerNorm(x), LayerNorm([memory; x]))       (pre-layer-norm)
    x = Gate(x, relu(y))
    y = MLP(LayerNorm(x))
    x = Gate(x, relu(y))

with GRU-type gates in place of residual connections (``Gate`` starts close to the identity:
its update-gate bias is ``gate_bias``). Positions are learned embeddings of a memory slot's age,
added to the keys. A validity mask marks which memory slots hold states of the current episode; it
is cleared at an episode start, so attention never reaches across one.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from quicknav_core.networks.common import ActorCriticHeads, reset_where


class GRUGate(nn.Module):
    """g(x, y) = (1 - z) * x + z * h,  z = σ(W_z y + U_z x - b_g),  h = tanh(W_g y + U_g (r * x))."""

    gate_bias: float = 2.0

    @nn.compact
    def __call__(self, x: jax.Array, y: jax.Array) -> jax.Array:
        size = x.shape[-1]
        dense = lambda name, bias=False: nn.Dense(size, use_bias=bias, name=name)  # noqa: E731
        r = nn.sigmoid(dense("w_r")(y) + dense("u_r")(x))
        z = nn.sigmoid(dense("w_z")(y) + dense("u_z")(x) - self.gate_bias)
        h = jnp.tanh(dense("w_g")(y) + dense("u_g")(r * x))
        return (1.0 - z) * x + z * h


class GTrXLLayer(nn.Module):
    num_heads: int
    head_size: int
    memory_length: int
    gate_bias: float = 2.0

    @nn.compact
    def __call__(self, x: jax.Array, memory: jax.Array, valid: jax.Array) -> jax.Array:
        """x (B, E), memory (B, M, E), valid (B, M) bool -> (B, E)."""
        b, e = x.shape
        h, d = self.num_heads, self.head_size
        context = jnp.concatenate([memory, x[:, None, :]], axis=1)  # (B, M+1, E), oldest first
        x_n = nn.LayerNorm(name="ln_q")(x)
        ctx_n = nn.LayerNorm(name="ln_kv")(context)
        ages = self.param(
            "age_embedding", nn.initializers.normal(0.02), (self.memory_length + 1, e)
        )  # slot i holds the state of age M - i
        q = nn.Dense(h * d, use_bias=False, name="query")(x_n).reshape(b, h, d)
        k = nn.Dense(h * d, use_bias=False, name="key")(ctx_n + ages[None]).reshape(b, -1, h, d)
        v = nn.Dense(h * d, use_bias=False, name="value")(ctx_n).reshape(b, -1, h, d)
        scores = jnp.einsum("bhd,bmhd->bhm", q, k) / jnp.sqrt(jnp.float32(d))
        mask = jnp.concatenate([valid, jnp.ones((b, 1), bool)], axis=1)  # itself always visible
        scores = jnp.where(mask[:, None, :], scores, -1e9)
        attn = jax.nn.softmax(scores, axis=-1)
        y = jnp.einsum("bhm,bmhd->bhd", attn, v).reshape(b, h * d)
        y = nn.Dense(e, name="attn_out")(y)
        x = GRUGate(self.gate_bias, name="gate_attn")(x, nn.relu(y))
        y = nn.Dense(4 * e, name="ff_in")(nn.LayerNorm(name="ln_ff")(x))
        y = nn.Dense(e, name="ff_out")(nn.relu(y))
        return GRUGate(self.gate_bias, name="gate_ff")(x, nn.relu(y))


class GTrXLPolicy(nn.Module):
    """Observation embedding, ``num_layers`` gated transformer layers, dense action and value heads.

    Carry: ``(memory (B, L, M, E), valid (B, M) bool)``.
    """

    action_dim: int = 2
    embed_size: int = 8
    num_heads: int = 2
    head_size: int = 4
    num_layers: int = 2
    memory_length: int = 32
    gate_bias: float = 2.0
    learned_log_std: bool = False
    init_log_std: float = -0.5

    def initial_carry(self, batch_size: int):
        memory = jnp.zeros(
            (batch_size, self.num_layers, self.memory_length, self.embed_size), jnp.float32
        )
        return memory, jnp.zeros((batch_size, self.memory_length), bool)

    @nn.compact
    def __call__(self, carry, obs: jax.Array, start: jax.Array, deterministic: bool = True):
        memory, valid = reset_where(start, self.initial_carry(obs.shape[0]), carry)
        x = nn.Dense(self.embed_size, name="embed")(obs)
        new_memory = []
        for i in range(self.num_layers):
            layer_memory = memory[:, i]
            # this layer's input at this step becomes the newest memory slot for the next step
            new_memory.append(jnp.concatenate([layer_memory[:, 1:], x[:, None, :]], axis=1))
            x = GTrXLLayer(
                self.num_heads,
                self.head_size,
                self.memory_length,
                self.gate_bias,
                name=f"layer_{i}",
            )(x, layer_memory, valid)
        new_valid = jnp.concatenate([valid[:, 1:], jnp.ones_like(valid[:, :1])], axis=1)
        out = ActorCriticHeads(self.action_dim, self.learned_log_std, self.init_log_std)(x)
        return (jnp.stack(new_memory, axis=1), new_valid), out
