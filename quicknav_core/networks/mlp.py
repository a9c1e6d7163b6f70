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
    ``memory_size == 0`` the carry is empty and this is the plain memoryless MLP, unless
    ``frames > 1``: then the MLP reads the current observation and the ``frames - 1`` before it
    (newest first; at an episode's start the current one stands in for those not yet seen),
    ``frame_stride`` steps apart, and its carry is the past observations it will need,
    (B, (frames - 1) * frame_stride, obs_dim). Without a memory head the
    steps of a sequence do not depend on one another's outputs, so a (T, B, obs) sequence runs in
    one call (``parallel_sequence``: training replays use it). Dropout (if
    ``dropout_rate > 0``) is active only when called with ``deterministic=False`` and a ``dropout``
    rng.
    """

    action_dim: int = 2
    hidden_sizes: Sequence[int] = (128, 128)
    memory_size: int = 0
    dropout_rate: float = 0.0
    learned_log_std: bool = False
    init_log_std: float = -0.5
    frames: int = 1
    frame_stride: int = 1  # steps between the frames read
    obs_dim: int = 0  # the carry's width when frames > 1

    @property
    def history(self) -> int:
        """Past observations the carry holds."""
        return (self.frames - 1) * self.frame_stride

    @property
    def parallel_sequence(self) -> bool:
        return self.memory_size == 0

    def initial_carry(self, batch_size: int):
        if self.memory_size:
            return jnp.zeros((batch_size, self.memory_size), jnp.float32)
        if self.frames > 1:
            if self.obs_dim <= 0:
                raise ValueError("an MLP with frames > 1 needs obs_dim (make_network's obs_dim)")
            return jnp.zeros((batch_size, self.history, self.obs_dim), jnp.float32)
        return ()

    def _past_frames(self, carry, obs: jax.Array, start: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One step: (the observations the MLP reads, (B, frames*obs_dim); the next carry)."""
        past = reset_where(start, jnp.broadcast_to(obs[:, None], carry.shape), carry)
        seen = jnp.concatenate([obs[:, None], past], axis=1)  # (B, history + 1, D), newest first
        return seen[:, :: self.frame_stride].reshape(obs.shape[0], -1), seen[:, :-1]

    def _sequence_frames(self, carry, obs: jax.Array, start: jax.Array) -> jax.Array:
        """A (T, B, D) sequence from ``carry``: (T, B, frames*D), as step by step. The
        observation j steps back at t is obs[t] where an episode starts at t, else the one j-1
        steps back at t-1; every ``frame_stride``-th is read."""
        frames, newer = [obs], obs
        at_start = start[..., None]
        for j in range(1, self.history + 1):
            shifted = jnp.concatenate([carry[None, :, j - 1], newer[:-1]], axis=0)
            newer = jnp.where(at_start, obs, shifted)
            if j % self.frame_stride == 0:
                frames.append(newer)
        return jnp.concatenate(frames, axis=-1)

    @nn.compact
    def __call__(self, carry, obs: jax.Array, start: jax.Array, deterministic: bool = True):
        x, new_carry = obs, ()
        if obs.ndim == 3:  # (T, B, obs): the whole sequence at once (memoryless only)
            if self.memory_size:
                raise ValueError("a memory head runs one step at a time, not a (T, B) sequence")
            if self.frames > 1:
                x = self._sequence_frames(carry, obs, start)
            new_carry = carry  # as the other sequence networks: the carry given
        elif self.memory_size:
            memory = reset_where(start, self.initial_carry(obs.shape[0]), carry)
            x = jnp.concatenate([obs, memory], axis=-1)
        elif self.frames > 1:
            x, new_carry = self._past_frames(carry, obs, start)
        for i, size in enumerate(self.hidden_sizes):
            x = nn.relu(
                nn.Dense(size, kernel_init=nn.initializers.orthogonal(2**0.5), name=f"dense_{i}")(x)
            )
            if self.dropout_rate > 0:
                x = nn.Dropout(self.dropout_rate)(x, deterministic=deterministic)
        out: PolicyOutput = ActorCriticHeads(
            self.action_dim, self.learned_log_std, self.init_log_std
        )(x)
        if self.memory_size:
            new_carry = jnp.tanh(nn.Dense(self.memory_size, name="memory")(x))
        return new_carry, out
