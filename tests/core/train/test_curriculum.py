"""Curriculum by difficulty: the episode pool, resets drawn from it, and levels opened by success."""

from __future__ import annotations

import itertools

import jax
import numpy as np
import pytest
from pydantic import ValidationError

from quicknav_core.config import CurriculumConfig, EnvConfig, TrainConfig, resolve_train
from quicknav_core.train.curriculum import draw_episodes, first_level, make_pool, with_pool
from tests.core.env.reference import grid_dijkstra

ENV = EnvConfig(grid_size=8, train_rooms=24, test_rooms=8, lidar_beams=8, max_steps=30)


@pytest.fixture(scope="module")
def bank():
    env, params = ENV.build("train")
    return env, params


def test_pool__episodes_follow_the_spawn_rule_and_lengths_match_a_dijkstra(bank):
    _, params = bank
    cur = CurriculumConfig(enabled=True, episodes_per_room=6, levels=(0.25, 0.5))
    pool = make_pool(params, ENV, cur, seed=3)
    rooms = np.asarray(params.rooms)
    g, cell = ENV.grid_size, ENV.room_size / ENV.grid_size
    assert len(pool) == 24 * 6 and sorted(np.bincount(pool.room)) == [6] * 24
    assert np.all(np.diff(pool.length) >= 0)
    for r, s, t, length in zip(pool.room, pool.start, pool.goal, pool.length, strict=True):
        free = ~rooms[r]
        assert s != t and free[s // g, s % g] and free[t // g, t % g]
        ref = max(grid_dijkstra(free, {(t // g, t % g): 0.0}, cell)[s // g, s % g] - ENV.goal_radius, 0.0)
        assert length == pytest.approx(ref, abs=1e-4)
    # levels: episodes shorter than 0.25 and 0.5 of the room's side, then all
    assert pool.level_counts == (int(np.sum(pool.length < 2.0)), int(np.sum(pool.length < 4.0)), 144)
    # the goal is the farthest of goal_candidates other cells: never nearer than the median cell
    room, start, goal = draw_episodes(rooms, ENV, 50, seed=0)
    far = [(goal[i] // g - start[i] // g) ** 2 + (goal[i] % g - start[i] % g) ** 2 for i in range(room.size)]
    assert np.median(far) > 4


def test_resets_draw_only_from_the_pool_episodes_in_use(bank):
    env, params = bank
    pool = make_pool(params, ENV, CurriculumConfig(enabled=True, episodes_per_room=8), seed=0)
    level = first_level(pool)
    count = pool.level_counts[level]
    assert 0 < count < len(pool)
    p = with_pool(params, pool, count)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(1), 400), p)
    g, cell = ENV.grid_size, ENV.room_size / ENV.grid_size
    allowed = {(int(pool.room[i]), int(pool.start[i]), int(pool.goal[i])) for i in range(count)}
    cells = np.asarray(states.cell)
    goals = np.floor(np.asarray(states.goal) / cell).astype(int)  # (x, y) -> (col, row)
    seen = {(int(r), int(c[0] * g + c[1]), int(q[1] * g + q[0]))
            for r, c, q in zip(np.asarray(states.room_index), cells, goals, strict=True)}  # fmt: skip
    assert seen <= allowed
    assert len(seen) > min(count, 10) // 2  # and not one episode over and over
    # the goal sits at its cell's centre, the start within its cell
    assert np.allclose(np.asarray(states.goal) / cell % 1.0, 0.5, atol=1e-5)
    # a step's auto-reset draws from the pool too
    ks = jax.random.split(jax.random.PRNGKey(2), 400)
    done_state = states.replace(time=states.time + ENV.max_steps)  # every env is at its limit
    _, after, _, done, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(ks, done_state, np.zeros((400, 2), np.float32), p)
    assert bool(np.all(np.asarray(done)))
    goals = np.floor(np.asarray(after.goal) / cell).astype(int)
    seen = {(int(r), int(c[0] * g + c[1]), int(q[1] * g + q[0]))
            for r, c, q in zip(np.asarray(after.room_index), np.asarray(after.cell), goals, strict=True)}  # fmt: skip
    assert seen <= allowed


def test_curriculum_config__errors_name_the_field():
    with pytest.raises(ValidationError, match=r"levels\[1\]=0.2 must be greater than levels\[0\]=0.5"):
        CurriculumConfig(levels=(0.5, 0.2))
    with pytest.raises(ValidationError, match=r"levels\[0\]=-0.1: allowed range"):
        CurriculumConfig(levels=(-0.1,))
    from quicknav_core.config import ConfigError, resolve_sweep

    with pytest.raises(ConfigError) as e:
        resolve_sweep({"space": "ppo", "overrides": {"curriculum.enabled": True}})
    assert "curriculum" in str(e.value) and "allowed: false" in str(e.value)


def _tiny(kind: str, promote_at: float) -> TrainConfig:
    net = {"kind": "mlp", "hidden_sizes": [16]} if kind == "mlp" else {"kind": "lstm", "num_layers": 1, "hidden_size": 8}
    return resolve_train({"config": {
        "env": ENV.model_dump(mode="json"),
        "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
        "network": net, "num_envs": 16, "total_steps": 16 * 16 * 16, "chunk_steps": 16 * 16 * 2,
        "curriculum": {"enabled": True, "levels": [0.25, 0.5, 0.75], "promote_at": promote_at,
                       "episodes_per_room": 8},
    }})  # fmt: skip


def _episodes_of(trainer, state) -> set[tuple[int, int]]:
    """(room, goal cell) of every env's current episode."""
    env_state = state.env_state.env_state if hasattr(state.env_state, "stats") else state.env_state
    g, cell = ENV.grid_size, ENV.room_size / ENV.grid_size
    goals = np.floor(np.asarray(env_state.goal) / cell).astype(int)
    return {(int(r), int(q[1] * g + q[0])) for r, q in zip(np.asarray(env_state.room_index), goals, strict=True)}


def _pool_episodes(pool, count: int) -> set[tuple[int, int]]:
    return {(int(pool.room[i]), int(pool.goal[i])) for i in range(count)}


@pytest.mark.parametrize("kind", ["mlp", "lstm"])  # rejax PPO and the recurrent PPO
def test_trainer__opens_the_next_level_at_the_threshold_without_recompiling(kind):
    from quicknav_core.train.trainers import _rejax_unit, make_trainer

    trainer = make_trainer(_tiny(kind, promote_at=0.8))
    pool = trainer.pool
    state = trainer.init_state()
    level = first_level(pool)
    assert trainer.pool_count(state) == pool.level_counts[level]
    allowed = _pool_episodes(pool, pool.level_counts[level])
    assert _episodes_of(trainer, state) <= allowed  # the first resets already use the first level
    for _ in range(2):  # (the first state's layout differs from the steady one's: 2 programs)
        state, _ = trainer.run_unit(state)
    compiled = _rejax_unit if kind == "mlp" else type(trainer.algo).train_chunk
    programs = compiled._cache_size()
    state, m = trainer.curriculum(state, {"success_rate": 0.79})
    assert m["curriculum_level"] == level and trainer.pool_count(state) == pool.level_counts[level]
    assert m["curriculum_max_path"] == pytest.approx(pool.max_length(level))
    state, m = trainer.curriculum(state, {"success_rate": 0.8})
    assert m["curriculum_level"] == level  # the chunk trained at the old level...
    nxt = level + 1
    while pool.level_counts[nxt] == pool.level_counts[level]:
        nxt += 1
    assert trainer.pool_count(state) == pool.level_counts[nxt]  # ...the next one is open now
    # the compiled program reads the new level from the state: episodes from the wider pool
    # appear, nothing recompiles
    wider = _pool_episodes(pool, pool.level_counts[nxt])
    seen = set()
    for _ in range(6):
        state, _ = trainer.run_unit(state)
        seen |= _episodes_of(trainer, state)
    assert seen <= wider and seen - allowed
    assert compiled._cache_size() == programs
    # the level is part of the checkpoint
    restored = trainer.from_bytes(trainer.to_bytes(state))
    assert trainer.pool_count(restored) == pool.level_counts[nxt]
    # at the last level nothing more opens
    last = trainer.with_pool_count(restored, len(pool))
    last, m = trainer.curriculum(last, {"success_rate": 1.0})
    assert trainer.pool_count(last) == len(pool) and m["curriculum_level"] == len(pool.level_counts) - 1


def test_train_run__records_the_level_of_every_chunk(tmp_path):
    from quicknav_core.train.run import read_metrics, train_run

    train_run(_tiny("mlp", promote_at=1.0), tmp_path / "run")
    metrics = read_metrics(tmp_path / "run")
    assert len(metrics) == 8
    for before, after in itertools.pairwise(metrics):
        if after["curriculum_level"] > before["curriculum_level"]:
            assert before["success_rate"] == 1.0
    assert all(m["curriculum_max_path"] < 2.0 for m in metrics if m["curriculum_level"] == 0)


def test_checkpoint_from_before_the_curriculum_field_still_restores():
    """Checkpoints written before the stats wrapper carried ``pool_count`` resume (fresh value)."""
    from flax import serialization

    from quicknav_core.train.trainers import make_trainer

    cfg = _tiny("mlp", promote_at=0.8).model_copy(update={"curriculum": CurriculumConfig()})
    trainer = make_trainer(cfg)
    state = jax.device_get(trainer.init_state())
    old = serialization.to_state_dict(state)
    del old["env_state"]["pool_count"]  # what an older checkpoint holds
    restored = trainer.from_bytes(serialization.msgpack_serialize(old))
    assert int(np.asarray(restored.env_state.pool_count)[0]) == 0
    np.testing.assert_array_equal(np.asarray(restored.env_state.env_state.pos), np.asarray(state.env_state.env_state.pos))


def test_checkpoint__a_complete_one_loads_without_running_init_state():
    """Loading takes the state's layout from tracing ``init_state`` (``jax.eval_shape``): nothing
    of it is computed (an eval, an export or a resume used to build and run the whole
    initialisation first, rooms and rollout buffers included, only to throw its values away)."""
    from flax import serialization

    from quicknav_core.train.trainers import make_trainer

    trainer = make_trainer(_tiny("mlp", promote_at=0.8))
    state = jax.device_get(trainer.init_state())
    data = serialization.msgpack_serialize(serialization.to_state_dict(state))
    fresh = make_trainer(_tiny("mlp", promote_at=0.8))
    traced = []  # per init_state call: were its outputs tracers (traced, not computed)?
    real_init = fresh.init_state

    def spy():
        out = real_init()
        traced.append(any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(out)))
        return out

    fresh.init_state = spy
    restored = fresh.from_bytes(data)
    assert traced == [True]
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the layout loading always gave: the fresh trainer's own initial state's
    assert jax.tree.structure(restored) == jax.tree.structure(real_init())
