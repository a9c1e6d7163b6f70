"""Sensor and actuator randomisation (``EnvConfig.randomize``): off changes nothing, on matches the
NumPy twin draw for draw, and each perturbation does what it says, measured."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pydantic import ValidationError

from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import HIT_NONE, LATENCY_MAX_STEPS
from quicknav_core.env.numpy_env import QuickNavNumpyEnv
from quicknav_core.env.perturb import at_rest

BASE = dict(grid_size=8, lidar_beams=8, train_rooms=32, test_rooms=16, max_steps=80)
ON = dict(
    lidar_noise_m=[0.0, 0.05], lidar_noise_frac=[0.0, 0.1], lidar_bias_m=[-0.05, 0.05],
    beam_dropout=[0.0, 0.3], wheel_scale_left=[0.85, 1.1], wheel_scale_right=[0.9, 1.15],
    latency_steps=[0, 3], robot_radius_m=[0.1, 0.2],
)  # fmt: skip


def _rollout(env, params, actions, seed):
    """vmap(env.step) over (T, N) actions; per step: obs, reward, done, final obs, fresh states."""
    n = actions.shape[1]
    obs0, s0 = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(seed), n), params)
    vstep = jax.vmap(env.step, in_axes=(0, 0, 0, None))

    def body(state, xs):
        key, act = xs
        obs, state, reward, done, info = vstep(jax.random.split(key, n), state, act, params)
        return state, (obs, reward, done, info["final_obs"], state)

    keys = jax.random.split(jax.random.PRNGKey(seed + 1), actions.shape[0])
    _, recs = jax.jit(lambda s: jax.lax.scan(body, s, (keys, actions)))(s0)
    return jax.tree.map(np.asarray, (obs0, s0)), jax.tree.map(np.asarray, recs)


def _actions(steps, n, seed=3):
    rng = np.random.default_rng(seed)
    a = 0.6 * rng.uniform(-1, 1, (steps, n, 2)).astype(np.float32) + np.float32(0.45)
    a[rng.random((steps, n)) < 0.02] = np.nan
    return a


def test_randomize__at_identity_is_the_plain_env_exactly(optimized):
    plain_env, plain_params = EnvConfig(**BASE).build()
    env, params = EnvConfig(**BASE, randomize={}).build()
    assert env != plain_env  # its own compiled program (the state carries the draws)
    actions = _actions(120, 6)
    (o0, _), (obs, rew, done, _, _) = _rollout(plain_env, plain_params, actions, seed=5)
    (p0, _), (pobs, prew, pdone, _, _) = _rollout(env, params, actions, seed=5)
    np.testing.assert_array_equal(o0, p0)
    np.testing.assert_array_equal(obs, pobs)
    np.testing.assert_array_equal(rew, prew)
    assert done.sum() >= 3 and (done == pdone).all()


def test_randomize__the_twin_matches_the_jax_env_with_the_same_draws():
    config = EnvConfig(**BASE, randomize=ON)
    env, params = config.build()
    n, steps = 8, 240
    actions = _actions(steps, n)
    (obs0, s0), (obs, rewards, dones, final, states) = _rollout(env, params, actions, seed=11)
    pert = lambda tree, i: jax.tree.map(lambda x: x[i], tree)  # noqa: E731
    twin = QuickNavNumpyEnv(config)
    b, max_range = config.lidar_beams, config.lidar_max_range
    episodes = delayed = dropped = 0
    for i in range(n):
        o = twin.load(s0.walls[i], s0.pos[i], s0.theta[i], s0.goal[i], pert(s0.perturbation, i))
        np.testing.assert_allclose(o, obs0[i], atol=1e-5)
        for t in range(steps):
            o, r, term, trunc, _ = twin.step(actions[t, i])
            ref = final[t, i]
            assert np.abs(o[:2] - ref[:2]).max() * config.room_size < 1e-3, (i, t, "position")
            assert np.abs(o[4 : 4 + b] - ref[4 : 4 + b]).max() * max_range < 1e-3, (i, t, "lidar")
            assert (o[4 + b : 4 + 3 * b] == ref[4 + b : 4 + 3 * b]).all(), (i, t, "hit types")
            assert abs(r - rewards[t, i]) < 1e-4, (i, t, "reward")
            assert (term or trunc) == bool(dones[t, i]), (i, t, "done")
            dropped += int(((o[4 + b : 4 + 3 * b].reshape(2, b).sum(0) == 0)).sum())
            if dones[t, i]:
                episodes += 1
                fresh = pert(states.perturbation, (t, i))
                delayed += int(fresh.latency_steps > 0)
                o = twin.load(states.walls[t, i], states.pos[t, i], states.theta[t, i],
                              states.goal[t, i], fresh)  # fmt: skip
                np.testing.assert_allclose(o, obs[t, i], atol=1e-5)
    assert episodes >= n and delayed >= 3 and dropped > 100


def test_randomize__draws_lie_in_their_ranges_per_env_per_episode():
    env, params = EnvConfig(**BASE, randomize=ON).build()
    keys = jax.random.split(jax.random.PRNGKey(0), 2000)
    _, s = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    p = jax.tree.map(np.asarray, s.perturbation)
    for name in ("lidar_noise_m", "lidar_noise_frac", "lidar_bias_m", "beam_dropout"):
        lo, hi = ON[name]
        v = getattr(p, name)
        assert v.min() >= lo and v.max() <= hi and v.max() - v.min() > 0.9 * (hi - lo), name
    for w, name in enumerate(("wheel_scale_left", "wheel_scale_right")):
        lo, hi = ON[name]
        assert lo <= p.wheel_scale[:, w].min() and p.wheel_scale[:, w].max() <= hi
    assert np.corrcoef(p.wheel_scale.T)[0, 1] < 0.1  # the wheels draw separately
    counts = np.bincount(p.latency_steps, minlength=LATENCY_MAX_STEPS + 1)
    assert (counts[:4] > 400).all() and counts[4:].sum() == 0  # 0..3 uniformly, nothing else
    assert p.robot_radius.min() >= 0.1 and p.robot_radius.max() <= 0.2
    assert len(np.unique(p.noise_seed)) > 1990


def test_randomize__noise_dropout_and_bias_have_their_measured_sizes():
    config = EnvConfig(**BASE)
    env, params = EnvConfig(**BASE, randomize={}).build()
    _, s = env.reset(jax.random.PRNGKey(4), params)
    true_ranges, true_hits = np.asarray(s.lidar_ranges), np.asarray(s.lidar_hits)
    assert (true_hits != HIT_NONE).all()

    def scans(**draws):
        p = at_rest(config.robot_radius, **draws)
        states = jax.vmap(lambda seed: s.replace(perturbation=p.replace(noise_seed=seed)))(
            jnp.arange(4000, dtype=jnp.uint32)
        )
        out = jax.vmap(env.with_lidar, in_axes=(0, None))(states, params)
        return np.asarray(out.lidar_ranges), np.asarray(out.lidar_hits)

    r, h = scans(lidar_noise_frac=0.05)
    rel = r / true_ranges - 1.0
    assert abs(rel.std() - 0.05) < 0.003 and abs(rel.mean()) < 0.003
    r, _ = scans(lidar_noise_m=0.02)
    assert abs((r - true_ranges).std() - 0.02) < 0.002
    r, h = scans(beam_dropout=0.25)
    gone = h == HIT_NONE
    assert abs(gone.mean() - 0.25) < 0.01 and (r[gone] == config.lidar_max_range).all()
    np.testing.assert_allclose(r[~gone], np.broadcast_to(true_ranges, r.shape)[~gone], atol=1e-6)
    r, _ = scans(lidar_bias_m=-0.1)
    np.testing.assert_allclose(r, np.maximum(true_ranges - 0.1, 0.0)[None].repeat(4000, 0), atol=1e-6)
    # the same state casts the same scan (auto-reset's final observation sees what the step saw)
    p = at_rest(config.robot_radius, lidar_noise_frac=0.1, noise_seed=9)
    a = env.with_lidar(s.replace(perturbation=p), params)
    b = env.with_lidar(s.replace(perturbation=p), params)
    np.testing.assert_array_equal(a.lidar_ranges, b.lidar_ranges)


def test_randomize__latency_delays_the_command_and_a_slow_wheel_turns_the_robot():
    config = EnvConfig(**BASE)
    env, params = EnvConfig(**BASE, randomize={}).build()
    walls = np.ones((8, 8), bool)
    walls[1:7, 1:7] = False
    start = dict(walls=walls, pos=jnp.array([1.5, 4.0]), theta=0.0, goal=jnp.array([3.5, 3.5]))

    def drive(steps, **draws):
        _, s = env.load_state(**start, params=params, perturbation=at_rest(config.robot_radius, **draws))
        xs, thetas = [], []
        for t in range(steps):
            _, s, _, _, _ = env.step_env(jax.random.PRNGKey(t), s, jnp.ones(2), params)
            xs.append(float(s.pos[0]))
            thetas.append(float(s.theta))
        return np.array(xs), np.array(thetas)

    x0, _ = drive(6)
    for k in (1, 2, 3):
        xk, _ = drive(6, latency_steps=k)
        assert (xk[:k] == 1.5).all() and xk[k] > 1.5  # at rest for k steps, then as without delay
        np.testing.assert_allclose(np.diff(xk[k:]), np.diff(x0[: 6 - k]), atol=1e-6)
    _, straight = drive(10)
    _, pulled = drive(10, wheel_scale=(0.9, 1.0))
    assert np.abs(straight).max() == 0.0
    # right wheel faster: the robot turns left (counter-clockwise) by 0.1 m/s / 0.3 m base per s
    np.testing.assert_allclose(pulled[-1], 10 * 0.1 * 0.1 / 0.3, rtol=1e-4)


def test_randomize__changing_ranges_does_not_recompile():
    a_env, a_params = EnvConfig(**BASE, randomize={"beam_dropout": [0.0, 0.1]}).build()
    b_env, b_params = EnvConfig(**BASE, randomize={"beam_dropout": [0.3, 0.5], "latency_steps": [1, 2]}).build()
    assert a_env == b_env and hash(a_env) == hash(b_env)
    step = jax.jit(a_env.step_env)
    _, s = a_env.reset(jax.random.PRNGKey(0), a_params)
    step(jax.random.PRNGKey(0), s, jnp.ones(2), a_params)
    _, s = b_env.reset(jax.random.PRNGKey(0), b_params)
    step(jax.random.PRNGKey(0), s, jnp.ones(2), b_params)
    assert step._cache_size() == 1


@pytest.mark.parametrize(
    "randomize, needle",
    [
        ({"lidar_noise_frac": [0.2, 0.1]}, "lidar_noise_frac=[0.2, 0.1]: a range is [low, high]"),
        ({"latency_steps": [0, LATENCY_MAX_STEPS + 1]}, "less than or equal to 4"),
        ({"beam_dropout": [0, 1.0]}, "less than or equal to 0.99"),
        ({"wheel_scale_left": [1.0, 1.5]}, "allowed range wheel scale <="),
        ({"lidar_noise": [0, 1]}, "lidar_noise"),
    ],
)
def test_randomize__bad_ranges_are_refused_naming_the_field_and_the_range(randomize, needle):
    extra = {"max_wheel_speed": 8.0} if "wheel_scale_left" in randomize else {}
    with pytest.raises(ValidationError) as e:
        EnvConfig(**BASE, **extra, randomize=randomize)
    assert needle in str(e.value)
    if "latency_steps" in randomize:
        assert "randomize.latency_steps" in str(e.value)
