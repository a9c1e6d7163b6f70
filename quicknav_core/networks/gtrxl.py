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
    def __call__(
        self, x: jax.Array, memory: jax.Array, valid: jax.Array, visible: jax.Array | None = None
    ) -> jax.Array:
        """One step: x (B, E), memory (B, M, E), valid (B, M) bool -> (B, E).

        A whole sequence at once (``visible`` given): x (T, B, E) this layer's inputs at every
        step, memory (B, M, E) and its slots as they were before the first step, visible
        (B, T, M + T) bool: which of [memory; x] step t may attend to -> (T, B, E). The same
        numbers as T single steps, computed as one banded attention instead of a loop."""
        e = x.shape[-1]
        h, d, m = self.num_heads, self.head_size, self.memory_length
        ln_q, ln_kv = nn.LayerNorm(name="ln_q"), nn.LayerNorm(name="ln_kv")
        ages = self.param(
            "age_embedding", nn.initializers.normal(0.02), (m + 1, e)
        )  # slot i holds the state of age M - i
        query = nn.Dense(h * d, use_bias=False, name="query")
        key = nn.Dense(h * d, use_bias=False, name="key")
        value = nn.Dense(h * d, use_bias=False, name="value")
        scale = jnp.sqrt(jnp.float32(d))
        if visible is None:
            b = x.shape[0]
            context = jnp.concatenate([memory, x[:, None, :]], axis=1)  # (B, M+1, E), oldest first
            ctx_n = ln_kv(context)
            q = query(ln_q(x)).reshape(b, h, d)
            k = key(ctx_n + ages[None]).reshape(b, -1, h, d)
            v = value(ctx_n).reshape(b, -1, h, d)
            scores = jnp.einsum("bhd,bmhd->bhm", q, k) / scale
            mask = jnp.concatenate([valid, jnp.ones((b, 1), bool)], axis=1)  # itself always visible
            scores = jnp.where(mask[:, None, :], scores, -1e9)
            attn = jax.nn.softmax(scores, axis=-1)
            y = jnp.einsum("bhm,bmhd->bhd", attn, v).reshape(b, h * d)
        else:
            t_len, b = x.shape[:2]
            context = jnp.concatenate([jnp.swapaxes(memory, 0, 1), x], axis=0)  # (M+T, B, E)
            ctx_n = ln_kv(context)
            q = query(ln_q(x)).reshape(t_len, b, h, d)
            k = key(ctx_n).reshape(m + t_len, b, h, d)
            v = value(ctx_n).reshape(m + t_len, b, h, d)
            # the key is linear without bias: W(ctx + age) = W ctx + W age, so the age part of a
            # score is q . W age[slot], with slot = position - step (the step itself is slot M)
            k_age = key(ages).reshape(m + 1, h, d)
            content = jnp.einsum("tbhd,pbhd->bhtp", q, k)
            by_slot = jnp.einsum("tbhd,shd->bhts", q, k_age)
            slot = jnp.clip(jnp.arange(m + t_len)[None, :] - jnp.arange(t_len)[:, None], 0, m)
            age_part = jnp.take_along_axis(by_slot, jnp.broadcast_to(slot, (b, h, t_len, m + t_len)), axis=-1)
            scores = (content + age_part) / scale
            scores = jnp.where(visible[:, None], scores, -1e9)
            attn = jax.nn.softmax(scores, axis=-1)
            y = jnp.einsum("bhtp,pbhd->tbhd", attn, v).reshape(t_len, b, h * d)
        y = nn.Dense(e, name="attn_out")(y)
        x = GRUGate(self.gate_bias, name="gate_attn")(x, nn.relu(y))
        y = nn.Dense(4 * e, name="ff_in")(nn.LayerNorm(name="ln_ff")(x))
        y = nn.Dense(e, name="ff_out")(nn.relu(y))
        return GRUGate(self.gate_bias, name="gate_ff")(x, nn.relu(y))


def sequence_visibility(valid: jax.Array, start: jax.Array, memory_length: int) -> jax.Array:
    """(B, T, M+T) bool: which of [memory slots; steps 0..T-1] step t attends to, as the
    step-by-step network would: the M steps before it and itself, never across an episode start
    (``start`` (T, B)), memory slots only while no start happened and where ``valid`` (B, M)."""
    t_len, b = start.shape
    m = memory_length
    steps = jnp.arange(t_len)
    # the step the current episode began at, or -M-1 when it began before the sequence (then the
    # memory slots' own validity decides)
    began = jax.lax.cummax(jnp.where(start, steps[:, None], -m - 1), axis=0)  # (T, B)
    pos = jnp.arange(m + t_len)  # context position p holds time p - M
    rel = pos[None, :] - steps[:, None]  # slot index, (T, M+T)
    band = (rel >= 0) & (rel <= m)
    time = pos - m
    in_episode = time[None, None, :] >= jnp.swapaxes(began, 0, 1)[:, :, None]  # (B, T, M+T)
    from_memory = jnp.concatenate([valid, jnp.ones((b, t_len), bool)], axis=1)  # (B, M+T)
    return band[None] & in_episode & from_memory[:, None, :]


class GTrXLPolicy(nn.Module):
    """Observation embedding, ``num_layers`` gated transformer layers, dense action and value heads.

    Carry: ``(memory (B, L, M, E), valid (B, M) bool)``. Called with (B, ...) observations it
    takes one step; with (T, B, ...) observations and starts it runs the whole sequence from the
    carry at once (``parallel_sequence``: training replays use this) and returns the carry given.
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

    parallel_sequence = True  # (T, B, ...) inputs run as one banded attention per layer

    def initial_carry(self, batch_size: int):
        memory = jnp.zeros(
            (batch_size, self.num_layers, self.memory_length, self.embed_size), jnp.float32
        )
        return memory, jnp.zeros((batch_size, self.memory_length), bool)

    @nn.compact
    def __call__(self, carry, obs: jax.Array, start: jax.Array, deterministic: bool = True):
        layers = [
            GTrXLLayer(self.num_heads, self.head_size, self.memory_length, self.gate_bias, name=f"layer_{i}")
            for i in range(self.num_layers)
        ]  # fmt: skip
        embed = nn.Dense(self.embed_size, name="embed")
        heads = ActorCriticHeads(self.action_dim, self.learned_log_std, self.init_log_std)
        if obs.ndim == 3:  # (T, B, obs): the whole sequence
            memory, valid = carry
            visible = sequence_visibility(valid, start, self.memory_length)
            x = embed(obs)
            for i, layer in enumerate(layers):
                x = layer(x, memory[:, i], valid, visible)
            return carry, heads(x)
        memory, valid = reset_where(start, self.initial_carry(obs.shape[0]), carry)
        x = embed(obs)
        new_memory = []
        for i, layer in enumerate(layers):
            layer_memory = memory[:, i]
            # this layer's input at this step becomes the newest memory slot for the next step
            new_memory.append(jnp.concatenate([layer_memory[:, 1:], x[:, None, :]], axis=1))
            x = layer(x, layer_memory, valid)
        new_valid = jnp.concatenate([valid[:, 1:], jnp.ones_like(valid[:, :1])], axis=1)
        return (jnp.stack(new_memory, axis=1), new_valid), heads(x)
