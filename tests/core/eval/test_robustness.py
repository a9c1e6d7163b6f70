"""``quicknav eval --robustness``: the same episodes at each fixed perturbation level."""

import json

import pytest
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import EnvConfig, EvalConfig, resolve_eval
from quicknav_core.eval import pictures
from quicknav_core.eval.evaluate import evaluate
from quicknav_core.eval.robustness import LEVELS, robustness_levels
from quicknav_core.eval.scripted import OracleAgent

ENV = EnvConfig(grid_size=8, lidar_beams=8, train_rooms=32, test_rooms=24, max_steps=80)


@pytest.fixture(scope="module")
def oracle_robustness(tmp_path_factory):
    out = tmp_path_factory.mktemp("robust")
    cfg = EvalConfig(policy="oracle", env=ENV, episodes=48, seed=3, gif_episodes=0, robustness=True)
    seen = []
    result, _ = evaluate(ENV, OracleAgent(ENV.room_size, ENV.goal_radius), cfg, out,
                         progress=lambda done, total: seen.append((done, total)))  # fmt: skip
    return result, out, seen


def test_robustness__one_row_per_level_on_the_same_episodes(oracle_robustness):
    result, out, seen = oracle_robustness
    rows = result["robustness"]
    assert [(r["perturbation"], r["level"]) for r in rows] == [(lv.perturbation, lv.level) for lv in LEVELS]
    by = {r["label"]: r for r in rows}
    plain = result["metrics"]
    # the unperturbed row is the plain evaluation: same rooms, starts and goals
    assert by["none"]["success_rate"] == plain["success_rate"] and by["none"]["spl"] == pytest.approx(plain["spl"])
    # the oracle plans from the map and never reads its lidar: sensor levels change nothing ...
    for label in ("lidar_noise 20 %", "beam_dropout 25 %", "lidar_bias 0.1 m"):
        assert by[label]["success_rate"] == by["none"]["success_rate"], label
        assert by[label]["mean_steps"] == by["none"]["mean_steps"], label
    # ... while its wheels obey the actuator levels: a delay makes it slower, then lose its way
    assert by["latency 1 steps"]["mean_steps"] > by["none"]["mean_steps"]
    assert by["latency 3 steps"]["success_rate"] < by["none"]["success_rate"] - 0.3
    assert by["wheel_asymmetry 20 %"]["mean_steps"] > by["none"]["mean_steps"]
    for r in rows:
        lo, hi = r["success_ci95"]
        assert 0.0 <= lo <= r["success_rate"] <= hi <= 1.0 and r["episodes"] == 48
    # progress counts the plain evaluation's episodes and every level's, to the end
    assert seen[-1] == (48 * (1 + len(LEVELS)),) * 2
    assert json.loads((out / "eval.json").read_text())["robustness"] == json.loads(json.dumps(rows))
    assert (out / "robustness.png").stat().st_size > 10_000 and result["warnings"] == []


def test_robustness__a_picture_that_fails_is_a_warning_and_the_rows_stay(monkeypatch, tmp_path):
    def broken(*args, **kwargs):
        raise RuntimeError("no fonts")

    monkeypatch.setattr(pictures, "draw_robustness", broken)
    cfg = EvalConfig(policy="oracle", env=ENV, episodes=8, seed=3, gif_episodes=0, robustness=True)
    result, _ = evaluate(ENV, OracleAgent(ENV.room_size, ENV.goal_radius), cfg, tmp_path)
    assert result["warnings"] == ["robustness.png was not drawn: RuntimeError: no fonts"]
    stored = json.loads((tmp_path / "eval.json").read_text())
    assert len(stored["robustness"]) == len(LEVELS) and stored["warnings"] == result["warnings"]
    assert not (tmp_path / "robustness.png").exists() and (tmp_path / "difficulty.png").exists()


def test_robustness__levels_replace_a_trained_envs_own_randomisation():
    trained = EnvConfig.model_validate({**ENV.model_dump(), "randomize": {"lidar_noise_frac": (0.0, 0.1)}})
    for level, env in robustness_levels(trained):
        r = env.randomize.model_dump()
        changed = {k: v for k, v in r.items() if v != type(env.randomize)().model_dump()[k]}
        assert changed == {k: tuple(v) for k, v in level.randomize.items()}, level.label


def test_robustness__every_door_passes_it_through():
    cfg = resolve_eval({"policy": "oracle", "robustness": True})
    assert cfg.robustness and not resolve_eval({"policy": "oracle"}).robustness
    printed = CliRunner().invoke(app, ["eval", "--policy", "oracle", "--robustness", "--print-config"])
    assert printed.exit_code == 0 and json.loads(printed.stdout)["robustness"] is True
    wrong = CliRunner().invoke(app, ["jobs", "submit", "train", "--robustness"])
    assert wrong.exit_code != 0 and "--robustness is for eval jobs" in wrong.output

    from quicknav_client.rest import core

    assert core.eval_body("abcd", None, 10, 0, None, robustness=True)["robustness"] is True
    assert "robustness" not in core.eval_body("abcd", None, 10, 0, None)
