"""A run's policy read from its checkpoint without its trainer (``load_policy``): the same network
and parameters the trainer's own restore gives, for every trainer kind, and a clear error for a
checkpoint that does not fit the run's config. No program here trains or initialises a state:
checkpoints are filled from the traced layout (``jax.eval_shape``)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from flax import serialization

from quicknav_core.config import resolve_train
from quicknav_core.train.trainers import make_trainer, policy_from_bytes

ENV = {"grid_size": 8, "room_size": 4.0, "train_rooms": 8, "test_rooms": 8, "lidar_beams": 8,
       "max_steps": 20}  # fmt: skip
KINDS = {
    "rejax-ppo": ({"name": "ppo", "num_steps": 8, "num_minibatches": 2, "num_epochs": 1},
                  {"kind": "mlp", "hidden_sizes": [16, 8]}),
    "recurrent-mlp": ({"name": "ppo", "implementation": "quicknav", "num_steps": 8,
                       "num_minibatches": 2, "num_epochs": 1},
                      {"kind": "mlp", "hidden_sizes": [16], "frames": 2}),
    "recurrent-lstm": ({"name": "ppo", "num_steps": 8, "num_minibatches": 2, "num_epochs": 1},
                       {"kind": "lstm", "num_layers": 1, "hidden_size": 8}),
    "rejax-sac": ({"name": "sac", "buffer_size": 64, "batch_size": 8, "fill_buffer": 8},
                  {"kind": "mlp", "hidden_sizes": [16]}),
    "rejax-td3": ({"name": "td3", "buffer_size": 64, "batch_size": 8, "fill_buffer": 8},
                  {"kind": "mlp", "hidden_sizes": [16]}),
}  # fmt: skip


def config_of(kind: str, **network):
    algo, net = KINDS[kind]
    return resolve_train({"config": {"env": ENV, "algorithm": algo, "network": {**net, **network},
                                     "num_envs": 4, "total_steps": 64, "chunk_steps": 32}})  # fmt: skip


def checkpoint_of(trainer, seed: int = 0) -> bytes:
    """What ``Trainer.to_bytes`` writes for a state of the trainer's layout, filled with numbers."""
    rng = np.random.default_rng(seed)

    def fill(leaf):
        if np.issubdtype(leaf.dtype, np.floating):
            return rng.normal(size=leaf.shape).astype(leaf.dtype)
        return np.zeros(leaf.shape, leaf.dtype)

    state = jax.tree.map(fill, jax.eval_shape(trainer.init_state))
    return serialization.msgpack_serialize(serialization.to_state_dict(state))


@pytest.mark.parametrize("kind", list(KINDS))
def test_load_policy__the_network_and_parameters_the_trainers_restore_gives(kind):
    config = config_of(kind)
    trainer = make_trainer(config)
    assert config.trainer_kind == (kind if kind.startswith("rejax") else "recurrent-ppo")
    data = checkpoint_of(trainer)
    want = trainer.policy(trainer.from_bytes(data))
    got = policy_from_bytes(config, data)
    assert got.kind == want.kind and got.module == want.module
    assert jax.tree.structure(got.params) == jax.tree.structure(want.params)
    for a, b in zip(jax.tree.leaves(got.params), jax.tree.leaves(want.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # and it acts as the trainer's policy does
    obs = np.random.default_rng(1).normal(size=(3, config.env.obs_dim)).astype(np.float32)
    start = np.ones(3, bool)
    acts = [p.act(p.initial_carry(3), obs, start, jax.random.PRNGKey(0))[1] for p in (got, want)]
    np.testing.assert_array_equal(np.asarray(acts[0]), np.asarray(acts[1]))
    assert np.abs(np.asarray(acts[0])).max() > 0  # the filled parameters act, not zeros


def test_load_policy__a_checkpoint_of_another_network_is_refused_by_name():
    data = checkpoint_of(make_trainer(config_of("rejax-ppo")))  # 16 x 8
    with pytest.raises(ValueError, match=r"checkpoint array /actor_ts/params/.* has shape"):
        policy_from_bytes(config_of("rejax-ppo", hidden_sizes=[32, 8]), data)
    lstm = checkpoint_of(make_trainer(config_of("recurrent-lstm")))
    with pytest.raises(ValueError, match=r"checkpoint has no /actor_ts/params"):
        policy_from_bytes(config_of("rejax-td3"), lstm)
    with pytest.raises(ValueError, match=r"holds other arrays than this run's network \(lstm\)"):
        policy_from_bytes(config_of("recurrent-lstm", num_layers=2), lstm)


def test_evaluation_and_export_read_a_run_without_building_its_trainer(tmp_path, monkeypatch):
    """An eval, an export or the Policy stream never builds the trainer (its room bank, its
    algorithm, its traced state): ``agent_from_run`` works with ``make_trainer`` gone."""
    from quicknav_core.eval.agents import agent_from_run
    from quicknav_core.layout import RunFolder
    from quicknav_core.train import trainers
    from quicknav_core.train.run import save_checkpoint

    config = config_of("recurrent-mlp")
    trainer = make_trainer(config)
    run = RunFolder(tmp_path / "run")
    run.path.mkdir()
    run.config.write_text(config.model_dump_json())
    data = checkpoint_of(trainer)
    monkeypatch.setattr(trainer, "to_bytes", lambda state, with_replay=True: data)
    monkeypatch.setattr(trainer, "env_steps", lambda state: 64)
    save_checkpoint(run.path, trainer, None, chunk=2)

    def refuse(*args, **kwargs):
        raise AssertionError("make_trainer called to load a policy")

    monkeypatch.setattr(trainers, "make_trainer", refuse)
    agent, env, meta = agent_from_run(run.path)
    assert env == config.env and meta["env_steps"] == 64
    want = policy_from_bytes(config, data)
    for a, b in zip(jax.tree.leaves(agent.policy.params), jax.tree.leaves(want.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
