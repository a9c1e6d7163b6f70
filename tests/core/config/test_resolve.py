"""The one path from a request to a config: overrides, resolve, and the traced-number contract."""

from __future__ import annotations

import dataclasses

import pytest
from pydantic import ValidationError

from quicknav_core.config import (
    ConfigError,
    EnvConfig,
    OverrideError,
    PPOConfig,
    RewardConfig,
    TrainConfig,
    apply_overrides,
    get_preset,
    parse_assignments,
    resolve_eval,
    resolve_sweep,
    resolve_train,
    traced_fields,
)
from quicknav_core.config.sweep import BUILTIN_TOTAL_STEPS
from quicknav_core.config.train import with_trainer_defaults


# --------------------------------------------------------------------------- overrides
def test_overrides__dotted_keys_typed_values_and_sections():
    cfg = apply_overrides(TrainConfig(), {
        "env.grid_size": 8, "env.reward": {"goal_reward": 20, "progress": "linear"},
        "algorithm.learning_rate": 1e-3, "seed": 4,
    })  # fmt: skip
    assert cfg.env.grid_size == 8 and cfg.env.reward.goal_reward == 20.0
    assert cfg.env.reward.progress == "linear" and cfg.env.reward.step_penalty == 0.1  # merged
    assert cfg.algorithm.learning_rate == 1e-3 and cfg.seed == 4
    # the CLI's strings become the same dict
    assert parse_assignments(["env.grid_size=8", "observe_goal=false", "name=x=y"]) == {
        "env.grid_size": 8, "observe_goal": False, "name": "x=y"}  # fmt: skip


def test_overrides__another_variant_starts_from_its_defaults():
    demo = get_preset("demo")  # PPO, MLP 64x64
    sac = apply_overrides(demo, {"algorithm.name": "sac", "algorithm.batch_size": 64})
    assert sac.algorithm.name == "sac" and sac.algorithm.batch_size == 64
    assert sac.algorithm.learning_rate == 3e-4, "SAC's default, not the PPO preset's 1e-3"
    same = apply_overrides(demo, {"algorithm.name": "ppo"})
    assert same.algorithm == demo.algorithm, "naming the same variant keeps its values"
    lstm = apply_overrides(demo, {"network": {"kind": "lstm", "hidden_size": 8}})
    assert lstm.network.kind == "lstm" and lstm.network.hidden_size == 8
    wide = apply_overrides(demo, {"network.hidden_layers": 3, "network.hidden_size": 32})
    assert wide.network.hidden_sizes == (32, 32, 32)


def test_overrides__unknown_keys_and_bad_values_are_named():
    with pytest.raises(OverrideError, match="unknown field 'gird_size' in env; did you mean 'grid_size'\\? known: rooms, floorplan, maps, room_size"):
        apply_overrides(TrainConfig(), {"env.gird_size": 8})
    with pytest.raises(OverrideError, match="'seed' has no sub-fields"):
        apply_overrides(TrainConfig(), {"seed.x": 1})
    with pytest.raises(ValidationError, match="grid_size"):
        apply_overrides(EnvConfig(), {"grid_size": 2})
    with pytest.raises(ValidationError, match="finite number"):
        apply_overrides(TrainConfig(), {"algorithm.learning_rate": float("nan")})


# --------------------------------------------------------------------------- resolve
def test_resolve_train__preset_or_config_then_overrides():
    cfg = resolve_train({"preset": "paper-ppo", "overrides": {"total_steps": 524288, "seed": 2}})
    expected = get_preset("paper-ppo").model_copy(update={"total_steps": 524288, "seed": 2})
    assert cfg == with_trainer_defaults(expected)  # what the preset leaves to rejax's PPO, written in
    assert cfg.network.init_log_std == 0.0
    from_config = resolve_train({"config": cfg.model_dump(mode="json"),
                                 "overrides": {"env.grid_size": 8}})  # fmt: skip
    assert from_config.env.grid_size == 8 and from_config.total_steps == 524288


@pytest.mark.parametrize(
    ("request_", "loc", "text"),
    [
        ({"preset": "nope"}, ["preset"], "unknown preset 'nope'; known: demo"),
        ({"preset": "demo", "overrides": {"num_envs": 0}}, ["overrides", "num_envs"], "greater than"),
        ({"preset": "demo", "overrides": {"algorithm.num_minibatches": 7, "seed": 1}},
         ["overrides", "algorithm.num_minibatches"], "must divide"),
        ({"config": {"num_envs": 0}}, ["config", "num_envs"], "greater than"),
        ({"preset": "demo", "config": {}}, [], "exactly one of"),
    ],
)  # fmt: skip
def test_resolve_train__errors_name_the_request_field(request_, loc, text):
    with pytest.raises(ConfigError) as e:
        resolve_train(request_)
    item = e.value.items[0]
    assert item["loc"] == loc and text in item["msg"], e.value.items


