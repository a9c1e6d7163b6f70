"""docs/building.md's journey, walked from the page's own text: the building preset trained (the
test run's shorter training of the same preset stands in), evaluated on the shipped office map it
never saw with nothing but the map, exported with the map, and driven by the SDK's Navigator.

Its own module, so that the test run's one building training (1-3 minutes on 2 cores) runs
beside README's journeys rather than after them.
"""

from __future__ import annotations

import json

import pytest

from tests.journeys.readme import ROOT, Runner
from tests.journeys.test_readme_journeys import walk
from tests.service.conftest import free_port


@pytest.fixture
def runner(tmp_path):
    r = Runner(workdir=tmp_path, port=free_port(), grpc_port=free_port())
    yield r
    r.stop()


@pytest.mark.slow  # docs/building.md's journey with the test run's short building training: ~1-2 min
def test_journey__drive_a_building(runner, trained_building_run):
    """Train (the test run's shorter training of the same preset stands in), evaluate on the
    shipped office map it never saw with nothing but the map, export with the map, and drive one
    step of the exported policy with the SDK's Navigator (onnxruntime and SciPy, no JAX)."""
    from tests.trained import BUILDING_TEST_STEPS

    (runner.workdir / "examples").symlink_to(ROOT / "examples")  # the page's paths, from a checkout
    runner.trained["uv run quicknav train --preset building"] = trained_building_run
    ran = [r[2] for r in walk(runner, "building")]
    assert [r.code for r in ran] == [0] * 4, "\n\n".join(map(str, ran))
    _, evaluated, exported, navigated = ran
    # the grid and the step limit followed the map at the policy's 0.5 m cells
    result = json.loads((runner.workdir / "office" / "eval.json").read_text())
    env = result["env_config"]
    assert env["room_size"] / env["grid_size"] == 0.5 and env["grid_size"] >= 42, env
    # in the map's own shape (21.2 m x 13.2 m: 29 x 45 cells with the ring), not a square around it
    assert (env["grid_rows"], env["grid_size"], env["grid_cols"]) == (29, 45, None), env
    assert env["max_steps"] > 300 and f"step limit {env['max_steps']}" in evaluated.stdout, str(evaluated)
    # among the preset's own unmapped obstacles, and it says so (a figure with them is not one
    # without them)
    assert env["obstacles"]["static"] == 6 and env["obstacles"]["moving"] == 3, env["obstacles"]
    assert "up to 6 boxes and 3 people" in evaluated.stdout, str(evaluated)
    # the office's 1 m doors and 0.1 m walls lose free space at 0.5 m cells: said, with the share
    assert "free space" in evaluated.stderr and "%" in evaluated.stderr, str(evaluated)
    # a policy that learned. This short training's policy is early and its figures move with the
    # machine's arithmetic: 6.3M steps of the preset with a 10 m lidar reached 14 % and 26 % of
    # these goals on two 2-core VMs (return 47 on the first); with its 4 m lidar, 4.2M steps 22 %
    # (return 72) and 6.3M 51 %; reading two frames, 2.1M steps 20 % (return 64; the test run's
    # budget since 2026-11) and 4.2M 48 % (return 108). The untrained policy (of the 10 m preset)
    # reaches none of them and returns -132 (time-outs)
    m = result["metrics"]
    assert m["success_rate"] >= 0.03 and m["return"]["mean"] >= 0.0, (
        f"the building preset after {BUILDING_TEST_STEPS:,} steps reached {m['success_rate']:.0%}"
        f" of office goals, return {m['return']['mean']:.1f}")  # fmt: skip
    doc = json.loads((runner.workdir / "robot" / "policy.json").read_text())
    assert doc["map"]["cell_m"] == 0.5 and (runner.workdir / "robot" / doc["map"]["file"]).is_file(), doc["map"]
    assert doc["map"]["grid"] == [29, 45] and "on a grid of 29 x 45 cells" in " ".join(exported.stdout.split())
    left, right = (float(w.split()[1]) for w in navigated.stdout.split(";")[0].split(",")[:2])
    assert abs(left) <= 1.0 and abs(right) <= 1.0 and "reached: False" in navigated.stdout, str(navigated)
    # the robot's side, closed loop: the NumPy twin drives the exported policy through Navigator
    driven = drive_with_navigator(runner.workdir / "robot", env, episodes=40)
    assert driven["max_obs_error"] < 1e-4, driven  # Navigator's observation is the env's, every step
    # it drives along the plan: the untrained policy covers 3 % of the plan's length (20 episodes),
    # the 14 % policy 43 %
    assert driven["progress"] >= 0.2, driven


