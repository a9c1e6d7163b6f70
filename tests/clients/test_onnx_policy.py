"""`quicknav_client.policy`: an exported policy driven as a robot drives it, without JAX.

The observation a robot's scan, pose and goal become is held to the NumPy twin's own (the goal
drawn into a walls-only scan as the simulator's lidar reports it); the resampler onto the
policy's beams is checked return by return; and (slow) a trained demo policy, exported, drives the
twin through the same 100 held-out episodes as `quicknav eval` in a process where importing JAX
fails, at the policy's own beams and from a 360-beam scan.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from quicknav_client.policy import LaserScan, Observer, resample

from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import beam_angles
from quicknav_core.env.numpy_env import QuickNavNumpyEnv, cast_lidar_np

FAR = np.array([1e6, 1e6], np.float32)  # a goal no beam meets: the scan a real lidar gives


def manifest_of(env: EnvConfig) -> dict:
    """The manifest fields the observer reads, as ``quicknav export`` writes them."""
    angles = [float(a) for a in beam_angles(env.lidar_beams, env.lidar_fov_deg)]
    from quicknav_core.export import observation_layout

    return {"env": env.model_dump(mode="json"),
            "observation": {"size": env.obs_dim, "layout": observation_layout(env)},
            "lidar": {"beam_angles_rad": angles, "fov_deg": env.lidar_fov_deg,
                      "max_range_m": env.lidar_max_range}}  # fmt: skip


def walls_only_scan(twin: QuickNavNumpyEnv, angles: np.ndarray) -> np.ndarray:
    s, c = twin.snapshot(), twin.config
    ranges, hits = cast_lidar_np(s["pos"], s["theta"], FAR, s["walls"], angles, c.room_size / c.grid_size,
                                 c.lidar_max_range, c.goal_radius)  # fmt: skip
    return np.where(hits == 0, np.inf, ranges)  # no return: inf, as a LaserScan says it


@pytest.mark.parametrize("fov", [360.0, 270.0])
def test_observer__a_robots_scan_pose_and_goal_become_the_twins_observation(fov):
    env = EnvConfig(grid_size=8, train_rooms=8, test_rooms=8, lidar_beams=16, lidar_fov_deg=fov)
    twin = QuickNavNumpyEnv(env, split="test")
    observe = Observer(manifest_of(env))
    rng = np.random.default_rng(0)
    goal_beams = 0
    for episode in range(6):
        obs, _ = twin.reset(seed=episode)
        for _ in range(60):
            s = twin.snapshot()
            scan = walls_only_scan(twin, np.asarray(observe.beam_angles))
            built = observe(scan, (s["pos"][0], s["pos"][1], s["theta"]), s["goal"])
            np.testing.assert_allclose(built, obs, atol=2e-5)
            goal_beams += int(obs[4 + 2 * 16:4 + 3 * 16].sum())
            obs, _, term, trunc, _ = twin.step(rng.uniform(-1, 1, 2).astype(np.float32))
            if term or trunc:
                break
    assert goal_beams > 0, "no beam ever met the goal: the goal drawing was not exercised"


def test_resample__the_valid_return_closest_to_each_beams_direction():
    angles = beam_angles(4, 360.0)  # 0, 90, 180, 270 degrees; sectors 90 degrees wide
    ranges = np.full(360, 5.0)
    ranges[10] = 2.0  # in beam 0's sector, 10 degrees off its direction: not what the beam sees
    ranges[90] = np.nan  # beam 1's own direction: no return ...
    ranges[89], ranges[91] = 1.5, 1.0  # ... so the two returns 1 degree off; as close: the shorter
    ranges[180] = 0.01  # below range_min: no return
    ranges[179], ranges[181] = np.inf, 3.0  # no return; the one valid return 1 degree off
    ranges[227:316] = np.inf  # beam 3's sector (225-315) without a valid return near the beam ...
    ranges[226] = 4.0  # ... but 44 degrees off, inside the sector (225 is farther)
    scan = LaserScan(angle_min=0.0, angle_increment=math.radians(1), ranges=ranges, range_min=0.05,
                     range_max=8.0)  # fmt: skip
    got = resample(scan, angles, 360.0, 10.0)
    np.testing.assert_allclose(got, [5.0, 1.0, 3.0, 4.0])
    # across the wrap: beam 0's closest valid returns lie at -1 and +2 degrees
    wrapped = ranges.copy()
    wrapped[0], wrapped[1], wrapped[359], wrapped[2] = np.nan, np.nan, 3.0, 0.5
    np.testing.assert_allclose(resample(LaserScan(0.0, math.radians(1), wrapped, 0.05, 8.0), angles,
                                        360.0, 10.0)[0], 3.0)  # fmt: skip
    # a sector without any valid return: no return (inf), which the observer turns into max range
    beam3 = ranges.copy()
    beam3[223:227] = np.inf
    assert np.isinf(resample(LaserScan(0.0, math.radians(1), beam3, 0.05, 8.0), angles, 360.0, 10.0)[3])
    # a mapping with a LaserScan's fields (a ROS message converted to a dict) reads the same
    as_dict = {"angle_min": 0.0, "angle_increment": math.radians(1), "ranges": list(ranges),
               "range_min": 0.05, "range_max": 8.0}  # fmt: skip
    np.testing.assert_allclose(resample(as_dict, angles, 360.0, 10.0), got)
    # every return of a sector missing: no return (inf), which the observer turns into max range
    empty = LaserScan(angle_min=0.0, angle_increment=math.radians(1), ranges=np.full(360, np.inf))
    assert np.isinf(resample(empty, angles, 360.0, 10.0)).all()
    # ranges at the policy's own beams pass through
    np.testing.assert_allclose(resample(np.array([1.0, 2.0, 3.0, 4.0]), angles, 360.0, 10.0), [1, 2, 3, 4])
    # a 270-degree scanner (-135..135) leaves the rear beam of a 360-degree policy unseen: refused,
    # never read as open space; a policy trained for 270 degrees takes the same scan
    hokuyo = LaserScan(angle_min=math.radians(-135), angle_increment=math.radians(0.25),
                       ranges=np.full(1081, 4.0), range_min=0.05, range_max=30.0)  # fmt: skip
    with pytest.raises(ValueError, match=r"covers -135 to 135 degrees; 1 of the policy's 4 beams \(at 180"
                                         r" degrees\).*trained for a 360-degree lidar.*"
                                         r"lidar_fov_deg=270, this scan's field of view"):  # fmt: skip
        resample(hokuyo, angles, 360.0, 10.0)
    np.testing.assert_allclose(resample(hokuyo, beam_angles(4, 270.0), 270.0, 10.0), [4.0] * 4)
    # as wide as the policy's 270 degrees but centred behind the robot (the scanner's frame, not
    # base_link): said so, rather than asking for another scanner
    backwards = LaserScan(angle_min=math.radians(45), angle_increment=math.radians(0.25),
                          ranges=np.full(1081, 4.0), range_min=0.05, range_max=30.0)  # fmt: skip
    with pytest.raises(ValueError, match=r"sweeps 270 degrees, as wide as the policy's 270, but centred at"
                                         r" -180 degrees, not on the robot's heading: give it in the"
                                         r" robot's frame"):  # fmt: skip
        resample(backwards, beam_angles(8, 270.0), 270.0, 10.0)
    with pytest.raises(ValueError, match="3 ranges given as an array; the policy has 4 beams"):
        resample(np.ones(3), angles, 360.0, 10.0)
    with pytest.raises(ValueError, match="needs angle_min, angle_increment and ranges"):
        resample({"ranges": [1.0]}, angles, 360.0, 10.0)


def test_observer__says_when_the_goal_is_missing():
    env = EnvConfig(grid_size=8, train_rooms=8, test_rooms=8)
    with pytest.raises(ValueError, match=r"goal: this policy observes its goal; give goal=\(x, y\)"):
        Observer(manifest_of(env))(np.ones(env.lidar_beams), (1.0, 1.0, 0.0))


def test_observer__a_pose_or_goal_it_cannot_read_is_an_error_never_an_action():
    """A NaN pose (a failed tf lookup), a goal outside the room the policy reads positions in, or
    a scan whose angles say nothing: refused, naming what is wrong, instead of wheel speeds (the
    demo policy drove NaN wheel speeds from a NaN pose, and full reverse towards a goal 300 m off)."""
    env = EnvConfig(grid_size=8, train_rooms=8, test_rooms=8, lidar_beams=8)  # an 8 m room
    observe = Observer(manifest_of(env))
    scan = np.full(8, 2.0)
    with pytest.raises(ValueError, match=r"pose: \(nan, 1.0, 0.0\): give 3 finite numbers \(x, y, yaw\)"):
        observe(scan, (float("nan"), 1.0, 0.0), (3.0, 3.0))
    with pytest.raises(ValueError, match=r"pose: \(1.0, 1.0\): give 3 finite numbers"):
        observe(scan, (1.0, 1.0), (3.0, 3.0))
    with pytest.raises(ValueError, match=r"goal: 'far' is not 2 numbers \(x, y\) in metres"):
        observe(scan, (1.0, 1.0, 0.0), "far")
    with pytest.raises(ValueError, match=r"goal: \(300, 3\) is outside the room this policy was"
                                         r" trained in \(0 to 8 m on each axis"):
        observe(scan, (1.0, 1.0, 0.0), (300.0, 3.0))
    with pytest.raises(ValueError, match=r"pose: \(-2, 1\) is outside the room"):
        observe(scan, (-2.0, 1.0, 0.0), (3.0, 3.0))
    still = LaserScan(angle_min=0.0, angle_increment=0.0, ranges=[2.0] * 8)
    with pytest.raises(ValueError, match="angle_increment non-zero"):
        observe(still, (1.0, 1.0, 0.0), (3.0, 3.0))
    # the room's edges are inside it
    assert observe(scan, (8.0, 0.0, 0.0), (0.0, 8.0)).shape == (env.obs_dim,)


def test_observer__a_return_beyond_the_policys_range_is_no_return():
    """A scanner that sees farther than the policy was trained to read (the building preset reads
    4 m): what lies beyond is no return, as in training, and what lies within is read as is."""
    env = EnvConfig(grid_size=8, train_rooms=8, test_rooms=8, lidar_beams=8, lidar_max_range=4.0)
    observe = Observer(manifest_of(env))
    scan = LaserScan(angle_min=0.0, angle_increment=math.radians(45), range_max=30.0,
                     ranges=[6.0, 3.0, 4.0, 25.0, 1.0, 4.5, np.inf, 2.0])  # fmt: skip
    obs = observe(scan, (1.0, 1.0, 0.0), (7.0, 7.0))  # 8.5 m away: beyond every beam's 4 m
    ranges, wall = obs[4:12], obs[12:20]  # the layout's ranges / max range, then the wall flags
    np.testing.assert_allclose(ranges, [1.0, 0.75, 1.0, 1.0, 0.25, 1.0, 1.0, 0.5])
    np.testing.assert_array_equal(wall, [0, 1, 1, 0, 1, 0, 0, 1])


# --------------------------------------------------------------------------- the journey, no JAX
NO_JAX_DRIVER = textwrap.dedent('''
    import json, math, sys

    class NoJax:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("jax", "jaxlib", "flax", "optax", "rejax"):
                raise ImportError(f"{name} is blocked in this process")

    sys.meta_path.insert(0, NoJax())
    import numpy as np
    from quicknav_client.policy import LaserScan, OnnxPolicy
    from quicknav_core.config.env import EnvConfig
    from quicknav_core.env.constants import beam_angles
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv, cast_lidar_np

    folder, episodes_file, beams = sys.argv[1], sys.argv[2], int(sys.argv[3])
    policy = OnnxPolicy.load(folder)
    env = EnvConfig.model_validate(policy.manifest["env"])
    twin = QuickNavNumpyEnv(env, split="test")
    data = np.load(episodes_file)
    angles = beam_angles(beams, 360.0)
    far = np.array([1e6, 1e6], np.float32)
    successes = []
    for walls, pos, theta, goal in zip(data["walls"], data["pos"], data["theta"], data["goal"]):
        twin.load(walls, pos, float(theta), goal)
        policy.reset()
        done = success = False
        while not done:
            s = twin.snapshot()
            r, hits = cast_lidar_np(s["pos"], s["theta"], far, s["walls"], angles,
                                    env.room_size / env.grid_size, env.lidar_max_range, env.goal_radius)
            scan = LaserScan(angle_min=0.0, angle_increment=2 * math.pi / beams,
                             ranges=np.where(hits == 0, np.inf, r), range_max=env.lidar_max_range)
            left, right = policy.act(scan, (s["pos"][0], s["pos"][1], s["theta"]), s["goal"])
            action = np.array([left, right], np.float32) / policy.max_wheel_speed
            _, _, success, truncated, _ = twin.step(action)
            done = success or truncated
        successes.append(bool(success))
    print(json.dumps({"success": float(np.mean(successes)), "jax_loaded": "jax" in sys.modules}))
''')


@pytest.mark.slow  # evaluates the test run's trained demo, drives 2 x 100 episodes without JAX: ~1 min
def test_onnx_policy__drives_the_held_out_episodes_without_jax(tmp_path, trained_demo_run):
    import jax

    from quicknav_core.config import EvalConfig, TrainConfig
    from quicknav_core.eval.evaluate import run_eval
    from quicknav_core.layout import RunFolder

    run_dir = RunFolder(trained_demo_run)  # trained once per test run, its policy exported
    cfg = TrainConfig.model_validate_json(run_dir.config.read_text())
    eval_cfg = EvalConfig(policy="trained", source=str(run_dir.path), env=cfg.env, episodes=100,
                          seed=0, gif_episodes=0, pictures=False)  # fmt: skip
    result, _ = run_eval(eval_cfg, None, run_dir=run_dir.path)
    jax_success = result["metrics"]["success_rate"]
    assert jax_success >= 0.9, f"the demo policy did not learn: {jax_success}"
    shutil.copytree(run_dir.path, tmp_path / "policy")  # policy.onnx + policy.json, as exported
    # the very episodes `quicknav eval` ran: episode i starts from reset(fold_in(PRNGKey(0), i))
    env, params = cfg.env.build("test")
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(0), i))(np.arange(100))
    _, states = jax.vmap(env.reset, (0, None))(keys, params)
    np.savez(tmp_path / "episodes.npz", walls=np.asarray(states.walls), pos=np.asarray(states.pos),
             theta=np.asarray(states.theta), goal=np.asarray(states.goal))  # fmt: skip
    driven = {}
    for beams in (cfg.env.lidar_beams, 360):
        done = subprocess.run([sys.executable, "-c", NO_JAX_DRIVER, str(tmp_path / "policy"),
                               str(tmp_path / "episodes.npz"), str(beams)],
                              capture_output=True, text=True, timeout=900)  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        out = json.loads(done.stdout.strip().splitlines()[-1])
        assert out["jax_loaded"] is False
        driven[beams] = out["success"]
    print(f"held-out success: JAX policy {jax_success:.2f}; OnnxPolicy without JAX, by beams: {driven}")
    assert abs(driven[cfg.env.lidar_beams] - jax_success) <= 0.02, (jax_success, driven)
    # A 360-beam scan reaches the policy resampled: each beam takes the return closest to its
    # direction, half a degree off at most here, so it drives as it did in training
    assert driven[360] >= jax_success - 0.05, (jax_success, driven)
