"""The safety layer (``quicknav_core.eval.shield``): its geometry, the robot's NumPy copy held
equal to it, and, in the JAX env with people walking, a plan follower that drives into them
without it and into nothing it sees with it."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import HIT_GOAL, HIT_NONE, HIT_WALL, beam_angles
from quicknav_core.eval.shield import MARGIN_M, SCALES, shield_command, shield_numbers

ENV = EnvConfig(lidar_beams=32, lidar_max_range=4.0)
NUMBERS = shield_numbers(ENV)
ANGLES = beam_angles(ENV.lidar_beams, 360.0).astype(np.float64)


@pytest.fixture(scope="module")
def shield():
    """(N, 2) actions, (N, B) ranges and hits -> (N, 2) commands, compiled once."""
    return jax.jit(jax.vmap(lambda a, r, h: shield_command(a, r, h, **NUMBERS)))


def _wall_ahead(at: float):
    """A scan with a flat wall across the robot's path ``at`` metres ahead, nothing else."""
    cos = np.cos(ANGLES)
    ahead = cos > 1e-3
    ranges = np.where(ahead, at / np.where(ahead, cos, 1.0), ENV.lidar_max_range)
    in_range = ahead & (ranges < ENV.lidar_max_range)
    return (np.where(in_range, ranges, ENV.lidar_max_range).astype(np.float32),
            np.where(in_range, HIT_WALL, HIT_NONE).astype(np.int32))  # fmt: skip


def _next_clearance(command, ranges, hits) -> float:
    v = 0.5 * (command[0] + command[1]) * ENV.max_wheel_speed
    mid = 0.5 * (command[1] - command[0]) * ENV.max_wheel_speed / ENV.wheel_base * ENV.dt
    d = np.array([v * ENV.dt * math.cos(mid), v * ENV.dt * math.sin(mid)])
    seen = (hits == HIT_WALL) & (ranges < ENV.lidar_max_range)
    pts = np.stack([ranges * np.cos(ANGLES), ranges * np.sin(ANGLES)], axis=-1)[seen]
    return float(np.min(np.linalg.norm(pts - d, axis=-1))) if len(pts) else math.inf


def test_shield__slows_a_command_into_a_wall_keeps_its_turn_and_lets_the_rest_through(shield):
    radius, step = ENV.robot_radius, ENV.max_wheel_speed * ENV.dt  # full speed: one step's metres
    near = radius + MARGIN_M + 0.6 * step  # a full step would end inside the margin, half would not
    far = radius + MARGIN_M + 2 * step
    cases = [  # (action, wall ahead at, what comes out)
        ((1.0, 1.0), near, (0.5, 0.5)),        # half speed keeps the margin
        ((1.0, 1.0), radius + MARGIN_M, (0.0, 0.0)),  # at the margin: no step ahead at all
        ((1.0, 1.0), far, (1.0, 1.0)),          # far enough: as commanded
        ((-1.0, -1.0), radius + 0.01, (-1.0, -1.0)),  # backing away from a wall it is touching
        ((0.8, 1.0), radius + MARGIN_M, (-0.1, 0.1)),  # the turn part kept, forward stopped
        ((-0.5, 0.5), radius + 0.01, (-0.5, 0.5)),  # turning in place: always let through
        ((float("nan"), 2.0), far, (0.0, 1.0)),  # sanitised as the env does
    ]
    scans = [_wall_ahead(at) for _, at, _ in cases]
    out = np.asarray(shield(jnp.asarray([c[0] for c in cases], jnp.float32),
                            jnp.asarray(np.stack([s[0] for s in scans])),
                            jnp.asarray(np.stack([s[1] for s in scans]))))  # fmt: skip
    for (action, at, expected), got, (r, h) in zip(cases, out, scans, strict=True):
        np.testing.assert_allclose(got, expected, atol=1e-6, err_msg=f"{action} at {at:.3f} m")
        after = _next_clearance(got, r, h)
        assert after >= radius + MARGIN_M - 1e-5 or after >= _next_clearance((0.0, 0.0), r, h) - 1e-5
    # a goal in the way is not an obstacle: its beams are ignored
    r, h = _wall_ahead(radius + MARGIN_M)
    got = shield(jnp.ones((1, 2)), jnp.asarray(r)[None], jnp.asarray(np.where(h == HIT_WALL, HIT_GOAL, h))[None])
    np.testing.assert_allclose(np.asarray(got)[0], (1.0, 1.0))


