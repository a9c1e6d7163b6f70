"""BatchedEnv's step (one lidar cast per env plus the few that reset) equals vmap(env.step)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.batch import BatchedEnv, batched_step
from tests.compile_settings import with_cpu_devices

N = 16


@pytest.mark.parametrize("capacity", [2, N])
def test_batched_step__equals_vmapped_env_step(capacity):
    # max_steps=9 makes every env that has not reached its goal truncate at once (the full path)
    # while random driving ends some episodes early at different steps (the gathered path)
    env, params = EnvConfig(grid_size=6, room_size=3.0, train_rooms=8, max_steps=9, goal_radius=0.9,
                            goal_candidates=1,
                            lidar_beams=8).build("train")  # fmt: skip
    keys = jax.random.split(jax.random.PRNGKey(0), N)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    ref_state = state
    fast = jax.jit(lambda k, s, a: batched_step(env, k, s, a, params, reset_capacity=capacity))
    slow = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    ended = []
    for t in range(40):
        step_keys = jax.random.split(jax.random.PRNGKey(t + 1), N)
        action = jax.random.uniform(jax.random.PRNGKey(100 + t), (N, 2), minval=-1, maxval=1)
        obs, state, reward, info, final = fast(step_keys, state, action)
        r_obs, ref_state, r_reward, r_done, r_info = slow(step_keys, ref_state, action, params)
        done = np.asarray(info["terminated"] | info["truncated"])
        np.testing.assert_array_equal(done, np.asarray(r_done))
        np.testing.assert_allclose(obs, r_obs, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(reward, r_reward, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(final, r_info["final_obs"], rtol=1e-4, atol=1e-5)
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(ref_state), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
        ended.append(int(done.sum()))
    # both paths ran: steps with a few ended envs and steps with more than the capacity
    assert any(0 < e <= 2 for e in ended) and any(e > 5 for e in ended), ended


def test_batched_env__reset_seed_is_reproducible_and_final_obs_only_for_ended_envs():
    cfg = EnvConfig(grid_size=6, room_size=3.0, train_rooms=8, max_steps=5, lidar_beams=8)
    env = BatchedEnv(cfg, 4, seed=3)
    first = env.reset()
    assert first.shape == (4, cfg.obs_dim) and first.dtype == np.float32
    for _ in range(4):
        r = env.step(np.zeros((4, 2), np.float32))
        assert r.done_indices.size == 0 and r.final_obs.shape == (0, cfg.obs_dim)
    r = env.step(np.zeros((4, 2), np.float32))
    np.testing.assert_array_equal(r.done_indices, np.arange(4))
    assert r.truncated.all() and r.final_obs.shape == (4, cfg.obs_dim)
    np.testing.assert_array_equal(env.reset(seed=3), first)
    assert not np.array_equal(env.reset(seed=4), first)
    assert jnp.asarray(r.obs).shape == (4, cfg.obs_dim)


_SHARDED = """
import jax, jax.numpy as jnp, numpy as np
from quicknav_core.config import EnvConfig
from quicknav_core.env.batch import BatchedEnv, step_keys
assert jax.local_device_count() == 2
cfg = EnvConfig(grid_size=6, room_size=3.0, train_rooms=8, max_steps=7, lidar_beams=4)
n = 512
be = BatchedEnv(cfg, n, seed=1)
assert be._sharding is not None  # the batch is split over the two devices
obs0 = be.reset()
env, params = be.env, be.params
rng = jax.random.PRNGKey(1)
rng, sub, word = jax.random.split(rng, 3)
counter = jnp.stack([jax.random.bits(word, (), jnp.uint32), jnp.uint32(0)])
ref_obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(sub, n), params)
np.testing.assert_allclose(obs0, ref_obs, rtol=1e-4, atol=1e-5)
step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
for t in range(12):
    a = np.random.default_rng(t).uniform(-1, 1, (n, 2)).astype(np.float32)
    r = be.step(a)
    obs, state, reward, done, info = step(step_keys(counter, n), state, jnp.asarray(a), params)
    counter = counter.at[1].add(1)
    np.testing.assert_allclose(r.obs, obs, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(r.reward, reward, rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(r.done_indices, np.flatnonzero(np.asarray(done)))
    np.testing.assert_allclose(r.final_obs, np.asarray(info["final_obs"])[r.done_indices], rtol=1e-4, atol=1e-5)
print("ok")
"""


@pytest.mark.slow  # a subprocess with two XLA CPU devices: ~27 s on 2 cores
def test_batched_env__sharded_over_two_cpu_devices_equals_one_device():
    import subprocess
    import sys

    env = with_cpu_devices(2)
    out = subprocess.run([sys.executable, "-c", _SHARDED], env=env, capture_output=True, text=True,
                         timeout=300)  # fmt: skip
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_gather_rows__matches_numpy_indexing_with_few_compiled_shapes():
    from quicknav_core.env.batch import _take_rows, gather_rows

    x = jnp.arange(300 * 5, dtype=jnp.float32).reshape(300, 5)
    rng = np.random.default_rng(0)
    compiled_before = _take_rows._cache_size()  # other tests in this process gather other shapes
    for n in [0, 1, 7, 8, 9, 33, 100, 300]:
        idx = np.sort(rng.choice(300, n, replace=False)).astype(np.int32)
        got = gather_rows(x, idx, 5)
        assert got.shape == (n, 5)
        np.testing.assert_array_equal(got, np.asarray(x)[idx])
    # one compiled gather per power of two from 8 up, not one per count
    assert _take_rows._cache_size() - compiled_before <= 7


def test_env_and_params__concurrent_starts_of_one_config_build_it_once(monkeypatch):
    """Two rollout streams starting the same new config at once: one carves, the other waits."""
    import threading
    import time

    from quicknav_core.config import EnvConfig
    from quicknav_core.env import batch
    from quicknav_core.runtime import Runtime

    cfg = EnvConfig(grid_size=8, lidar_beams=4, train_rooms=8, test_rooms=4, room_seed=424242)
    calls = []
    real_build = EnvConfig.build

    def slow_build(self, split="train", runtime=None):
        calls.append(split)
        time.sleep(0.3)  # a build long enough for the other thread to arrive meanwhile
        return real_build(self, split, runtime)

    monkeypatch.setattr(EnvConfig, "build", slow_build)
    out = []
    runtime = Runtime()  # the server's one runtime
    threads = [threading.Thread(target=lambda: out.append(batch.env_and_params(cfg, "train", runtime)))
               for _ in range(3)]  # fmt: skip
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert calls == ["train"] and len(out) == 3 and all(o is out[0] for o in out)


def test_bank_walls__above_32_cells_a_step_reads_the_bank_as_it_read_the_state():
    """On a grid above 32 cells the lidar's window and the rows that the collision test, the
    proximity term and the people's walk read come from the room bank by the state's room index:
    nothing in a step reads the state's own copy of its room (XLA copied it twice a step, as a
    buffer read and then rewritten in place by the resets). The same episodes step exactly as
    when every read came from that copy (the code before), with people walking, a plan, and
    resets inside the run."""
    from quicknav_core.env.quicknav import QuickNavEnv

    cfg = EnvConfig(rooms="floorplan", grid_size=48, room_size=24.0, lidar_beams=16, train_rooms=8,
                    test_rooms=2, max_steps=25, obstacles={"static": 2, "moving": 3},
                    observe_plan=True, reward={"proximity_penalty": 0.5})  # fmt: skip
    env, params = cfg.build("train")
    assert env.lidar_window and env.bank_rows and params.room_col_window is not None
    own = QuickNavEnv(cfg, env.rooms)  # the same env, reading its state's copy of the room
    own.lidar_window = own.bank_rows = False
    n = 32
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(4), n), params)
    # (the two envs are equal as jit's static arguments: each gets its own jitted function)
    steps = [jax.jit(lambda k, s, a, e=e: batched_step(e, k, s, a, params)) for e in (env, own)]
    states = [state, state]
    rng, ended, collisions = np.random.default_rng(2), 0, 0
    for t in range(40):
        keys = jax.random.split(jax.random.PRNGKey(50 + t), n)
        action = jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32)
        out = []
        for i in range(2):
            obs, states[i], reward, info, _ = steps[i](keys, states[i], action)
            out.append((np.asarray(obs), np.asarray(reward), np.asarray(info["collision"]),
                        np.asarray(info["terminated"] | info["truncated"])))  # fmt: skip
        for a, b in zip(*out, strict=True):
            np.testing.assert_array_equal(a, b)
        ended, collisions = ended + int(out[0][3].sum()), collisions + int(out[0][2].sum())
    assert ended >= n and collisions > 20  # episodes ended and began again; walls were hit
    np.testing.assert_array_equal(np.asarray(states[0].row_bits), np.asarray(states[1].row_bits))
    # a state made by hand names the bank room its walls are: the lidar reads the bank by index
    room = int(states[0].room_index[0])
    walls, pos, goal = (np.asarray(x[0]) for x in (states[0].walls, states[0].pos, states[0].goal))
    with pytest.raises(ValueError, match=r"room_index=-1 must name the bank room .* \(0 \.\. 7\)"):
        env.load_state(walls, pos, 0.3, goal, params)
    other = (room + 1) % 8  # another room of the bank: other walls
    with pytest.raises(ValueError, match=rf"room_index={other} must name the bank room"):
        env.load_state(walls, pos, 0.3, goal, params, room_index=other)
    _, loaded = env.load_state(walls, pos, 0.3, goal, params, room_index=room)
    _, by_hand = own.load_state(walls, pos, 0.3, goal, params)
    np.testing.assert_array_equal(np.asarray(loaded.lidar_ranges), np.asarray(by_hand.lidar_ranges))
