"""`quicknav_client.navigate`: the robot-side global plan (SciPy's Dijkstra) against the env's own
(the NumPy twin's Bellman-Ford, itself held to the JAX env), the map frame, and the refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from quicknav_client.navigate import GridPlanner, Navigator, disc_fits

from quicknav_core.config import EnvConfig
from quicknav_core.env import clearance
from quicknav_core.env.numpy_env import (
    QuickNavNumpyEnv,
    cell_field_np,
    plan_features_np,
    plan_waypoints_np,
)
from quicknav_core.eval.map_fit import fit_map

OFFICE = "examples/maps/office.yaml"
PLAN = dict(rooms="floorplan", grid_size=24, room_size=12.0, train_rooms=8, test_rooms=8,
            lidar_beams=8, observe_plan=True, observe_pose=False, observe_goal=False,
            plan_lookahead=2, plan_waypoints=3)  # fmt: skip


@pytest.mark.parametrize("radius", [0.15, 0.4])
def test_planner__inflation_field_and_features_are_the_twins(radius):
    cfg = EnvConfig(**PLAN, robot_radius=radius)
    twin = QuickNavNumpyEnv(cfg, split="test")
    rng = np.random.default_rng(0)
    compared = same = 0
    for episode in range(6):
        twin.reset(seed=episode)
        s = twin.snapshot()
        walls, cell = s["walls"], cfg.cell_size
        planner = GridPlanner(walls, cell, radius, cfg.plan_lookahead, cfg.plan_waypoints)
        usable = clearance.disc_fits(walls, cell, radius)
        np.testing.assert_array_equal(planner.usable, usable)
        field = planner.plan(s["goal"])
        goal_rc = tuple(np.floor(np.asarray(s["goal"])[::-1] / cell).astype(int))
        ref = cell_field_np(usable, goal_rc)
        reached = ref < 1e8
        np.testing.assert_allclose(field[reached], ref[reached], rtol=1e-5)
        assert (field[~reached] >= 1e8).all()
        # the observation's plan part at random poses in cells the disc fits
        rows, cols = np.nonzero(usable & reached)
        for k in rng.choice(rows.size, 40):
            pos = (np.array([cols[k], rows[k]]) + rng.uniform(0.2, 0.8, 2)) * cell
            theta = rng.uniform(-math.pi, math.pi)
            rc = (rows[k], cols[k])
            points = plan_waypoints_np(ref, usable, rc, s["goal"], cell, cfg.plan_lookahead,
                                       cfg.plan_waypoints)  # fmt: skip
            want = plan_features_np(pos.astype(np.float32), np.float32(theta), points, ref, rc, cell,
                                    cfg.plan_lookahead)  # fmt: skip
            got = planner.features((pos[0], pos[1], theta))
            compared += 1
            # equal-length paths: the two may descend different ones (rounding of the lengths)
            same += bool(np.allclose(got, want, atol=1e-5))
            assert got[-1] == pytest.approx(want[-1], abs=1e-5)  # the path left always agrees
    assert same >= 0.95 * compared, f"{same} of {compared} plan observations agree"


def test_disc_fits__is_the_envs_inflation():
    rng = np.random.default_rng(1)
    walls = rng.random((20, 20)) < 0.2
    for radius in (0.1, 0.3, 0.55, 1.2):
        np.testing.assert_array_equal(disc_fits(walls, 0.5, radius), clearance.disc_fits(walls, 0.5, radius))


class StandIn:
    """The OnnxPolicy surface a Navigator uses, answering with its observation's length."""

    def __init__(self, env: EnvConfig):
        from quicknav_client.policy import Observer

        from quicknav_core.env.constants import beam_angles
        from quicknav_core.export import observation_layout

        self.manifest = {"env": env.model_dump(mode="json"),
                         "observation": {"size": env.obs_dim, "layout": observation_layout(env)},
                         "lidar": {"beam_angles_rad": [float(a) for a in beam_angles(env.lidar_beams, 360.0)],
                                   "fov_deg": 360.0, "max_range_m": env.lidar_max_range}}  # fmt: skip
        self.observer = Observer(self.manifest)
        self.resets = 0

    def reset(self):
        self.resets += 1

    def observation(self, scan, pose, goal=None, plan=None):
        return self.observer(scan, pose, goal, plan)

    def act_on(self, obs):
        return float(obs.size), 0.0


