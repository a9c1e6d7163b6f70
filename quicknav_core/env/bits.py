"""Bit-packed boolean grids: a (g, g) grid as (g, W) uint32 words, W = ceil(g / 32).

Row-major packing: bit ``c % 32`` of word ``c // 32`` of row ``r`` is ``grid[r, c]``. The lidar and
the collision check read walls from these words with shifts instead of gathers, and the state
carries 4x less data than a bool grid (8x less than one byte per cell would suggest, per word).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def num_words(grid_size: int) -> int:
    """Words per packed row."""
    return -(-grid_size // 32)


def pack_rows(grid: jax.Array) -> jax.Array:
    """(..., g, g) bool -> (..., g, W) uint32, packing along the last axis."""
    g = grid.shape[-1]
    words = num_words(g)
    pad = words * 32 - g
    x = jnp.asarray(grid).astype(jnp.uint32)
    if pad:
        x = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)])
    x = x.reshape(*x.shape[:-1], words, 32)
    shifts = jnp.arange(32, dtype=jnp.uint32)
    # distinct bits, so the sum is a bitwise OR
    return jnp.sum(jnp.left_shift(x, shifts), axis=-1, dtype=jnp.uint32)


def pack_rows_np(grid: np.ndarray) -> np.ndarray:
    """NumPy twin of ``pack_rows`` (used when building banks)."""
    g = grid.shape[-1]
    words = num_words(g)
    pad = words * 32 - g
    x = np.asarray(grid).astype(np.uint64)
    if pad:
        x = np.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, pad)])
    x = x.reshape(*x.shape[:-1], words, 32)
    return (x << np.arange(32, dtype=np.uint64)).sum(axis=-1).astype(np.uint32)


def unpack_rows(bits: jax.Array, grid_size: int) -> jax.Array:
    """(..., g, W) uint32 -> (..., g, g) bool."""
    c = jnp.arange(grid_size, dtype=jnp.int32)
    words = jnp.take(bits, c // 32, axis=-1)  # (..., g, g)
    return (jnp.right_shift(words, (c % 32).astype(jnp.uint32)) & jnp.uint32(1)).astype(bool)


def read_bit(words: jax.Array, index: jax.Array) -> jax.Array:
    """Bit ``index`` of packed words: words (..., W) uint32, index (...) int32 -> bool (...).

    An index outside [0, 32*W) reads as False (a right shift by 32 or more gives 0 here).
    """
    n = words.shape[-1]
    if n == 1:
        word = words[..., 0]
    else:
        sel = (index // 32)[..., None] == jnp.arange(n, dtype=jnp.int32)
        word = jnp.sum(jnp.where(sel, words, jnp.uint32(0)), axis=-1, dtype=jnp.uint32)
    return (jnp.right_shift(word, (index % 32).astype(jnp.uint32)) & jnp.uint32(1)).astype(bool)


def set_bit(bits: jax.Array, row: jax.Array, col: jax.Array) -> jax.Array:
    """(g, W) packed grid with bit (row, col) set.

    Up to 32 cells a side (one word per row) as a masked OR over the whole grid (vmaps without
    scatters, and the grid is a few words); larger grids rewrite only the row (one gather and one
    scatter per env: a masked OR over a 128-cell grid cost more than the rest of the step)."""
    g, n = bits.shape
    mask = jnp.left_shift(jnp.uint32(1), (col % 32).astype(jnp.uint32))
    if n > 1:
        words = bits[row]
        return bits.at[row].set(jnp.where(jnp.arange(n) == col // 32, words | mask, words))
    hit = (jnp.arange(g)[:, None] == row) & (jnp.arange(n)[None, :] == col // 32)
    return jnp.where(hit, bits | mask, bits)


class BankRows:
    """One room's packed rows read in place from a bank: ``rows[r]`` is ``bank[room, r]`` (W,),
    ``rows.shape`` the room's (rows, W). For the readers of a few rows near the robot (the
    collision test, the proximity term, the obstacles' walk) on grids above 32 cells: an env
    state's own copy of its room is then read by nothing in a step, so the step does not hold it
    twice (XLA copies a buffer that a loop both reads and rewrites in place)."""

    def __init__(self, bank: jax.Array, room: jax.Array):
        self.bank, self.room = bank, room

    @property
    def shape(self) -> tuple[int, int]:
        return self.bank.shape[1], self.bank.shape[2]

    def __getitem__(self, row: jax.Array) -> jax.Array:
        return self.bank[self.room, row]