def test_shield__the_robots_numpy_copy_lets_through_what_the_evaluation_does(shield):
    """``quicknav_client.shield`` (what ``Navigator(shield=True)`` runs) against the JAX layer on
    2,000 random scans and commands, half of them with returns inside a step of the robot."""
    from quicknav_client.shield import MARGIN_M as CLIENT_MARGIN
    from quicknav_client.shield import SCALES as CLIENT_SCALES
    from quicknav_client.shield import scan_in_robot_frame
    from quicknav_client.shield import shield_command as client_shield

    assert (CLIENT_MARGIN, CLIENT_SCALES) == (MARGIN_M, SCALES)
    rng = np.random.default_rng(0)
    n, b = 2000, ENV.lidar_beams
    actions = rng.uniform(-1.2, 1.2, (n, 2)).astype(np.float32)
    close = rng.uniform(ENV.robot_radius - 0.02, ENV.robot_radius + 0.3, (n, b))
    ranges = np.where(rng.random((n, 1)) < 0.5, close, rng.uniform(0.1, 5.0, (n, b))).astype(np.float32)
    hits = np.where(rng.random((n, b)) < 0.7, HIT_WALL, HIT_NONE).astype(np.int32)
    hits = np.where(ranges >= ENV.lidar_max_range, HIT_NONE, hits)
    ranges = np.minimum(ranges, ENV.lidar_max_range).astype(np.float32)
    jax_out = np.asarray(shield(jnp.asarray(actions), jnp.asarray(ranges), jnp.asarray(hits)))
    changed = 0
    for i in range(n):
        valid = hits[i] == HIT_WALL
        points = scan_in_robot_frame(ranges[i], ANGLES, valid)
        got = client_shield(actions[i], points, radius=ENV.robot_radius, max_wheel_speed=ENV.max_wheel_speed,
                            wheel_base=ENV.wheel_base, dt=ENV.dt)  # fmt: skip
        np.testing.assert_allclose(got, jax_out[i], atol=1e-5, err_msg=f"case {i}")
        changed += not np.allclose(got, np.clip(actions[i], -1, 1))
    assert 200 < changed < n - 200, changed  # both outcomes are well represented


def test_shield__a_blind_plan_follower_stops_walking_into_people_it_sees(optimized):
    """The oracle follows its plan blind to people and walks into them (and, on this small grid,
    clips a wall now and then); through the safety layer the same oracle, in the same 48
    episodes, collides a quarter as often or less and reaches at least as many goals (measured:
    0.25 -> 0.02 collisions per episode, 75 -> 88 % success; the one collision left is a wall
    corner between two of its 32 beams, which it does not see)."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import run_eval

    env = EnvConfig(rooms="floorplan", grid_size=16, room_size=8.0, train_rooms=8, test_rooms=8,
                    lidar_beams=32, lidar_max_range=4.0, max_steps=200, end_on_collision=True,
                    obstacles={"static": 0, "moving": 4})  # fmt: skip
    runs = {}
    for shield in (False, True):
        cfg = EvalConfig(policy="oracle", env=env, episodes=48, gif_episodes=0, pictures=False, shield=shield)
        runs[shield], _ = run_eval(cfg)
    plain, shielded = runs[False]["metrics"], runs[True]["metrics"]
    assert (runs[False]["agent"], runs[True]["agent"]) == ("oracle", "oracle+shield")
    assert plain["collisions_per_episode"] >= 0.1, plain  # the blind oracle does walk into people
    assert shielded["collisions_per_episode"] <= plain["collisions_per_episode"] / 4, (plain, shielded)
    assert shielded["success_rate"] >= plain["success_rate"], (plain, shielded)
