"""Cheap counter-based randomness for resets: hashing a PRNG key's data instead of Threefry.

A reset runs for every env on every step under vmap (gymnax's auto-reset is a select), so its
randomness must cost a few integer operations, and still be a deterministic function of the key
(same key, same reset).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

GOLDEN = 0x9E3779B9  # 2**32 / golden ratio: spreads consecutive counters over the word


def fmix32(x: jax.Array) -> jax.Array:
    """MurmurHash3's 32-bit finaliser: a cheap bijection of uint32 words with full avalanche."""
    x = x ^ jnp.right_shift(x, jnp.uint32(16))
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ jnp.right_shift(x, jnp.uint32(13))
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ jnp.right_shift(x, jnp.uint32(16))


def key_word(key: jax.Array) -> jax.Array:
    """One uint32 word that mixes all of a PRNG key's data (typed or raw): the seed of a stream."""
    data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
    data = data.reshape(-1).astype(jnp.uint32)
    mixed = data[0]
    for word in data[1:]:
        mixed = fmix32(mixed ^ fmix32(word + jnp.uint32(GOLDEN)))
    return mixed


def counter_bits(word: jax.Array, counter: jax.Array) -> jax.Array:
    """Random uint32 words of the stream ``word`` (``key_word``) at positions ``counter``."""
    counter = counter.astype(jnp.uint32)
    return fmix32(word ^ fmix32(counter * jnp.uint32(GOLDEN) + jnp.uint32(0x632BE5AB)))


def hash_key_bits(key: jax.Array, count: int) -> jax.Array:
    """``count`` uint32 words derived from a PRNG key (typed or raw) by hashing it with a counter."""
    return counter_bits(key_word(key), jnp.arange(count, dtype=jnp.uint32))


def uniform_from_bits(bits: jax.Array) -> jax.Array:
    """uint32 random bits -> float32 uniform in [0, 1) (23 mantissa bits)."""
    one_to_two = jax.lax.bitcast_convert_type(
        jnp.right_shift(bits, jnp.uint32(9)) | jnp.uint32(0x3F800000), jnp.float32
    )
    return one_to_two - 1.0


def step_keys(counter: jax.Array, num_envs: int) -> jax.Array:
    """Per-env keys for one batched step: raw uint32 pairs (hash of session word and step, env index).

    ``counter`` is ``(session word, steps since reset)``. The dynamics are deterministic; a key
    only seeds an auto-reset, and the env hashes key data itself, so a Threefry split of
    ``num_envs`` keys every step is not needed.
    """
    word = fmix32(counter[0] ^ fmix32(counter[1] * jnp.uint32(GOLDEN) + jnp.uint32(1)))
    i = jnp.arange(num_envs, dtype=jnp.uint32)
    return jnp.stack([jnp.broadcast_to(word, (num_envs,)), i], axis=-1)
