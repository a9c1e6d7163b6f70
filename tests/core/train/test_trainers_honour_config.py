"""What a config names is what trains: every trainer builds the network shapes, activation and
log std its config names, and a field a trainer cannot honour is refused at resolve time with its
name (rejax's SAC once trained 64x64 whatever ``hidden_sizes`` said)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import ConfigError, resolve_sweep, resolve_train
from quicknav_core.train.trainers import make_trainer

SMALL = {"env.grid_size": 8, "env.train_rooms": 8, "env.test_rooms": 8, "num_envs": 4,
         "total_steps": 4096}  # fmt: skip
OFF_POLICY = {**SMALL, "algorithm.buffer_size": 1000, "algorithm.batch_size": 16}
HIDDEN = [24, 12]


def trained(preset: str, **overrides):
    cfg = resolve_train({"preset": preset, "overrides": overrides})
    trainer = make_trainer(cfg)
    return cfg, trainer, trainer.init_state()


def shapes(tree) -> dict[str, tuple]:
    flat = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {"/".join(str(getattr(k, "key", k)) for k in path): tuple(np.shape(x)) for path, x in flat}


def relu_mlp(params: dict, x: np.ndarray, names: list[str]) -> np.ndarray:
    """A ReLU MLP computed by hand from a parameter tree (the reference for the activation)."""
    for name in names:
        x = np.maximum(x @ np.asarray(params[name]["kernel"]) + np.asarray(params[name]["bias"]), 0)
    return x


def obs_batch(cfg, n: int = 5) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (n, cfg.env.obs_dim)).astype(np.float32)


# --------------------------------------------------------------------------- rejax trainers
def test_rejax_ppo__widths_relu_and_the_log_std_it_names():
    cfg, trainer, state = trained("paper-ppo", **SMALL, **{"network.hidden_sizes": HIDDEN,
                                                           "network.init_log_std": -1.25})  # fmt: skip
    o = cfg.env.obs_dim
    actor = state.actor_ts.params["params"]
    assert shapes(actor) == {
        "action_log_std": (2,), "action_mean/bias": (2,), "action_mean/kernel": (12, 2),
        "features/Dense_0/bias": (24,), "features/Dense_0/kernel": (o, 24),
        "features/Dense_1/bias": (12,), "features/Dense_1/kernel": (24, 12)}  # fmt: skip
    assert shapes(state.critic_ts.params["params"])["Dense_2/kernel"] == (12, 1)
    np.testing.assert_array_equal(actor["action_log_std"], [-1.25, -1.25])
    x = obs_batch(cfg)
    hidden = relu_mlp(actor["features"], x, ["Dense_0", "Dense_1"])
    mean = hidden @ np.asarray(actor["action_mean"]["kernel"]) + np.asarray(actor["action_mean"]["bias"])
    _, action = trainer.policy(state).act((), jnp.asarray(x), None, None, deterministic=True)
    np.testing.assert_allclose(np.asarray(action), np.clip(mean, -1, 1), atol=1e-5)


def test_rejax_sac__trains_the_width_it_names_not_rejaxs_64():
    cfg, trainer, state = trained("paper-sac", **OFF_POLICY, **{"network.hidden_sizes": HIDDEN})
    o = cfg.env.obs_dim
    actor = state.actor_ts.params["params"]
    assert shapes(actor)["features/Dense_0/kernel"] == (o, 24)
    assert shapes(actor)["features/Dense_1/kernel"] == (24, 12)
    assert shapes(actor)["action_log_std/kernel"] == (12, 2)  # per-state log std, as resolved
    critics = shapes(state.critic_ts.params["params"])
    assert critics["Dense_0/kernel"] == (2, o + 2, 24) and critics["Dense_1/kernel"] == (2, 24, 12)
    assert cfg.network.learned_log_std is True and cfg.network.init_log_std is None
    x = obs_batch(cfg)
    hidden = relu_mlp(actor["features"], x, ["Dense_0", "Dense_1"])
    loc = hidden @ np.asarray(actor["action_mean"]["kernel"]) + np.asarray(actor["action_mean"]["bias"])
    _, action = trainer.policy(state).act((), jnp.asarray(x), None, None, deterministic=True)
    np.testing.assert_allclose(np.asarray(action), np.tanh(loc), atol=1e-5)


def test_rejax_td3__widths_and_relu():
    cfg, trainer, state = trained("paper-td3", **OFF_POLICY, **{"network.hidden_sizes": HIDDEN})
    actor = state.actor_ts.params["params"]
    assert shapes(actor) == {
        "Dense_0/bias": (24,), "Dense_0/kernel": (cfg.env.obs_dim, 24), "Dense_1/bias": (12,),
        "Dense_1/kernel": (24, 12), "Dense_2/bias": (2,), "Dense_2/kernel": (12, 2)}  # fmt: skip
    x = obs_batch(cfg)
    hidden = relu_mlp(actor, x, ["Dense_0", "Dense_1"])
    out = hidden @ np.asarray(actor["Dense_2"]["kernel"]) + np.asarray(actor["Dense_2"]["bias"])
    _, action = trainer.policy(state).act((), jnp.asarray(x), None, None, deterministic=True)
    np.testing.assert_allclose(np.asarray(action), np.tanh(out), atol=1e-5)


# --------------------------------------------------------------------------- recurrent PPO
RECURRENT = {**SMALL, "algorithm.num_minibatches": 2, "algorithm.num_steps": 8}


@pytest.mark.parametrize("preset,network,expect", [
    ("paper-mlp", {"network.hidden_sizes": HIDDEN, "network.memory_size": 5},
     {"dense_0/kernel": ("obs+5", 24), "dense_1/kernel": (24, 12), "memory/kernel": (12, 5),
      "ActorCriticHeads_0/mean/kernel": (12, 2)}),
    ("paper-lstm", {"network.hidden_size": 7, "network.num_layers": 3},
     {"lstm_0/ii/kernel": ("obs", 7), "lstm_2/hf/kernel": (7, 7),
      "ActorCriticHeads_0/mean/kernel": (7, 2)}),
    ("paper-gtrxl", {"network.embed_size": 6, "network.num_layers": 2, "network.num_heads": 2,
                     "network.head_size": 4, "network.memory_length": 4},
     {"embed/kernel": ("obs", 6), "layer_1/query/kernel": (6, 8), "layer_1/age_embedding": (5, 6),
      "ActorCriticHeads_0/mean/kernel": (6, 2)}),
])  # fmt: skip
def test_recurrent_ppo__the_shapes_and_log_std_it_names(preset, network, expect):
    cfg, trainer, state = trained(preset, **RECURRENT, **network, **{"network.init_log_std": -1.5})
    got = shapes(trainer.policy(state).params["params"])
    o = cfg.env.obs_dim
    for name, shape in expect.items():
        want = tuple(o + 5 if d == "obs+5" else o if d == "obs" else d for d in shape)
        assert got[name] == want, (name, got)
    assert not any(k.startswith(("lstm_3", "layer_2")) for k in got), "more layers than named"
    log_std = trainer.policy(state).params["params"]["ActorCriticHeads_0"]["log_std"]
    np.testing.assert_array_equal(log_std, [-1.5, -1.5])


# --------------------------------------------------------------------------- resolve
def test_resolve__writes_in_what_each_trainer_does_with_the_log_std():
    assert resolve_train({"preset": "paper-ppo"}).network.init_log_std == 0.0
    assert resolve_train({"preset": "paper-ppo"}).network.learned_log_std is False
    assert resolve_train({"preset": "paper-lstm"}).network.init_log_std == -0.5
    sac = resolve_train({"preset": "paper-sac"}).network
    assert (sac.learned_log_std, sac.init_log_std) == (True, None)
    td3 = resolve_train({"preset": "paper-td3"}).network
    assert (td3.learned_log_std, td3.init_log_std) == (None, None)
    assert resolve_sweep({"space": "ppo"}).base.network.init_log_std == 0.0


@pytest.mark.parametrize("preset,overrides,field,says", [
    ("paper-ppo", {"network.dropout": 0.5}, "network.dropout", "no trainer applies dropout"),
    ("paper-mlp", {"network.dropout": 0.2}, "network.dropout", "allowed: 0"),
    ("paper-ppo", {"network.learned_log_std": True}, "network.learned_log_std",
     "implementation='quicknav'"),
    ("paper-sac", {"network.learned_log_std": False}, "network.learned_log_std", "per state"),
    ("paper-sac", {"network.init_log_std": -1.0}, "network.init_log_std", "allowed: null"),
    ("paper-td3", {"network.init_log_std": -1.0}, "network.init_log_std", "deterministic"),
    ("paper-td3", {"network.learned_log_std": False}, "network.learned_log_std", "deterministic"),
])  # fmt: skip
def test_resolve__refuses_what_the_trainer_cannot_honour_naming_the_field(preset, overrides, field, says):
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": preset, "overrides": overrides})
    (item,) = e.value.items
    assert item["loc"] == ["overrides", field] and field in item["msg"] and says in item["msg"]


def test_resolve__a_sweep_base_is_checked_too():
    with pytest.raises(ConfigError) as e:
        resolve_sweep({"space": "ppo", "overrides": {"network.dropout": 0.3}})
    assert e.value.items[0]["loc"] == ["overrides", "network.dropout"]
    with pytest.raises(ConfigError, match="deterministic"):
        resolve_train({"config": {"algorithm": {"name": "td3"}, "network": {"kind": "mlp", "init_log_std": 0.0}}})