def drive_with_navigator(folder, env_config: dict, episodes: int) -> dict:
    """Office episodes driven by an exported policy through the SDK's ``Navigator`` (onnxruntime,
    SciPy's Dijkstra on ``map.npz``) in the NumPy twin, without unmapped obstacles, one episode at
    a time by ``benchmarks/navigator_parity.py``'s ``drive`` (the twin moves the robot and casts a
    walls-only lidar; the Navigator sees the scan, the map-frame pose and the goal; its observation
    is compared with the twin's own at every step; ``progress``: the share of the plan's length
    covered). Starts and goals: cell centres the robot fits at, 3 m or more apart."""
    import math

    import numpy as np
    from quicknav_client.navigate import Navigator

    from benchmarks.navigator_parity import drive
    from quicknav_core.config import EnvConfig
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv

    nav = Navigator.load(folder)
    cfg = EnvConfig(**{**env_config, "obstacles": None})
    twin = QuickNavNumpyEnv(cfg, split="test")
    cell = float(nav.frame["cell_m"])
    free = np.argwhere(nav.planner.usable)
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(episodes):
        while True:
            a, b = free[rng.integers(len(free), size=2)]
            start, goal = (a[::-1] + 0.5) * cell, (b[::-1] + 0.5) * cell
            if np.linalg.norm(start - goal) >= 3.0:
                break
        rows.append(drive(nav, twin, cfg, nav.planner.walls, start, rng.uniform(-math.pi, math.pi), goal))
    return {"success_rate": sum(r["success"] for r in rows) / episodes,
            "progress": sum(r["progress"] for r in rows) / episodes,
            "max_obs_error": max(r["max_obs_error"] for r in rows),
            "steps": sum(r["steps"] for r in rows)}  # fmt: skip


@pytest.mark.slow  # the test run's building policy, exported, driven by the Navigator: ~10 s
def test_navigator__the_learned_planner_replans_around_a_door_the_map_does_not_show(
    trained_building_run, tmp_path
):
    """The SDK's Navigator with the building policy (onnxruntime) in the NumPy twin: a ring
    corridor whose short way is closed by a wall the map does not show. Without re-planning the
    policy presses on at the door until the step limit (the plan runs through it, and it never
    met a wall across its plan in training); with the Navigator's default re-planning it goes the
    long way round and reaches every goal."""
    from quicknav_client.navigate import Navigator
    from quicknav_client.policy import OnnxPolicy

    from quicknav_core.config import EnvConfig
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv
    from quicknav_core.export import export_run
    from tests.clients.test_navigate import _drive, _ring_and_wall

    export_run(trained_building_run, tmp_path / "robot")
    policy = OnnxPolicy.load(tmp_path / "robot")
    # the policy's own env in the ring; contacts do not end the episode, so that the door holds it
    env = {**policy.manifest["env"], "rooms": "floorplan", "obstacles": None, "max_steps": 800,
           "end_on_collision": False}  # fmt: skip
    cfg = EnvConfig.model_validate(env)
    twin = QuickNavNumpyEnv(cfg, split="test")
    walls, world = _ring_and_wall()
    frame = {"cell_m": cfg.cell_size, "grid_corner_in_map": [0.0, 0.0]}
    trips = (((1.25, 5.25), (10.75, 5.25)), ((1.75, 4.25), (10.75, 4.75)), ((10.75, 5.25), (1.25, 5.25)))
    for start, goal in trips:
        stuck = Navigator(policy, walls, frame, replan_after_s=None)
        assert not _drive(stuck, twin, cfg, world, start, goal, 800), (start, goal)
        nav = Navigator(policy, walls, frame)  # re-planning after 5 s without progress
        reached = _drive(nav, twin, cfg, world, start, goal, 800)
        assert reached and nav.replans >= 1 and world[nav.blocked].all(), (start, goal, nav.replans)