def test_resolve_sweep__space_defaults_shorthands_and_routing():
    cfg = resolve_sweep({"space": "ppo"})
    assert cfg.base.total_steps == BUILTIN_TOTAL_STEPS and cfg.study_name == "ppo"
    assert cfg.trials == 20 and cfg.space["algorithm.gamma"].high == 0.999
    cfg = resolve_sweep({"space": "lstm", "trials": 4, "total_steps": 262144, "overrides": {
        "env.grid_size": 8, "base.seed": 3, "objective": "spl", "eval_episodes": 10}})  # fmt: skip
    assert (cfg.trials, cfg.base.total_steps, cfg.base.env.grid_size, cfg.base.seed) == (
        4, 262144, 8, 3)  # fmt: skip
    assert cfg.objective == "spl" and cfg.eval_episodes == 10
    with pytest.raises(ConfigError) as e:
        resolve_sweep({"space": "ppo", "total_steps": 1})
    assert e.value.items[0]["loc"] == ["total_steps"] and "less than one update" in str(e.value)
    with pytest.raises(ConfigError) as e:
        resolve_sweep({"space": "ppo", "overrides": {"env.nope": 1}})
    assert e.value.items[0]["loc"] == ["overrides", "env.nope"]


def test_resolve_eval__baseline_env_trained_env_and_the_old_names():
    cfg = resolve_eval({"policy": "oracle", "env": {"grid_size": 8}, "seed": 3})
    assert cfg.policy == "oracle" and cfg.env == EnvConfig(grid_size=8) and cfg.seed == 3
    trained = EnvConfig(grid_size=8, lidar_beams=8, observe_goal=False)
    lookups = []

    def env_of(source):
        lookups.append(source)
        return trained

    for key in ("source", "job_id", "run"):
        cfg = resolve_eval({key: "abc", "env": {"max_steps": 50}, "split": "train"}, env_of)
        assert cfg.policy == "trained" and cfg.source == "abc" and cfg.split == "train"
        assert cfg.env == trained.model_copy(update={"max_steps": 50})
    assert lookups == ["abc"] * 3
    with pytest.raises(ConfigError, match="keep lidar_beams and observe_goal"):
        resolve_eval({"job_id": "abc", "env": {"lidar_beams": 16}}, env_of)
    # `stochastic` is the old opposite of `deterministic`
    assert resolve_eval({"policy": "random", "stochastic": True}).deterministic is False
    with pytest.raises(ConfigError, match="contradicts"):
        resolve_eval({"policy": "random", "stochastic": True, "deterministic": True})


def test_resolve__every_field_error_of_a_request_at_once():
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": "demo", "overrides": {
            "env.gird_size": 8, "env.grid_size": 1000, "num_envs": -5}})  # fmt: skip
    by_loc = {tuple(i["loc"]): i["msg"] for i in e.value.items}
    assert set(by_loc) == {("overrides", "env.gird_size"), ("overrides", "env.grid_size"),
                           ("overrides", "num_envs")}  # fmt: skip
    assert "less than or equal to 256" in by_loc[("overrides", "env.grid_size")]
    assert "greater than or equal to 1" in by_loc[("overrides", "num_envs")]
    with pytest.raises(ConfigError) as e:
        resolve_sweep({"space": "ppo", "overrides": {"trials": 0, "objectiv": "spl",
                                                     "env.grid_size": 2}})  # fmt: skip
    assert {tuple(i["loc"]) for i in e.value.items} == {
        ("overrides", "trials"), ("overrides", "objectiv"), ("overrides", "env.grid_size")}  # fmt: skip


@pytest.mark.parametrize(
    ("request_", "loc"),
    [
        ({"preset": "demo", "overrides": {"env": {"grid_size": 1000}}},
         ["overrides", "env", "grid_size"]),
        ({"preset": "demo", "overrides": {"env": {"reward": {"goal_reward": -1}}}},
         ["overrides", "env", "reward", "goal_reward"]),
        ({"config": {"env": {"grid_size": 1000}}}, ["config", "env", "grid_size"]),
    ],
)  # fmt: skip
def test_resolve__a_nested_section_error_names_the_field_not_the_section(request_, loc):
    with pytest.raises(ConfigError) as e:
        resolve_train(request_)
    assert [i["loc"] for i in e.value.items] == [loc]


