import json
import re

import pytest
from pydantic import ValidationError

from quicknav_core.config import EnvConfig, apply_overrides, format_validation_error


def _error_text(**kwargs) -> str:
    with pytest.raises(ValidationError) as exc:
        EnvConfig(**kwargs)
    return format_validation_error(exc.value)


def test_config__defaults_match_the_paper():
    c = EnvConfig()
    assert (c.room_size, c.grid_size, c.carve_fraction, c.return_prob) == (8.0, 16, 0.8, 0.05)
    assert (c.robot_radius, c.max_wheel_speed, c.lidar_beams, c.lidar_fov_deg) == (
        0.15,
        1.0,
        16,
        360.0,
    )
    assert (c.lidar_max_range, c.goal_candidates, c.max_steps) == (10.0, 5, 300)
    r = c.reward
    assert (r.cycle_penalty, r.progress_reward, r.step_penalty, r.collision_penalty, r.goal_reward) == (
        0.0, 1.0, 0.1, 10.0, 50.0,
    )  # fmt: skip
    assert c.cell_size == 0.5


def test_config__json_round_trip():
    c = EnvConfig(grid_size=8, lidar_beams=4, reward={"goal_reward": 20.0, "progress": "linear"})
    again = EnvConfig.model_validate_json(c.model_dump_json())
    assert again == c
    assert json.loads(c.model_dump_json())["reward"]["progress"] == "linear"


@pytest.mark.parametrize(
    ("kwargs", "field", "allowed"),
    [
        ({"grid_size": 3}, "grid_size", "greater than or equal to 4"),
        ({"lidar_beams": 0}, "lidar_beams", "greater than or equal to 1"),
        ({"lidar_fov_deg": 400}, "lidar_fov_deg", "less than or equal to 360"),
        ({"return_prob": 1.0}, "return_prob", "less than 1"),
        ({"carve_fraction": 0.0}, "carve_fraction", "greater than 0"),
        (
            {"max_wheel_speed": 10.0},
            "max_wheel_speed*dt",
            "max_wheel_speed*dt <= room_size/grid_size",
        ),
        ({"carve_max_steps": 10}, "carve_max_steps", "carve_max_steps >= 157"),
        ({"reward": {"goal_reward": -1}}, "reward.goal_reward", "greater than or equal to 0"),
    ],
)
def test_config__bad_values_name_field_and_range(kwargs, field, allowed):
    text = _error_text(**kwargs)
    assert field in text
    assert allowed in text


def test_config__a_room_laid_as_grid_times_cell_gives_back_the_cell():
    # a map laid at a 0.1 m-cell policy's cells: room 48 x 0.1 m, and 4.8 / 48 reads
    # 0.09999999999999999, below the default step of exactly 0.1 m (it was refused), and a robot of
    # radius 0.2 m at 0.2 m cells reached two cells instead of one (a different compiled env)
    assert 4.8 / 48 < 0.1 == EnvConfig().max_wheel_speed * EnvConfig().dt
    assert EnvConfig(room_size=48 * 0.1, grid_size=48).cell_size == 0.1
    wide = {"robot_radius": 0.2, "room_size": 48 * 0.2, "grid_size": 48}
    assert 9.6 / 48 < 0.2 and EnvConfig(**wide).collision_reach == 1
    assert EnvConfig(**{**wide, "grid_size": 49}).cell_size == pytest.approx(9.6 / 49, rel=1e-12)
    assert "max_wheel_speed*dt" in _error_text(room_size=4.7, grid_size=48)


def test_config__unknown_field_rejected():
    assert "lidar_beam" in _error_text(lidar_beam=8)


def test_config__a_robot_wider_than_a_cell_is_a_config_not_an_error():
    # grid 64 in an 8 m room makes 0.125 m cells: the 0.3 m robot spans several, and drives where
    # it fits (tests/core/env/test_wide_robot.py); the config says how far its disc reaches
    assert EnvConfig(grid_size=64).collision_reach == 2
    assert EnvConfig().collision_reach == 0  # narrower than a cell: the four-cell test


def test_overrides__nested_and_typed():
    c = apply_overrides(EnvConfig(), ["grid_size=8", "reward.goal_reward=20", "observe_goal=false"])
    assert c.grid_size == 8 and c.reward.goal_reward == 20.0 and c.observe_goal is False


