"""Sweeps: both storages, resume without repeats, batched == one at a time, space validation."""

import json

import jax
import numpy as np
import optuna
import pytest
import redis
from pydantic import ValidationError
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import (
    ConfigError,
    SweepConfig,
    TrainConfig,
    apply_overrides,
    resolve_sweep,
)
from quicknav_core.sweep import run_sweep
from quicknav_core.train.batched import train_batch

REDIS_URL = "redis://127.0.0.1:6379/13"  # this suite's own DB index

BASE = {
    "env": {"grid_size": 8, "train_rooms": 32, "test_rooms": 16, "max_steps": 40},
    "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
    "network": {"kind": "lstm", "num_layers": 1, "hidden_size": 8},
    "num_envs": 8, "total_steps": 256, "chunk_steps": 128,
}  # fmt: skip
SPACE = {
    "algorithm.learning_rate": {"type": "log_float", "low": 1e-4, "high": 1e-2},
    "env.reward.step_penalty": {"type": "float", "low": 0.01, "high": 0.5},
}


def tiny_sweep(**kw) -> SweepConfig:
    data = {"base": BASE, "space": SPACE, "trials": 3, "parallel": 2, "eval_episodes": 4,
            "objective": "return"}  # fmt: skip
    data.update(kw)
    return SweepConfig.model_validate(data)


def _finished(study):
    return [t for t in study.get_trials() if t.state.is_finished()]


@pytest.mark.slow  # two sweeps of 3 and 5 trials: ~40 s on 2 cores
def test_sweep__sqlite_completes_writes_outputs_and_resumes(tmp_path):
    summary = run_sweep(tiny_sweep(), tmp_path)
    assert summary["trials"] == 3 and summary["best_value"] is not None
    for name in ("best_params.json", "best_config.json", "trials.csv", "optimization_history.png",
                 "parallel_coordinate.png", "study.db"):  # fmt: skip
        assert (tmp_path / name).exists(), name
    best_cfg = TrainConfig.model_validate_json((tmp_path / "best_config.json").read_text())
    assert (
        best_cfg.algorithm.learning_rate
        == json.loads((tmp_path / "best_params.json").read_text())["params"][
            "algorithm.learning_rate"
        ]
    )
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    # trials.json (what the browser's sweep page reads) agrees with the study itself
    listed = json.loads((tmp_path / "trials.json").read_text())
    assert listed["direction"] == "maximize" and listed["objective"] == "return"  # as tiny_sweep asks
    study = optuna.load_study(study_name="quicknav", storage=storage)
    assert [(t["number"], t["state"], t["value"], t["params"]) for t in listed["trials"]] == [
        (t.number, t.state.name, t.value, t.params) for t in study.trials
    ]
    before = {
        t.number: (t.params, t.value)
        for t in optuna.load_study(study_name="quicknav", storage=storage).trials
    }
    # an interrupted run leaves a trial RUNNING: the next run fails it (with the study kept) and goes on
    study = optuna.load_study(study_name="quicknav", storage=storage)
    study.ask()
    run_sweep(tiny_sweep(trials=5), tmp_path)
    study = optuna.load_study(study_name="quicknav", storage=storage)
    after = {t.number: (t.params, t.value) for t in study.trials}
    for number, record in before.items():
        assert after[number] == record, "finished trials are not repeated or changed"
    states = [t.state for t in study.trials]
    assert states.count(optuna.trial.TrialState.FAIL) == 1
    assert len(_finished(study)) >= 5


def test_sweep__redis_journal_storage_is_shared(tmp_path):
    client = redis.Redis.from_url(REDIS_URL)
    client.ping()  # no Redis here is a failure, not a skip
    client.flushdb()
    try:
        # groups of 2 trials throughout: one compiled program (shared with the CLI test's sweep)
        cfg = tiny_sweep(storage=REDIS_URL, study_name="redis-test", trials=2)
        summary = run_sweep(cfg, tmp_path / "a")
        assert summary["trials"] == 2
        # a second "worker" sees the same study and continues it
        run_sweep(cfg.model_copy(update={"trials": 4}), tmp_path / "b")
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalRedisBackend

        study = optuna.load_study(
            study_name="redis-test", storage=JournalStorage(JournalRedisBackend(REDIS_URL))
        )
        assert len(_finished(study)) == 4
    finally:
        client.flushdb()