def test_navigator__map_frame_poses_and_the_refusals():
    env = EnvConfig(**{**PLAN, "lidar_beams": 16})
    fit = fit_map(env, OFFICE)
    frame = {"cell_m": fit.cell_m, "grid_corner_in_map": list(fit.grid_corner_in_map)}
    nav = Navigator(StandIn(env), fit.walls, frame)
    ox, oy = fit.grid_corner_in_map
    free_r, free_c = np.nonzero(nav.planner.usable)
    start = ((free_c[0] + 0.5) * fit.cell_m + ox, (free_r[0] + 0.5) * fit.cell_m + oy)
    goal = ((free_c[-1] + 0.5) * fit.cell_m + ox, (free_r[-1] + 0.5) * fit.cell_m + oy)
    with pytest.raises(ValueError, match="no goal: call set_goal"):
        nav.act(np.full(16, 3.0), (*start, 0.0))
    # the policy alone, without its plan, names what gives it (names the SDK has)
    import quicknav_client.navigate as navigate

    with pytest.raises(ValueError, match=r"give plan= the plan's features \(quicknav_client\.navigate\."
                                         r"GridPlanner\.features\), or drive it with quicknav_client\."
                                         r"navigate\.Navigator"):  # fmt: skip
        nav.policy.observer(np.full(16, 3.0), (*start, 0.0))
    assert callable(navigate.GridPlanner.features) and callable(navigate.Navigator)
    nav.set_goal(goal)
    assert nav.policy.resets == 1
    left, _ = nav.act(np.full(16, 3.0), (*start, 0.0))
    assert left == env.obs_dim
    # the plan seen from the map frame is the planner's in the grid frame
    obs = nav.observation(np.full(16, 3.0), (*start, 0.3))
    grid_pose = (start[0] - ox, start[1] - oy, 0.3)
    np.testing.assert_allclose(obs[-(2 * env.plan_waypoints + 1):], nav.planner.features(grid_pose))
    assert nav.planner.path_length_m(*grid_pose[:2]) > 5.0
    # refusals name the point in the map frame the robot gave, and the map's extent there
    rows, cols = fit.walls.shape
    extent = (rf"its grid spans x {ox:g} to {ox + cols * fit.cell_m:g} m and y {oy:g} to"
              rf" {oy + rows * fit.cell_m:g} m in the map frame")  # fmt: skip
    with pytest.raises(ValueError, match=rf"pose \({ox - 3.0:.2f}, {oy:.2f}\) m lies outside the map: {extent}"):
        nav.act(np.full(16, 3.0), (ox - 3.0, oy, 0.0))
    with pytest.raises(ValueError, match=rf"goal \({ox:.2f}, {oy + 100:.2f}\) m lies outside the map: {extent}"):
        nav.set_goal((ox, oy + 100.0))
    # a failed localisation's NaN is named, never driven on
    with pytest.raises(ValueError, match=r"pose: \(nan, .*\): give 3 finite numbers \(x, y, yaw\) in the map frame"):
        nav.act(np.full(16, 3.0), (float("nan"), start[1], 0.0))
    with pytest.raises(ValueError, match=r"pose: .*: give 3 finite numbers"):
        nav.act(np.full(16, 3.0), (*start, float("inf")))
    with pytest.raises(ValueError, match=r"goal: \(nan, nan\): give 2 finite numbers"):
        nav.set_goal((float("nan"), float("nan")))
    wall_r, wall_c = np.nonzero(fit.walls[1:-1, 1:-1])
    in_wall = ((wall_c[0] + 1.5) * fit.cell_m + ox, (wall_r[0] + 1.5) * fit.cell_m + oy)
    with pytest.raises(ValueError, match="lies in a wall cell of the map"):
        nav.act(np.full(16, 3.0), (*in_wall, 0.0))
    with pytest.raises(ValueError, match=rf"goal \({in_wall[0]:.2f}, {in_wall[1]:.2f}\) m in the map frame:"
                                         " the robot does not fit there"):  # fmt: skip
        nav.set_goal(in_wall)