def test_overrides__unknown_key_is_named():
    with pytest.raises(ValueError, match="unknown field 'gird_size'"):
        apply_overrides(EnvConfig(), ["gird_size=8"])
    with pytest.raises(ValidationError, match="grid_size"):
        apply_overrides(EnvConfig(), ["grid_size=2"])


def test_config__carver_bad_value_names_field_and_allowed_values():
    text = _error_text(carver="fast")
    assert "carver" in text
    assert all(name in text for name in ("'auto'", "'paper'", "'centre'", "'carved'"))


@pytest.mark.parametrize(
    ("grid", "carver"),
    [(8, "paper"), (16, "paper"), (32, "centre"), (48, "carved"), (128, "carved")],
)
def test_config__auto_carver_keeps_the_paper_walk_where_it_is_quick(grid, carver):
    assert EnvConfig(grid_size=grid, room_size=grid * 0.5).resolved_carver == carver


def test_config__large_grid_accepted_with_auto_refused_with_centre_returns():
    # grid 48 at the default return_prob: refused before, now carved by returns to carved cells
    EnvConfig(grid_size=48, room_size=24.0)
    text = _error_text(grid_size=48, room_size=24.0, carver="paper")
    assert "carver='paper'" in text and "carve_max_steps (2,116,000)" in text
    assert "return_prob <= 0.0364" in text and "carver='carved'" in text
    EnvConfig(grid_size=48, room_size=24.0, carver="paper", return_prob=0.0364)  # the way out
    text = _error_text(grid_size=128, room_size=64.0, carver="centre")
    assert "carver='centre'" in text and "grid_size <=" in text


def test_config__carved_target_out_of_reach_of_the_step_cap_is_refused():
    base = {"grid_size": 64, "room_size": 32.0, "carver": "carved"}
    text = _error_text(**base, carve_max_steps=20_000)
    assert "carver='carved'" in text and "carve_max_steps (20,000)" in text
    # the ways out the message names are accepted
    cap = int(re.search(r"carve_max_steps >= ([\d,]+)", text).group(1).replace(",", ""))
    fraction = float(re.search(r"carve_fraction <= ([\d.]+)", text).group(1))
    EnvConfig(**base, carve_max_steps=cap)
    EnvConfig(**base, carve_max_steps=20_000, carve_fraction=fraction)
    assert "carve_max_steps" in _error_text(**base, carve_max_steps=cap - 1000)


def test_json_types__a_boolean_is_no_number_and_a_number_no_boolean():
    """What the schema says a field takes is what it takes: pydantic alone reads ``true`` as 1
    where a number is expected and ``0`` as False where a flag is (schemathesis found both in the
    API: ``"seed": false`` and ``"stochastic": 0`` were accepted)."""
    from quicknav_core.config import EnvConfig, TrainConfig
    from quicknav_core.config.resolve import EvalRequest

    with pytest.raises(ValidationError, match="seed: false is a boolean; a number is expected"):
        EvalRequest.model_validate({"policy": "oracle", "seed": False})
    with pytest.raises(ValidationError, match="grid_size: true is a boolean"):
        EnvConfig.model_validate({"grid_size": True})
    for flag in ({"observe_goal": 1}, {"end_on_collision": "yes"}):
        with pytest.raises(ValidationError, match="valid boolean"):
            EnvConfig.model_validate(flag)
    with pytest.raises(ValidationError, match="valid boolean"):
        EvalRequest.model_validate({"policy": "oracle", "stochastic": 0})
    # numbers stay numbers (an int where a float is expected), flags stay flags, and None is None
    env = EnvConfig.model_validate({"room_size": 8, "observe_goal": False, "carve_max_steps": None})
    assert env.room_size == 8.0 and env.observe_goal is False
    assert TrainConfig.model_validate({"algorithm": {"name": "ppo", "anneal_lr": False}}).algorithm.anneal_lr is False
    # the tags of the algorithm and network unions are required in the schema (the API refuses
    # a config without them), while Python keeps their defaults
    schema = TrainConfig.model_json_schema()["$defs"]
    assert all(schema[m]["required"][0] == "name" for m in ("PPOConfig", "SACConfig", "TD3Config"))
    assert all(schema[m]["required"][0] == "kind" for m in ("MLPNetwork", "LSTMNetwork", "GTrXLNetwork"))
