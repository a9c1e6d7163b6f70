"""Evaluation metrics, the shortest-path planner against brute force, and the oracle baseline."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import EnvConfig, EvalConfig, TrainConfig
from quicknav_core.eval.evaluate import Episodes, evaluate, spl, summarize, wilson_interval
from quicknav_core.eval.planning import INF, goal_field, greedy_path, node_positions
from quicknav_core.eval.scripted import OracleAgent, RandomAgent
from quicknav_core.train import train_run
from tests.compile_settings import optimized
from tests.core.env.reference import disc_wall_clearance, grid_dijkstra


def _episodes(success, steps, path, ref, returns=None, collisions=None, truncated=None):
    n = len(success)
    z = np.zeros(n)
    return Episodes(
        success=np.array(success, bool), truncated=np.array(truncated or [not s for s in success]),
        steps=np.array(steps), returns=np.array(returns or z), collisions=np.array(collisions or z),
        path_length=np.array(path, float), reference_length=np.array(ref, float),
        trajectories=np.zeros((n, 2, 2)), walls=np.zeros((n, 4, 4), bool), goals=np.zeros((n, 2)),
        gif={},
    )  # fmt: skip


def test_spl_and_success__hand_made_episodes():
    # success with a detour (path twice the shortest), a perfect success, and a failure
    ep = _episodes([True, True, False], [40, 20, 300], [8.0, 2.0, 5.0], [4.0, 2.0, 3.0],
                   returns=[10.0, 20.0, -30.0], collisions=[1, 0, 5])  # fmt: skip
    assert spl(ep.success, ep.path_length, ep.reference_length) == pytest.approx(
        (0.5 + 1.0 + 0.0) / 3
    )
    m = summarize(ep, max_steps=300, step_length=0.1)
    assert m["success_rate"] == pytest.approx(2 / 3)
    assert m["steps_to_goal_successes"]["mean"] == 30 and m["steps_to_goal_successes"]["std"] == 10
    assert m["steps_to_goal_failures_as_limit"]["mean"] == pytest.approx((40 + 20 + 300) / 3)
    assert m["collisions_per_episode"] == 2 and m["timeout_rate"] == pytest.approx(1 / 3)
    # the first success touched a wall on the way: one of three reached the goal cleanly
    assert m["collision_free_success_rate"] == pytest.approx(1 / 3)
    assert m["return"]["mean"] == 0.0
    # a path shorter than the reference (a rounding artefact) never scores above 1
    assert spl(np.array([True]), np.array([1.9]), np.array([2.0])) == 1.0


def test_by_path_length__bins_the_episodes_by_the_oracle_path(tmp_path):
    from quicknav_core.eval.evaluate import by_path_length, draw_difficulty

    # room 8 m: bins 0-2, 2-4, 4-6, 6-8, >= 8 m of oracle path; nothing falls in 4-6
    ep = _episodes([True, False, True, True, False], [20, 300, 50, 90, 300],
                   [1.5, 2.0, 3.5, 7.0, 9.0], [1.0, 1.5, 3.0, 6.5, 8.5])  # fmt: skip
    rows = by_path_length(ep, room_size=8.0, max_steps=300)
    assert [r["path_m"] for r in rows] == [[0.0, 2.0], [2.0, 4.0], [6.0, 8.0], [8.0, None]]
    assert [r["episodes"] for r in rows] == [2, 1, 1, 1]
    assert [r["success_rate"] for r in rows] == [0.5, 1.0, 1.0, 0.0]
    assert rows[0]["steps_failures_as_limit"] == (20 + 300) / 2
    assert rows[0]["spl"] == pytest.approx(spl(np.array([True, False]), np.array([1.5, 2.0]),
                                               np.array([1.0, 1.5])))  # fmt: skip
    lo, hi = rows[0]["success_ci95"]
    assert lo < 0.5 < hi
    assert draw_difficulty(rows, tmp_path / "d.png").stat().st_size > 5000


def test_wilson_interval__known_values():
    lo, hi = wilson_interval(95, 100)
    assert lo == pytest.approx(0.8882, abs=1e-3) and hi == pytest.approx(0.9785, abs=1e-3)
    assert wilson_interval(0, 10)[0] == pytest.approx(0.0, abs=1e-12)
    assert wilson_interval(10, 10)[1] == pytest.approx(1.0)
    assert wilson_interval(10, 10)[0] == pytest.approx(0.7225, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_shortest_path__matches_brute_force_dijkstra_and_keeps_clearance(seed):
    cfg = EnvConfig(grid_size=8, train_rooms=8, room_seed=seed)
    env, params = cfg.build()
    _, state = env.reset(jax.random.PRNGKey(seed), params)
    k, r = 3, cfg.robot_radius
    field, usable = goal_field(state.row_bits, state.goal, cfg.room_size, r, k)
    field, usable = np.asarray(field), np.asarray(usable)
    # independent usable check: clearance against every wall cell
    walls = np.asarray(state.walls)
    nodes = np.asarray(node_positions(cfg.grid_size, cfg.room_size, k))
    clear = np.array([[disc_wall_clearance(p, walls, cfg.cell_size) for p in row] for row in nodes])
    assert (usable == (clear >= r)).all()
    # same seeds as the planner: the nodes around the goal, at their straight-line distance
    n, h = field.shape[0], cfg.room_size / field.shape[0]
    gr, gc = (np.floor(np.asarray(state.goal)[::-1] / h)).astype(int)
    seeds = {(rr, cc): float(np.linalg.norm(nodes[rr, cc] - np.asarray(state.goal)))
             for rr in range(gr - 1, gr + 2) for cc in range(gc - 1, gc + 2)}  # fmt: skip
    ref = grid_dijkstra(usable, seeds, h)
    reachable = np.isfinite(ref)
    assert reachable.sum() > 0.5 * usable.sum()
    np.testing.assert_allclose(field[reachable], ref[reachable], rtol=1e-5, atol=1e-4)
    assert (field[~reachable] >= INF / 2).all()
    # following the field from the start keeps the disc clear of every wall and reaches the goal
    start_node = tuple(int(v) for v in np.floor(np.asarray(state.pos)[::-1] / h))
    path = np.asarray(greedy_path(jnp.asarray(field), jnp.asarray(usable), start_node, 4 * n))
    for rr, cc in path:
        assert disc_wall_clearance(nodes[rr, cc], walls, cfg.cell_size) >= r - 1e-6
    assert field[path[-1][0], path[-1][1]] < 2 * h


@pytest.fixture(scope="module")
def baselines():
    cfg = EnvConfig(train_rooms=256, test_rooms=128)
    ecfg = EvalConfig(episodes=100, seed=5, pictures=False)
    # 100 episodes of each agent run far more than they compile: with every optimisation here and
    # in the replay test, the module's CPU fell from 27.9 to 18.2 s (2-core AMD EPYC VM)
    with optimized():
        oracle, _ = evaluate(cfg, OracleAgent(cfg.room_size, cfg.goal_radius), ecfg)
        random, _ = evaluate(cfg, RandomAgent(), ecfg)
    return cfg, oracle, random


def test_oracle__reaches_the_goal_well_inside_the_limit(baselines):
    cfg, oracle, _ = baselines
    m = oracle["metrics"]
    assert m["success_rate"] >= 0.98
    assert max(oracle["per_episode"]["steps"]) < 0.6 * cfg.max_steps
    # close to the physical limit, and SPL near 1
    assert m["steps_to_goal_successes"]["mean"] < 1.25 * m["steps_lower_bound"]["mean"]
    assert m["spl"] > 0.9
    assert m["collisions_per_episode"] < 0.5


def test_random__rarely_succeeds_on_the_same_episodes(baselines):
    _, oracle, random = baselines
    assert random["metrics"]["success_rate"] < 0.2
    # same seed, same episodes: identical reference lengths for both agents
    assert oracle["per_episode"]["reference_length"] == random["per_episode"]["reference_length"]


def test_eval__replay_json_holds_the_picture_episodes_step_by_step(baselines, tmp_path):
    from quicknav_core.env.numpy_env import cast_lidar_np

    cfg, oracle, _ = baselines
    with optimized():  # the baselines' settings: the same program, the same episodes to the bit
        result, ep = evaluate(cfg, OracleAgent(cfg.room_size, cfg.goal_radius),
                              EvalConfig(episodes=100, seed=5, pictures=False), out_dir=tmp_path)  # fmt: skip
    assert result["per_episode"] == oracle["per_episode"]
    bins = json.loads((tmp_path / "eval.json").read_text())["by_path_length"]
    assert sum(b["episodes"] for b in bins) == 100
    assert sum(b["success_rate"] * b["episodes"] for b in bins) == pytest.approx(
        sum(oracle["per_episode"]["success"]))
    replay = json.loads((tmp_path / "replay.json").read_text())
    assert len(replay["episodes"]) == 3 and replay["grid_size"] == cfg.grid_size
    angles = np.asarray(replay["beam_angles"], np.float32)
    for i, e in enumerate(replay["episodes"]):
        n = oracle["per_episode"]["steps"][i] + 1
        assert e["success"] == oracle["per_episode"]["success"][i] and len(e["x"]) == n
        assert e["outcome"] == ("reached" if e["success"] else "timed out"), e["outcome"]  # no end on collision
        assert e["walls"] == ["".join("#" if w else "." for w in row) for row in ep.walls[i]]
        np.testing.assert_allclose(np.c_[e["x"], e["y"]], ep.trajectories[i, :n], atol=6e-4)
        # the lidar of every 7th frame, cast again by the NumPy twin from the stored pose
        for t in range(0, n, 7):
            ranges, hits = cast_lidar_np(
                np.array([e["x"][t], e["y"][t]], np.float32), e["theta"][t],
                np.asarray(e["goal"], np.float32), ep.walls[i], angles, cfg.cell_size,
                cfg.lidar_max_range, cfg.goal_radius,
            )  # fmt: skip
            np.testing.assert_allclose(e["ranges"][t], ranges, atol=0.01)
            assert (np.asarray(e["hits"][t]) == hits).mean() >= 0.9  # rounding may flip a grazing beam


@pytest.mark.slow  # trains, then three CLI evaluations: ~50 s on 2 cores
def test_eval__run_folder_twice_gives_identical_results(tmp_path):
    cfg = TrainConfig.model_validate({
        "env": {"grid_size": 8, "train_rooms": 32, "test_rooms": 16, "max_steps": 60},
        "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
        "network": {"kind": "lstm", "num_layers": 1, "hidden_size": 8},
        "num_envs": 8, "total_steps": 256, "chunk_steps": 128,
    })  # fmt: skip
    train_run(cfg, tmp_path / "run")
    runner = CliRunner()
    for out in ("a", "b"):
        result = runner.invoke(app, ["eval", str(tmp_path / "run"), "--episodes", "12",
                                     "--out", str(tmp_path / out)])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert "success rate" in result.output
    a = json.loads((tmp_path / "a" / "eval.json").read_text())
    b = json.loads((tmp_path / "b" / "eval.json").read_text())
    assert a["per_episode"] == b["per_episode"] and a["metrics"] == b["metrics"]
    assert (tmp_path / "a" / "trajectories.png").exists() and (
        tmp_path / "a" / "episodes.gif"
    ).exists()
    # the checkpoint folder works too, and names the same policy (the same episodes' numbers; the
    # same episode count, so its program comes from the compilation cache)
    result = runner.invoke(app, ["eval", str(tmp_path / "run" / "checkpoint"), "--episodes", "12",
                                 "--out", str(tmp_path / "c")])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "c" / "eval.json").read_text())["per_episode"] == a["per_episode"]


@pytest.mark.slow  # compiles an evaluation and draws its GIF: ~20 s on 2 cores
def test_eval_cli__baseline_writes_results_and_pictures(tmp_path):
    result = CliRunner().invoke(app, ["eval", "--policy", "random", "--episodes", "8", "--set",
                                      "grid_size=8", "--out", str(tmp_path)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "return, mean ± std" in result.output  # the spread is named, not a bare ±
    assert json.loads((tmp_path / "eval.json").read_text())["metrics"]["episodes"] == 8
    assert (tmp_path / "trajectories.png").exists() and (tmp_path / "episodes.gif").exists()


def test_eval_cli__bad_input_fails_before_compiling(tmp_path):
    runner = CliRunner()
    assert runner.invoke(app, ["eval"]).exit_code == 2
    bad = runner.invoke(app, ["eval", "--policy", "smart"])
    assert bad.exit_code == 2 and "allowed values" in bad.output
    missing = runner.invoke(app, ["eval", str(tmp_path / "nope")])
    assert missing.exit_code == 2 and "not a run folder" in missing.output