def test_map_fit__grid_step_limit_and_frame_follow_the_map():
    env = EnvConfig(**PLAN)
    fit = fit_map(env, OFFICE)
    assert fit.cell_m == env.cell_size == 0.5
    assert fit.grid_corner_in_map == (fit.origin[0] - 0.5, fit.origin[1] - 0.5)
    # the step limit covers the longest shortest path twice over at full speed
    assert fit.max_steps >= 2 * fit.longest_path_m / (env.max_wheel_speed * env.dt)
    again = EnvConfig.model_validate({**env.model_dump(), **fit.env_overrides(OFFICE)})
    assert again.grid_size == fit.grid_size and again.room_size == pytest.approx(fit.room_size)
    from quicknav_core.env.maps import MapError

    with pytest.raises(MapError, match=r"a grid of \d+, above the 256 an env may have.*cells of at least"):
        fit_map(EnvConfig(**{**PLAN, "room_size": 1.8, "max_wheel_speed": 0.7}), OFFICE)  # 0.075 m cells


def test_eval_map__lies_over_a_config_env_and_under_set(tmp_path):
    """`quicknav eval --policy dwa --config ENV.json --map MAP`: the map replaces the config's
    rooms, grid and step limit (a baseline measured on the map, not on the config's floor plans);
    --set still wins over both."""
    import json

    from typer.testing import CliRunner

    from quicknav_cli.main import app

    (tmp_path / "env.json").write_text(json.dumps({**PLAN, "lidar_beams": 16}))
    r = CliRunner().invoke(app, ["eval", "--policy", "dwa", "--config", str(tmp_path / "env.json"),
                                 "--map", OFFICE, "--set", "max_steps=900", "--print-config"])  # fmt: skip
    assert r.exit_code == 0, r.output
    env = json.loads(r.stdout)["env"]  # --print-config prints the JSON alone
    assert env["rooms"] == "maps" and env["maps"]["train"] == [OFFICE], env
    assert env["grid_size"] == fit_map(EnvConfig(**PLAN), OFFICE).grid_size and env["lidar_beams"] == 16
    assert env["max_steps"] == 900
    # a baseline's cell size from --set: the map is laid at it, the grid follows the map
    r = CliRunner().invoke(app, ["eval", "--policy", "oracle", "--map", OFFICE, "--set", "room_size=4",
                                 "--set", "env.grid_size=16", "--print-config"])  # fmt: skip
    assert r.exit_code == 0, r.output
    env = json.loads(r.stdout)["env"]
    fine = fit_map(EnvConfig(room_size=4.0, grid_size=16), OFFICE)  # 0.25 m cells
    assert env["grid_size"] == fine.grid_size > 64 and env["room_size"] == pytest.approx(fine.room_size)


