import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.bits import pack_rows
from quicknav_core.env.dynamics import disc_overlaps_wall, move_with_sliding, wheel_command
from tests.core.env.reference import disc_wall_clearance


def _open_room(g=8):
    walls = np.ones((g, g), bool)
    walls[1:-1, 1:-1] = False
    return walls


def test_disc__never_overlaps_a_wall_in_long_random_rollouts(default_env, default_config):
    env, params = default_env
    n_envs, n_steps = 64, 400
    keys = jax.random.split(jax.random.PRNGKey(3), n_envs)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

    def body(carry, key):
        state = carry
        k_act, k_step = jax.random.split(key)
        # biased forward so the robots run into walls and slide along them
        act = jax.random.uniform(k_act, (n_envs, 2), minval=-0.3, maxval=1.0)
        _, state, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(k_step, n_envs), state, act, params
        )
        return state, (state.pos, state.walls, info["collision"])

    _, (pos, walls, coll) = jax.jit(
        lambda s: jax.lax.scan(body, s, jax.random.split(jax.random.PRNGKey(4), n_steps))
    )(state)
    pos, walls, coll = np.asarray(pos), np.asarray(walls), np.asarray(coll)
    assert coll.mean() > 0.01, "the rollouts should hit walls often enough to test sliding"
    r = default_config.robot_radius
    cell = default_config.cell_size
    worst = min(
        disc_wall_clearance(pos[t, i], walls[t, i], cell)
        for t in range(0, n_steps, 3)
        for i in range(n_envs)
    )
    assert worst >= r - 1e-6, worst


def test_sliding__keeps_the_feasible_axis():
    bits = pack_rows(_open_room())
    r, cell = 0.3, 1.0
    # against the bottom wall (y = 1): moving down-right slides along x
    pos = jnp.array([3.5, 1.31])
    new, hit = move_with_sliding(pos, jnp.array([0.2, -0.1]), bits, cell, r)
    assert bool(hit)
    np.testing.assert_allclose(np.asarray(new), [3.7, 1.31], atol=1e-6)
    # against the left wall (x = 1): moving up-left slides along y
    pos = jnp.array([1.31, 3.5])
    new, hit = move_with_sliding(pos, jnp.array([-0.1, 0.2]), bits, cell, r)
    assert bool(hit)
    np.testing.assert_allclose(np.asarray(new), [1.31, 3.7], atol=1e-6)
    # into a corner: both axes blocked, the robot stays
    pos = jnp.array([1.31, 1.31])
    new, hit = move_with_sliding(pos, jnp.array([-0.1, -0.1]), bits, cell, r)
    assert bool(hit)
    np.testing.assert_allclose(np.asarray(new), [1.31, 1.31])
    # a free move is no collision
    new, hit = move_with_sliding(jnp.array([3.5, 3.5]), jnp.array([0.1, 0.1]), bits, cell, r)
    assert not bool(hit)
    np.testing.assert_allclose(np.asarray(new), [3.6, 3.6], atol=1e-6)


def test_overlap__touching_is_allowed_and_corners_count():
    walls = _open_room()
    assert not bool(disc_overlaps_wall(jnp.array([1.5, 1.5]), walls, 1.0, 0.5))
    assert bool(disc_overlaps_wall(jnp.array([1.49, 3.5]), walls, 1.0, 0.5))
    # an inner wall block at cell (row 4, col 4): the disc near its corner overlaps it diagonally
    walls[4, 4] = True
    assert bool(disc_overlaps_wall(jnp.array([3.8, 3.8]), walls, 1.0, 0.3))
    assert not bool(disc_overlaps_wall(jnp.array([3.7, 3.7]), walls, 1.0, 0.3))


@pytest.mark.parametrize(
    ("action", "expected"),
    [([np.nan, 0.5], [0.0, 0.5]), ([2.0, -3.0], [1.0, -1.0]), ([np.nan, np.nan], [0.0, 0.0])],
)
def test_wheel_command__nan_is_zero_and_clipped(action, expected):
    np.testing.assert_allclose(np.asarray(wheel_command(jnp.array(action, jnp.float32))), expected)


def test_drive__straight_and_turn_in_place():
    cfg = EnvConfig(grid_size=8, train_rooms=4, test_rooms=4)
    env, params = cfg.build()
    walls = _open_room()
    _, s = env.load_state(walls, [4.5, 4.5], 0.0, [1.5, 1.5], params)
    _, s2, _, _, _ = env.step_env(jax.random.PRNGKey(0), s, jnp.array([1.0, 1.0]), params)
    np.testing.assert_allclose(np.asarray(s2.pos), [4.6, 4.5], atol=1e-6)  # 1 m/s for 0.1 s
    _, s3, _, _, info = env.step_env(jax.random.PRNGKey(0), s, jnp.array([-1.0, 1.0]), params)
    np.testing.assert_allclose(np.asarray(s3.pos), [4.5, 4.5], atol=1e-6)
    # omega = 2 / 0.3 rad/s for 0.1 s
    np.testing.assert_allclose(float(s3.theta), 2.0 / 0.3 * 0.1, atol=1e-5)
    assert not bool(info["collision"])
    # NaN action: no motion at all
    _, s4, _, _, _ = env.step_env(jax.random.PRNGKey(0), s, jnp.array([np.nan, np.nan]), params)
    np.testing.assert_allclose(np.asarray(s4.pos), [4.5, 4.5])
    assert float(s4.theta) == 0.0