def test_resolve__unknown_keys_say_what_was_meant():
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": "demo", "total_steps": 100000})
    (item,) = e.value.items
    assert item["loc"] == ["total_steps"]
    assert item["msg"] == ("unknown field 'total_steps': training settings go in overrides:"
                           ' {"overrides": {"total_steps": ...}}')  # fmt: skip
    with pytest.raises(ConfigError, match="did you mean 'overrides'"):
        resolve_train({"preset": "demo", "overides": {}})
    with pytest.raises(ConfigError, match="did you mean 'learning_rate'"):
        resolve_train({"preset": "demo", "overrides": {"algorithm.learning_rat": 1e-3}})
    with pytest.raises(ConfigError, match=r"in config\.algorithm; did you mean 'batch_size'"):
        resolve_train({"config": {"algorithm": {"name": "sac", "batch_sizes": 3}}})
    with pytest.raises(ConfigError, match="sweep settings go in overrides"):
        resolve_sweep({"space": "ppo", "objective": "spl"})
    # a name nothing resembles: no guess, the known names
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": "demo", "overrides": {"zzzz": 1}})
    assert "did you mean" not in str(e.value) and "known: env, algorithm" in str(e.value)
    # a field set one level too high (or in the wrong section): the path where it is, exactly,
    # before any lookalike ('goal_reward' looks like env.goal_radius, and is env.reward's)
    for key, meant in (("lidar_fov_deg", "env.lidar_fov_deg"), ("learning_rate", "algorithm.learning_rate"),
                       ("env.goal_reward", "env.reward.goal_reward")):  # fmt: skip
        with pytest.raises(ConfigError, match=rf"unknown field .*; did you mean '{meant}'\? known:"):
            resolve_train({"preset": "demo", "overrides": {key: 1}})
    # a preset's typo, wherever a preset is named
    with pytest.raises(ConfigError, match=r"unknown preset 'buildin'; did you mean 'building'\? known: demo"):
        resolve_train({"preset": "buildin"})
    with pytest.raises(ConfigError, match=r"base: unknown preset 'paperppo'; did you mean 'paper-ppo'\?"):
        resolve_sweep({"space": "ppo", "base": "paperppo"})


# --------------------------------------------------------------------------- traced numbers
def test_traced_fields__are_exactly_what_batched_training_varies():
    from quicknav_core.config import EnvConfig
    from quicknav_core.env.quicknav import traced_numbers
    from quicknav_core.env.types import EnvParams
    from quicknav_core.train.recurrent_ppo import PPOHyper

    hyper = {f.name for f in dataclasses.fields(PPOHyper)}
    assert hyper == traced_fields(PPOConfig), "PPOHyper must hold every traced PPO number"
    numbers = traced_numbers(EnvConfig())
    bank = {"rooms", "room_col_bits", "room_row_bits", "free_cells", "num_free", "room_col_window",
            "room_row_window"}  # fmt: skip
    pool = {f.name for f in dataclasses.fields(EnvParams) if f.name.startswith("pool_")}
    # every number of EnvParams comes from a field marked traced (none from a hand-kept list)
    assert set(numbers) == {f.name for f in dataclasses.fields(EnvParams)} - bank - pool
    # every traced number really changes the params: no field is silently dropped
    changed = traced_numbers(EnvConfig(
        room_size=9.0, robot_radius=0.2, max_wheel_speed=0.9, wheel_base=0.4, dt=0.11,
        lidar_max_range=5.0, goal_radius=0.25, max_steps=200,
        reward=RewardConfig(step_penalty=0.3, collision_penalty=1, cycle_penalty=2,
                            progress_reward=0.5, goal_reward=5, cycle_cap=3, exploration_reward=1,
                            progress="linear", potential_gamma=0.9,
                            proximity_penalty=1.0, proximity_m=0.3),
        randomize={"beam_dropout": [0.0, 0.1]}, obstacles={"static": 2}))  # fmt: skip
    sections = ("randomize", "obstacles")  # their ranges, when the config has the section
    assert all(changed[k] != numbers[k] for k in numbers if k not in sections)
    assert all(numbers[k] is None and changed[k] is not None for k in sections)
