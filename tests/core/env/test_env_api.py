"""gymnax API, batching, compilation behaviour, and the pitfalls seen in another implementation."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.lidar import beam_angles
from tests.core.env.reference import brute_force_lidar


def test_reset__first_observation_has_the_real_lidar(default_env, default_config):
    env, params = default_env
    cfg = default_config
    keys = jax.random.split(jax.random.PRNGKey(0), 50)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    obs, state = np.asarray(obs), jax.tree.map(np.asarray, state)
    b = cfg.lidar_beams
    assert (obs[:, 4 : 4 + b] > 0).all(), "lidar must not be left at zero after a reset"
    for i in range(50):
        ref, _ = brute_force_lidar(
            state.pos[i], state.theta[i], state.goal[i], state.walls[i],
            np.asarray(beam_angles(b, 360.0)), cfg.cell_size, cfg.lidar_max_range, cfg.goal_radius,
        )  # fmt: skip
        np.testing.assert_allclose(obs[i, 4 : 4 + b] * cfg.lidar_max_range, ref, atol=1e-4)


def test_reset__start_and_goal_differ_and_are_independent(small_env, small_config):
    env, params = small_env
    g, cell = small_config.grid_size, small_config.cell_size
    keys = jax.random.split(jax.random.PRNGKey(1), 4000)
    _, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    pos, goal = np.asarray(state.pos), np.asarray(state.goal)
    walls, room = np.asarray(state.walls), np.asarray(state.room_index)
    start_cell = np.floor(pos / cell).astype(int)
    goal_cell = np.floor(goal / cell).astype(int)
    assert (start_cell != goal_cell).any(axis=1).all(), "goal must never be in the start cell"
    rows = np.arange(len(pos))
    assert not walls[rows, start_cell[:, 1], start_cell[:, 0]].any()
    assert not walls[rows, goal_cell[:, 1], goal_cell[:, 0]].any()
    # goal is the farthest of 5 candidates: clearly farther than a uniform free cell would be
    dist = np.linalg.norm(goal - pos, axis=1)
    assert dist.mean() > 0.3 * g * cell
    # spawn uses its own keys: start cells of one room spread over its free cells
    r0 = room == np.bincount(room).argmax()
    starts = {tuple(c) for c in start_cell[r0]}
    assert len(starts) >= 0.8 * (~walls[r0][0]).sum()
    # headings cover the circle
    theta = np.asarray(state.theta)
    assert abs(np.cos(theta).mean()) < 0.1 and abs(np.sin(theta).mean()) < 0.1
    # every room of the bank is used
    assert len(np.unique(room)) == params.rooms.shape[0]


def test_observation__inside_the_exact_space(small_env):
    env, params = small_env
    space = env.observation_space(params)
    keys = jax.random.split(jax.random.PRNGKey(2), 256)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    assert obs.shape == (256, *space.shape) and obs.dtype == jnp.float32
    assert bool(jax.vmap(space.contains)(obs).all())
    assert env.action_space(params).shape == (2,)


def test_vmap_over_many_envs_and_no_retrace(small_env):
    env, params = small_env
    n = 1024
    traces = []

    def rollout(state, key):
        traces.append(1)  # runs only while tracing

        def body(s, k):
            act = jax.random.uniform(k, (n, 2), minval=-1.0, maxval=1.0)
            obs, s, r, d, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k, n), s, act, params
            )
            return s, (r, d)

        return jax.lax.scan(body, state, jax.random.split(key, 20))

    run = jax.jit(rollout)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(
        jax.random.split(jax.random.PRNGKey(0), n), params
    )
    for i in range(3):
        state, (r, d) = run(state, jax.random.PRNGKey(i))
    assert len(traces) == 1
    assert r.shape == (20, n) and bool(jnp.isfinite(r).all())
    # an equal env (same config) is the same static argument: shared compiled code
    env2, _ = EnvConfig.model_validate(env.config.model_dump()).build()
    assert env2 == env and hash(env2) == hash(env)


def test_auto_reset__final_obs_is_pre_reset(small_env):
    env, params = small_env
    cfg = env.config.model_copy(update={"max_steps": 2})
    env2, params2 = cfg.build()
    _, s = env2.reset(jax.random.PRNGKey(0), params2)
    _, s, _, d, _ = env2.step(jax.random.PRNGKey(1), s, jnp.zeros(2), params2)
    assert not bool(d)
    obs, s_new, _, d, info = env2.step(jax.random.PRNGKey(2), s, jnp.zeros(2), params2)
    assert bool(d) and bool(info["truncated"])
    assert int(s_new.time) == 0  # a fresh episode
    # the final observation shows the robot where it stood (zero action: it did not move)
    np.testing.assert_allclose(
        np.asarray(info["final_obs"][:2]) * cfg.room_size, np.asarray(s.pos), atol=1e-6
    )
    np.testing.assert_allclose(
        np.asarray(obs[:2]) * cfg.room_size, np.asarray(s_new.pos), atol=1e-6
    )


def test_test_split_uses_held_out_bank(small_config):
    _, train = small_config.build("train")
    _, test = small_config.build("test")
    train_set = {r.tobytes() for r in np.asarray(train.rooms)}
    assert not any(r.tobytes() in train_set for r in np.asarray(test.rooms))
    with pytest.raises(ValueError, match="split"):
        small_config.build("val")


def test_numpy_twin_does_not_import_jax():
    code = (
        "import sys; import quicknav_core.env.numpy_env as m; "
        "from quicknav_core.config.env import EnvConfig; "
        "env = m.QuickNavNumpyEnv(EnvConfig()); env.reset(seed=0); env.step([1.0, 1.0]); "
        "assert not any(k == 'jax' or k.startswith('jax.') for k in sys.modules), 'jax imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_numpy_twin__gymnasium_checker():
    from gymnasium.utils.env_checker import check_env

    from quicknav_core.env.numpy_env import QuickNavNumpyEnv

    env = QuickNavNumpyEnv(EnvConfig(grid_size=8, train_rooms=8))
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    for _ in range(50):
        obs, *_ = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)


def test_rejax_ppo_trains_on_the_env(small_env):
    import rejax

    env, params = small_env
    algo = rejax.PPO.create(
        env=env, env_params=params, num_envs=8, num_steps=16, num_epochs=1, num_minibatches=2,
        total_timesteps=8 * 16 * 2, eval_freq=8 * 16, skip_initial_evaluation=True,
        agent_kwargs={"hidden_layer_sizes": (16,)},
    )  # fmt: skip
    algo = algo.replace(eval_callback=lambda a, ts, rng: jnp.zeros(()))
    ts, _ = jax.jit(algo.train)(jax.random.PRNGKey(0))
    leaves = jax.tree.leaves(ts.actor_ts.params)
    assert all(bool(jnp.isfinite(x).all()) for x in leaves)
    assert int(ts.global_step) >= 8 * 16 * 2
