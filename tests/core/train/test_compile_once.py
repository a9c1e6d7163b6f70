"""Compile once per shape: configs that differ only in numbers (reward weights, speeds, the room
bank's seed) share compiled code, in the env and in the trainers of one runtime; numbers are never
baked into a program another config reuses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import ConfigError, EnvConfig, resolve_train
from quicknav_core.env.quicknav import QuickNavEnv

BASE = {"grid_size": 8, "train_rooms": 8, "test_rooms": 8, "lidar_beams": 8}
NUMBERS_ONLY = {"room_seed": 3, "robot_radius": 0.2, "max_steps": 77, "max_wheel_speed": 0.8,
                "reward": {"goal_reward": 20.0, "step_penalty": 0.3}}  # fmt: skip


def test_env__numbers_do_not_enter_the_compile_key_and_are_never_baked_in():
    a, pa = EnvConfig(**BASE).build("train")
    b, pb = EnvConfig(**BASE, **NUMBERS_ONLY).build("train")
    c, _ = EnvConfig(**{**BASE, "lidar_beams": 12}).build("train")
    assert a == b and hash(a) == hash(b) and a != c
    key = jax.random.PRNGKey(0)
    before = QuickNavEnv._jit_reset._cache_size()
    obs_a, state_a = a.reset(key, pa)
    obs_b, state_b = b.reset(key, pb)
    assert QuickNavEnv._jit_reset._cache_size() == before + 1  # one program for both
    # each ran with its own numbers: B's room bank (another seed) and B's defaults when omitted
    assert not np.array_equal(state_a.walls, state_b.walls)
    obs_b2, state_b2 = b.reset(key)  # params=None: B's own train params, not A's baked in
    np.testing.assert_array_equal(obs_b2, obs_b)
    np.testing.assert_array_equal(state_b2.walls, state_b.walls)
    action = jnp.array([1.0, 1.0])
    _, moved_a, reward_a, _, _ = a.step(key, state_a, action, pa)
    _, moved_b, reward_b, _, _ = b.step(key, state_a, action, pb)
    # the same start driven at B's slower wheel speed moves less, and B's step penalty shows
    step_a = np.linalg.norm(moved_a.pos - state_a.pos)
    step_b = np.linalg.norm(moved_b.pos - state_a.pos)
    assert step_b == pytest.approx(0.8 * step_a, rel=1e-4)
    assert float(reward_a) != float(reward_b)


TINY = {"env.grid_size": 8, "env.train_rooms": 8, "env.test_rooms": 8, "env.lidar_beams": 8,
        "num_envs": 4, "algorithm.num_steps": 8, "algorithm.num_minibatches": 2,
        "algorithm.num_epochs": 1, "total_steps": 64, "chunk_steps": 32}  # fmt: skip


@pytest.mark.parametrize("preset,probe", [("paper-ppo", "rejax"), ("paper-mlp", "recurrent")])
def test_trainers__runs_that_differ_only_in_numbers_compile_once(preset, probe):
    from quicknav_core.runtime import Runtime
    from quicknav_core.train import trainers
    from quicknav_core.train.recurrent_ppo import RecurrentPPO

    compiled = trainers._rejax_unit if probe == "rejax" else RecurrentPPO.train_chunk
    runtime = Runtime()  # the process's (a worker's): what makes rejax's optimisers shareable
    runs = []
    # rejax's optimiser is a closure over its learning rate (a compile constant there): only
    # QuickNav's PPO varies it here
    numbers = {"env.reward.goal_reward": 7.0, "env.room_seed": 5, "env.robot_radius": 0.2}
    if probe == "recurrent":
        numbers["algorithm.learning_rate"] = 1e-2
    for extra in ({}, numbers):
        cfg = resolve_train({"preset": preset, "overrides": {**TINY, **extra}})
        trainer = trainers.make_trainer(cfg, runtime)
        runs.append((trainer, trainer.init_state()))
    before = compiled._cache_size()
    for trainer, state in runs:
        trainer.run_unit(state)
    assert compiled._cache_size() == before + 1


def test_recurrent_ppo__env_steps_are_counted_past_two_billion():
    from quicknav_core.train.trainers import make_trainer

    cfg = resolve_train({"preset": "paper-mlp", "overrides": TINY})
    trainer = make_trainer(cfg)
    state = trainer.init_state().replace(update=jnp.int32(2_000_000_000))
    assert trainer.env_steps(state) == 2_000_000_000 * cfg.num_envs * cfg.algorithm.num_steps


def test_resolve__rejax_runs_past_its_int32_step_count_are_refused():
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": "paper-ppo", "overrides": {"total_steps": 3_000_000_000}})
    (item,) = e.value.items
    assert item["loc"] == ["overrides", "total_steps"] and "implementation='quicknav'" in item["msg"]
    ok = resolve_train({"preset": "paper-ppo", "overrides": {
        "total_steps": 3_000_000_000, "algorithm.implementation": "quicknav"}})  # fmt: skip
    assert ok.total_steps == 3_000_000_000


def test_compilation_cache__one_setup_for_the_cli_and_the_workers(tmp_path, monkeypatch):
    """Both doors turn the cache on through quicknav_core.compile_cache: the environment's
    JAX_COMPILATION_CACHE_DIR wins, else the folder given (made), and an unusable one means no
    cache rather than no run."""
    import jax

    from quicknav_core.compile_cache import MIN_COMPILE_TIME_S, enable_compilation_cache

    before = jax.config.jax_compilation_cache_dir
    min_time = jax.config.jax_persistent_cache_min_compile_time_secs
    try:
        monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
        assert enable_compilation_cache(tmp_path / "mine") == tmp_path / "mine"
        assert (tmp_path / "mine").is_dir()
        assert jax.config.jax_compilation_cache_dir == str((tmp_path / "mine").resolve())
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "shared"))
        assert enable_compilation_cache(tmp_path / "mine") == tmp_path / "shared"
        monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR")
        (tmp_path / "file").write_text("")
        assert enable_compilation_cache(tmp_path / "file" / "below") is None
        assert enable_compilation_cache(None) is None
        # the smallest program worth a file: ours, unless the environment names one (as JAX's own
        # variable does; this test run sets it so its hundreds of processes share small programs)
        monkeypatch.delenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", raising=False)
        enable_compilation_cache(tmp_path / "mine")
        assert jax.config.jax_persistent_cache_min_compile_time_secs == MIN_COMPILE_TIME_S
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
        enable_compilation_cache(tmp_path / "mine")
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.1
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", min_time)
