"""Sensor and actuator randomisation (``EnvConfig.randomize``): what a real robot adds to the model.

At every spawn an env draws one ``Perturbation`` from the ranges in ``EnvParams.randomize``: lidar
noise (additive and proportional), a range bias, beam dropout, a speed scale per wheel, an action
latency and a robot radius. A step then reads the draws from the state:

- ``apply_command``: the wheels turn ``latency_steps`` steps after the command, each at its scale;
- ``perturb_scan``: the scan the robot sees, noisy, biased and with dropped beams.

The per-step noise is a counter hash of the episode's seed and the step (``rng.counter_bits``), so
a scan is a pure function of the state: casting it twice (auto-reset's final observation) gives the
same scan, and the NumPy twin computes the same noise from the same seed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.constants import HIT_NONE, LATENCY_MAX_STEPS
from quicknav_core.env.rng import GOLDEN, counter_bits, fmix32, uniform_from_bits
from quicknav_core.env.types import Perturbation, RandomizeRanges

# Random words a spawn draws for the perturbation: seven uniforms, the latency, the noise seed.
PERTURBATION_WORDS = 9
# Mixed into a step's counter so the noise stream differs from every other use of the seed.
_SCAN_SALT = 0x2545F491


def randomize_numbers(config) -> RandomizeRanges | None:
    """The ``EnvParams.randomize`` of an ``EnvConfig`` (None when it is not randomised)."""
    r = config.randomize
    if r is None:
        return None
    f32 = np.float32
    radius = r.robot_radius_m if r.robot_radius_m is not None else (config.robot_radius,) * 2
    return RandomizeRanges(
        lidar_noise_m=np.asarray(r.lidar_noise_m, f32),
        lidar_noise_frac=np.asarray(r.lidar_noise_frac, f32),
        lidar_bias_m=np.asarray(r.lidar_bias_m, f32),
        beam_dropout=np.asarray(r.beam_dropout, f32),
        wheel_scale=np.asarray([r.wheel_scale_left, r.wheel_scale_right], f32),
        latency_steps=np.asarray(r.latency_steps, np.int32),
        robot_radius=np.asarray(radius, f32),
    )


def draw(ranges: RandomizeRanges, bits: jax.Array) -> Perturbation:
    """One episode's perturbation from ``PERTURBATION_WORDS`` random uint32 words."""
    u = uniform_from_bits(bits[:8])

    def within(pair, x):
        return pair[..., 0] + x * (pair[..., 1] - pair[..., 0])

    lat = ranges.latency_steps
    latency = lat[0] + jnp.floor(u[7] * (lat[1] - lat[0] + 1).astype(jnp.float32)).astype(jnp.int32)
    return Perturbation(
        noise_seed=bits[8],
        lidar_noise_m=within(ranges.lidar_noise_m, u[0]),
        lidar_noise_frac=within(ranges.lidar_noise_frac, u[1]),
        lidar_bias_m=within(ranges.lidar_bias_m, u[2]),
        beam_dropout=within(ranges.beam_dropout, u[3]),
        wheel_scale=within(ranges.wheel_scale, u[4:6]),
        latency_steps=jnp.minimum(latency, lat[1]),
        robot_radius=within(ranges.robot_radius, u[6]),
        past_commands=jnp.zeros((LATENCY_MAX_STEPS, 2), jnp.float32),
    )


def at_rest(robot_radius, **draws) -> Perturbation:
    """A perturbation that changes nothing (``draws`` set some of its values), queue at rest."""
    values = {
        "noise_seed": jnp.uint32(0),
        "lidar_noise_m": 0.0,
        "lidar_noise_frac": 0.0,
        "lidar_bias_m": 0.0,
        "beam_dropout": 0.0,
        "wheel_scale": (1.0, 1.0),
        "latency_steps": 0,
        "robot_radius": robot_radius,
        "past_commands": np.zeros((LATENCY_MAX_STEPS, 2)),
    }
    unknown = set(draws) - set(values)
    if unknown:
        raise ValueError(f"unknown perturbation fields {sorted(unknown)}; known: {sorted(values)}")
    values.update(draws)
    ints = {"noise_seed": jnp.uint32, "latency_steps": jnp.int32}
    return Perturbation(**{
        k: jnp.asarray(v, ints.get(k, jnp.float32)) for k, v in values.items()
    })  # fmt: skip


def apply_command(p: Perturbation, command: jax.Array) -> tuple[jax.Array, Perturbation]:
    """The wheel speeds (in units of max_wheel_speed) that act now, and the updated queue.

    ``past_commands[0]`` is the previous step's command; a latency of k acts on the command of k
    steps ago (at rest before the episode's first command)."""
    queue = p.past_commands
    pick = (jnp.arange(LATENCY_MAX_STEPS, dtype=jnp.int32) == p.latency_steps - 1)[:, None]
    delayed = jnp.sum(jnp.where(pick, queue, 0.0), axis=0)
    acting = jnp.where(p.latency_steps > 0, delayed, command)
    queue = jnp.concatenate([command[None], queue[:-1]], axis=0)
    return acting * p.wheel_scale, p.replace(past_commands=queue)


def scan_uniforms(seed: jax.Array, time: jax.Array, beams: int) -> jax.Array:
    """(3, beams) uniforms in [0, 1) for the scan at step ``time`` of the episode seeded ``seed``."""
    word = fmix32(seed ^ fmix32(time.astype(jnp.uint32) * jnp.uint32(GOLDEN) + jnp.uint32(_SCAN_SALT)))
    return uniform_from_bits(counter_bits(word, jnp.arange(3 * beams, dtype=jnp.uint32))).reshape(3, beams)


def perturb_scan(
    p: Perturbation, time: jax.Array, ranges: jax.Array, hits: jax.Array, max_range
) -> tuple[jax.Array, jax.Array]:
    """The scan the robot reads: noise and bias on each return (at least 0), dropped beams, and no
    return where the noise carries a range past ``max_range``."""
    u = scan_uniforms(p.noise_seed, time, ranges.shape[-1])
    radius = jnp.sqrt(-2.0 * jnp.log(1.0 - u[0]))
    angle = (2.0 * np.pi) * u[1]
    z_frac, z_add = radius * jnp.cos(angle), radius * jnp.sin(angle)
    noisy = ranges * (1.0 + p.lidar_noise_frac * z_frac) + p.lidar_noise_m * z_add + p.lidar_bias_m
    returned = (hits != HIT_NONE) & (u[2] >= p.beam_dropout) & (noisy <= max_range)
    return (
        jnp.where(returned, jnp.maximum(noisy, 0.0), max_range).astype(jnp.float32),
        jnp.where(returned, hits, HIT_NONE).astype(hits.dtype),
    )