def test_eval_map__a_plain_image_read_at_the_scale_set_and_only_the_map_named(tmp_path):
    """`quicknav eval --map IMAGE --set maps.resolution=...`: a plain image's scale (and how its
    pixels read) is set with the map, as the error asking for it says; a policy trained on maps
    with held-out ones is evaluated on the map named, never on its own held-out maps; the map's
    lists are the request's map alone, and a bad reading field is named."""
    import json

    from typer.testing import CliRunner

    from quicknav_cli.main import app
    from quicknav_core.env.maps import load_map

    image = tmp_path / "office.pgm"
    image.write_bytes((Path(OFFICE).parent / "office.pgm").read_bytes())
    run = lambda *a: CliRunner().invoke(app, ["eval", "--policy", "oracle", *a])  # noqa: E731
    asked = run("--map", str(image), "--print-config")
    assert asked.exit_code == 2 and "set maps.resolution (metres per pixel)" in asked.output, asked.output
    r = run("--map", str(image), "--set", "maps.resolution=0.05", "--print-config")
    assert r.exit_code == 0, r.output
    env = json.loads(r.stdout)["env"]
    assert env["maps"]["train"] == [str(image)] and env["maps"]["resolution"] == 0.05, env["maps"]
    # laid as the map_server pair with the same scale is: the same grid
    assert env["grid_size"] == fit_map(EnvConfig(), OFFICE).grid_size, env["grid_size"]
    assert load_map(image, resolution=0.05).blocked.shape == load_map(OFFICE).blocked.shape
    # a policy's env on maps with held-out ones: only the map named, read as the policy reads maps
    held_out = {**PLAN, "rooms": "maps", "maps": {"train": [OFFICE], "test": ["elsewhere.yaml"],
                                                 "unknown": "free"}}  # fmt: skip
    (tmp_path / "env.json").write_text(json.dumps(held_out))
    r = run("--config", str(tmp_path / "env.json"), "--map", OFFICE, "--print-config")
    assert r.exit_code == 0, r.output
    maps = json.loads(r.stdout)["env"]["maps"]
    assert maps["train"] == [OFFICE] and maps["test"] is None and maps["unknown"] == "free", maps
    bad = run("--map", str(image), "--set", "maps.resolution=-1")
    assert bad.exit_code == 2 and "env.maps.resolution: Input should be greater than 0" in bad.output, bad.output
    both = run("--map", str(image), "--set", "maps.test=[a.yaml]")
    assert both.exit_code == 2 and "env.maps.test: the map evaluated on is the request's map" in both.output


def test_eval_map__written_beside_the_held_out_evaluation_not_over_it(tmp_path):
    """Without --out, `quicknav eval RUN --map MAP` writes RUN/eval-MAP (and --split train,
    --stochastic, --shield or --set K=V: RUN/eval-train, RUN/eval-stochastic, RUN/eval-shield,
    RUN/eval-K=V): RUN/eval keeps the held-out evaluation that `quicknav export` reads as the
    policy's held-out success."""
    from quicknav_cli.eval import default_out

    run = tmp_path / "runs" / "building-s0"
    assert default_out(run, None, None) == run / "eval"
    assert default_out(run, None, Path("examples/maps/office.yaml")) == run / "eval-office"
    assert default_out(None, "oracle", None) == Path("eval") / "oracle"
    assert default_out(None, "dwa", Path("depot.yaml")) == Path("eval") / "dwa-depot"
    # the training rooms, or acting stochastically: beside it too
    assert default_out(run, None, None, split="train") == run / "eval-train"
    assert default_out(run, None, None, deterministic=False) == run / "eval-stochastic"
    assert default_out(run, None, Path("office.yaml"), "train", False) == run / "eval-office-train-stochastic"
    # through the safety layer, or in an env --set changed: beside it too, named by what changed
    assert default_out(run, None, None, shield=True) == run / "eval-shield"
    assert default_out(run, None, None, sets={"lidar_fov_deg": 270, "obstacles": None}) == run / (
        "eval-lidar_fov_deg=270-obstacles=null")
    assert default_out(None, "oracle", None, sets={"rooms": "floorplan"}) == Path("eval") / "oracle-rooms=floorplan"
    # a map's reading is part of its name; a long list is cut and told apart by a digest
    assert default_out(run, None, Path("a.png"), sets={"maps.resolution": 0.05}) == run / "eval-a"
    long = default_out(run, None, None, sets={f"reward.term_{i}": 1.5 for i in range(8)}).name
    assert len(long) <= 70 and long != default_out(run, None, None, sets={"reward.term_0": 2}).name
    assert "/" not in default_out(run, None, None, sets={"maps.names": ["x/y"]}).name