# the recurrent path also trains batched in the fast sweep tests; its equality check is slow
@pytest.mark.parametrize("network", [pytest.param("lstm", marks=pytest.mark.slow), "mlp"])
def test_batched_trials_equal_one_at_a_time(network):
    base = TrainConfig.model_validate(
        BASE if network == "lstm" else {**BASE, "network": {"kind": "mlp", "hidden_sizes": [16]}}
    )
    configs = [apply_overrides(base, {"algorithm.learning_rate": lr, "env.reward.step_penalty": sp})
               for lr, sp in ((3e-3, 0.05), (1e-3, 0.3))]  # fmt: skip
    _, batched, _, hist_b = train_batch(configs)
    for i, cfg in enumerate(configs):
        trainer, alone, _, hist_a = train_batch([cfg])
        pb = trainer.policy(batched[i]).params
        pa = trainer.policy(alone[0]).params
        for x, y in zip(jax.tree.leaves(pb), jax.tree.leaves(pa), strict=True):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-5)
        assert hist_b[-1][i]["episodes"] == hist_a[-1][0]["episodes"]
    # and the two trials really differ
    p0, p1 = (jax.tree.leaves(trainer.policy(b).params) for b in batched)
    assert not all(np.allclose(x, y) for x, y in zip(p0, p1, strict=True))


@pytest.mark.parametrize(
    ("space", "message"),
    [
        (
            {"algorithm.learning_rate": {"type": "float", "low": 0.1, "high": 0.01}},
            "low=0.1 > high=0.01",
        ),
        ({"algorithm.num_steps": {"type": "categorical", "choices": []}}, "non-empty 'choices'"),
        (
            {"algorithm.learnin_rate": {"type": "float", "low": 0.1, "high": 0.2}},
            "unknown parameter 'algorithm.learnin_rate'",
        ),
        (
            {"algorithm.learning_rate": {"type": "log_float", "low": 0.0, "high": 0.1}},
            "log_float needs low > 0",
        ),
        ({"x": {"type": "float", "low": 0.1}}, "needs 'low' and 'high'"),
    ],
)
def test_invalid_search_spaces_are_rejected(space, message):
    with pytest.raises(ValidationError, match=message.replace("(", r"\(").replace(")", r"\)")):
        SweepConfig.model_validate({"base": BASE, "space": space})


def test_builtin_spaces_match_the_paper():
    cfg = resolve_sweep({"space": "ppo"})
    s = cfg.space
    assert (s["algorithm.learning_rate"].low, s["algorithm.learning_rate"].high) == (1e-5, 1e-3)
    assert s["algorithm.num_minibatches"].choices == [16, 32, 64, 128, 256]
    assert s["algorithm.num_steps"].choices == [64, 128, 256, 512]
    assert (s["algorithm.gamma"].low, s["algorithm.gamma"].high) == (0.9, 0.999)
    lstm = resolve_sweep({"space": "lstm"}).space
    assert (lstm["env.reward.cycle_penalty"].low, lstm["env.reward.cycle_penalty"].high) == (
        0.001,
        0.5,
    )
    mlp = resolve_sweep({"space": "mlp"})
    widened = apply_overrides(mlp.base, {"network.hidden_layers": 3, "network.hidden_size": 64})
    assert widened.network.hidden_sizes == (64, 64, 64)
    with pytest.raises(ConfigError, match="space"):
        resolve_sweep({"space": "dqn"})


def test_cli_sweep__config_file(tmp_path):
    path = tmp_path / "sweep.json"
    path.write_text(tiny_sweep(trials=2).model_dump_json())
    result = CliRunner().invoke(
        app, ["sweep", "--config", str(path), "--out", str(tmp_path / "out")]
    )
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "trials.csv").exists()
    bad = CliRunner().invoke(app, ["sweep", "--preset", "dqn"])
    assert bad.exit_code == 2 and "allowed values" in bad.output


def test_objective__collision_free_success_ranks_a_wall_sliding_trial_below_a_clean_one():
    """`collision_free_success` reads the eval's collision_free_success_rate and is maximised: a
    trial that reaches more goals by sliding along the walls loses to one that touches nothing,
    where success_rate would rank them the other way round."""
    from quicknav_core.sweep import objective_value

    cfg = tiny_sweep(objective="collision_free_success")
    assert cfg.resolved_direction == "maximize"
    sliding = {"success_rate": 0.94, "collision_free_success_rate": 0.72}
    clean = {"success_rate": 0.90, "collision_free_success_rate": 0.88}
    assert objective_value(sliding, "success_rate") > objective_value(clean, "success_rate")
    assert objective_value(sliding, cfg.objective) < objective_value(clean, cfg.objective)
    with pytest.raises(ValidationError, match="collision_free_success"):
        tiny_sweep(objective="clean")  # the error lists the objectives, the new one among them
