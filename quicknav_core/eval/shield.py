"""A safety layer between any policy and the wheels, as ROS 2 Navigation's collision monitor sits
between its controller and the motors: it reads the current scan and slows a command that would
bring the robot's disc within ``MARGIN_M`` of a return.

The command's forward part is scaled by the first of ``SCALES`` whose next pose (one control
period of the robot's own differential drive) keeps the disc ``radius + MARGIN_M`` from every
wall return, or at least no closer than it is now; its turning part is kept. At scale 0 the
robot turns in place, which a disc can always do, so the layer never leaves the robot without a
command. People in QuickNav turn back where they would step into the robot, and the scan shows
them where the robot's next move is checked against them, so a shielded robot does not walk into
one it sees. It does not see a wall corner between two beams, nor what the simulator's goal disc
hides behind it (beams that hit the goal are not obstacles). Wheel-speed errors and latency
(``env.perturbation``) are not modelled: the layer assumes the wheels do what they are told. A
policy that keeps pushing into a wall it sees stays there, turning in place: a time-out instead
of a collision.

``shield_command`` is the JAX version (evaluations with ``shield=True``); ``quicknav_client.
shield`` is the NumPy one a robot runs (``Navigator(shield=True)``), held equal to it by
``tests/core/eval/test_shield.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from quicknav_core.env.constants import HIT_WALL, beam_offsets
from quicknav_core.env.dynamics import drive, wheel_command
from quicknav_core.eval.agents import Agent

SCALES = (1.0, 0.5, 0.25, 0.0)  # of the command's forward part, tried in order
MARGIN_M = 0.01  # kept between the robot's edge and a return (float rounding, beams ~6 degrees apart)


def shield_command(action, ranges, hits, *, beams: int, fov_deg: float, radius, max_wheel_speed,
                   wheel_base, dt, max_range) -> jax.Array:  # fmt: skip
    """The (left, right) command in [-1, 1] the layer lets through for one robot, from the
    policy's ``action`` and the scan (``ranges`` in metres, ``hits`` the lidar's hit types, in the
    robot's frame: beam i at ``constants.beam_angles``)."""
    command = wheel_command(action)
    ca, sa = beam_offsets(beams, fov_deg)
    seen = (hits == HIT_WALL) & (ranges < max_range)
    points = jnp.stack([ranges * ca, ranges * sa], axis=-1)  # (B, 2), robot frame
    now = jnp.min(jnp.where(seen, jnp.linalg.norm(points, axis=-1), jnp.inf))
    forward, turn = 0.5 * (command[0] + command[1]), 0.5 * (command[1] - command[0])
    candidates = jnp.stack([jnp.stack([s * forward - turn, s * forward + turn]) for s in SCALES])

    def clearance(cmd):
        delta, _ = drive(jnp.float32(0.0), cmd, max_wheel_speed, wheel_base, dt)
        gaps = jnp.linalg.norm(points - delta[None, :], axis=-1)
        return jnp.min(jnp.where(seen, gaps, jnp.inf))

    after = jax.vmap(clearance)(candidates)
    ok = (after >= radius + MARGIN_M) | (after >= now)
    ok = ok.at[-1].set(True)  # turning in place does not move the disc
    return candidates[jnp.argmax(ok)]


def shield_numbers(env_config) -> dict:
    """The static numbers ``shield_command`` takes from an ``EnvConfig``."""
    c = env_config
    return dict(beams=c.lidar_beams, fov_deg=c.lidar_fov_deg, radius=c.robot_radius,
                max_wheel_speed=c.max_wheel_speed, wheel_base=c.wheel_base, dt=c.dt,
                max_range=c.lidar_max_range)  # fmt: skip


class ShieldedAgent(Agent):
    """``inner``'s commands through the safety layer (``shield_command``), with the env's robot and
    lidar; everything else is ``inner``'s."""

    def __init__(self, inner: Agent, env_config):
        self.inner = inner
        self.name = f"{inner.name}+shield"
        self.numbers = shield_numbers(env_config)

    @property
    def payload(self):
        return self.inner.payload

    def static_key(self):
        return ("shield", MARGIN_M, SCALES, tuple(sorted(self.numbers.items())), self.inner.static_key())

    def init(self, env, params, states, payload):
        return self.inner.init(env, params, states, payload)

    def act(self, agent_state, obs, states, start, key, deterministic, payload):
        agent_state, action = self.inner.act(agent_state, obs, states, start, key, deterministic, payload)
        let = jax.vmap(lambda a, r, h: shield_command(a, r, h, **self.numbers))
        return agent_state, let(action, states.lidar_ranges, states.lidar_hits)