class Pursuit(StandIn):
    """A stand-in policy that steers at the plan's first waypoint (no learning): what the
    Navigator's re-planning gives it is what it drives."""

    def act_on(self, obs):
        env = self.manifest["env"]
        w = env["plan_waypoints"]
        fwd, left = (float(v) for v in obs[-(2 * w + 1) : -(2 * w - 1)])
        angle = math.atan2(left, fwd)
        speed = env["max_wheel_speed"]
        v = 0.6 * speed * max(math.cos(angle), 0.0)
        turn = 1.5 * angle * env["wheel_base"] / 2
        return (float(np.clip(v - turn, -speed, speed)), float(np.clip(v + turn, -speed, speed)))


def _ring_and_wall():
    """A ring corridor round a block (the map), the short way round (the top) closed by a wall
    the map does not show (the world)."""
    walls = np.ones((24, 24), bool)
    walls[1:23, 1:23] = False
    walls[7:18, 4:20] = True  # the block: the top corridor (rows 1-6) is the shorter way
    world = walls.copy()
    world[1:7, 12] = True  # a closed door across the top corridor
    return walls, world


def _drive(nav, twin, cfg, world, start, goal, steps):
    from quicknav_core.env.constants import HIT_NONE
    from quicknav_core.env.numpy_env import cast_lidar_np

    angles = np.asarray(nav.policy.manifest["lidar"]["beam_angles_rad"], np.float32)
    twin.load(world, np.asarray(start, np.float32), 0.0, np.asarray(goal, np.float32))
    nav.set_goal(goal)  # the grid's corner is the map frame's origin here
    for _ in range(steps):
        s = twin.snapshot()
        ranges, hits = cast_lidar_np(s["pos"], s["theta"], np.full(2, -1e4, np.float32), s["walls"],
                                     angles, cfg.cell_size, cfg.lidar_max_range, cfg.goal_radius)  # fmt: skip
        pose = (float(s["pos"][0]), float(s["pos"][1]), float(s["theta"]))
        left, right = nav.act(np.where(hits == HIT_NONE, np.inf, ranges), pose)
        _, _, terminated, truncated, info = twin.step(np.array([left, right]) / cfg.max_wheel_speed)
        if terminated or truncated:
            return bool(info["goal_reached"])
    return False


def test_navigator__replans_around_a_closed_door_the_map_does_not_show():
    """In the NumPy twin, a wall closes the plan's way; a plan follower is stuck there for good
    without re-planning, and with it the Navigator marks what the lidar sees, plans the long way
    round and reaches the goal. A new goal drops the marks."""
    cfg = EnvConfig(**{**PLAN, "lidar_beams": 32, "lidar_max_range": 4.0, "max_steps": 800})
    twin = QuickNavNumpyEnv(cfg, split="test")
    walls, world = _ring_and_wall()
    frame = {"cell_m": cfg.cell_size, "grid_corner_in_map": [0.0, 0.0]}
    start, goal = (1.25, 5.25), (10.75, 5.25)  # left and right of the block, the top way shorter
    stuck = Navigator(Pursuit(cfg), walls, frame, replan_after_s=None)
    assert not _drive(stuck, twin, cfg, world, start, goal, 800)
    assert stuck.replans == 0 and twin.snapshot()["pos"][0] < 6.0  # it stays at the door
    # (pressed against the door, its 32 beams see a few of the door's cells at a time: it marks
    # them, tries the plan left, and after a re-plan or two the long way round is the plan)
    nav = Navigator(Pursuit(cfg), walls, frame, replan_after_s=2.0)
    assert _drive(nav, twin, cfg, world, start, goal, 800)
    assert nav.replans >= 1 and nav.blocked[1:7, 12].sum() >= 3, nav.blocked.sum()
    assert world[nav.blocked].all()  # every mark lies on the door, none in free space
    nav.set_goal(start)
    assert nav.blocked_cells == 0 and nav.replans == 0


def test_navigator__replan_refusals_and_a_walled_in_robot_keeps_the_map_plan():
    cfg = EnvConfig(**{**PLAN, "lidar_beams": 16})
    walls, _ = _ring_and_wall()
    frame = {"cell_m": cfg.cell_size, "grid_corner_in_map": [0.0, 0.0]}
    with pytest.raises(ValueError, match=r"replan_after_s=0: allowed: > 0 seconds, or None"):
        Navigator(StandIn(cfg), walls, frame, replan_after_s=0)
    with pytest.raises(ValueError, match=r"mark_range_m=-1: allowed: > 0 metres"):
        Navigator(StandIn(cfg), walls, frame, mark_range_m=-1)
    nav = Navigator(StandIn(cfg), walls, frame)
    nav.set_goal((10.75, 5.25))
    before = nav.planner.field.copy()
    # a 360-reading scan with returns all round at 1.2 m: every way out closed, so the marks go
    # and the map's plan stays
    ring = {"angle_min": -math.pi, "angle_increment": math.pi / 180, "ranges": [1.2] * 360}
    assert not nav.replan(ring, (1.25, 5.25, 0.0))
    assert nav.blocked_cells == 0 and nav.replans == 0
    np.testing.assert_array_equal(nav.planner.field, before)


def test_navigator__the_safety_layer_stops_a_plan_follower_short_of_a_door_the_map_does_not_show():
    """The plan follower presses against the closed door every step without the safety layer; with
    ``shield=True`` it stops short of it and never touches it, turning in place at most (the
    NumPy twin counts the contacts; no re-planning, so the door holds it either way)."""
    from quicknav_core.env.constants import HIT_NONE
    from quicknav_core.env.numpy_env import cast_lidar_np

    cfg = EnvConfig(**{**PLAN, "lidar_beams": 32, "lidar_max_range": 4.0, "max_steps": 300})
    walls, world = _ring_and_wall()
    frame = {"cell_m": cfg.cell_size, "grid_corner_in_map": [0.0, 0.0]}
    with pytest.raises(ValueError, match="allowed"):
        Navigator(Pursuit(cfg), walls, frame, mark_range_m=0, shield=True)
    contacts = {}
    for shield in (False, True):
        twin = QuickNavNumpyEnv(cfg, split="test")
        nav = Navigator(Pursuit(cfg), walls, frame, replan_after_s=None, shield=shield)
        angles = np.asarray(nav.policy.manifest["lidar"]["beam_angles_rad"], np.float32)
        start, goal = (2.0, 2.0), (10.75, 5.25)  # in the top corridor, the door ahead
        twin.load(world, np.asarray(start, np.float32), 0.0, np.asarray(goal, np.float32))
        nav.set_goal(goal)
        touched = 0
        for _ in range(200):
            s = twin.snapshot()
            ranges, hits = cast_lidar_np(s["pos"], s["theta"], np.full(2, -1e4, np.float32), s["walls"],
                                         angles, cfg.cell_size, cfg.lidar_max_range, cfg.goal_radius)  # fmt: skip
            pose = (float(s["pos"][0]), float(s["pos"][1]), float(s["theta"]))
            left, right = nav.act(np.where(hits == HIT_NONE, np.inf, ranges), pose)
            *_, info = twin.step(np.array([left, right]) / cfg.max_wheel_speed)
            touched += bool(info["collision"])
        contacts[shield] = (touched, nav.shielded, float(twin.snapshot()["pos"][0]))
    assert contacts[False][0] >= 100 and contacts[False][1] == 0, contacts  # pressed on the door
    assert contacts[True][0] == 0 and contacts[True][1] >= 100, contacts  # stopped every step
    assert 4.5 < contacts[True][2] < 6.0, contacts  # at the door, not turned back
