import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import HIT_GOAL, HIT_NONE, HIT_WALL, beam_angles
from quicknav_core.env.lidar import cast_lidar
from quicknav_core.env.numpy_env import cast_lidar_np
from quicknav_core.env.room_sources import make_room_bank
from tests.core.env.reference import brute_force_lidar, disc_wall_clearance

cast_batch = jax.jit(
    jax.vmap(cast_lidar, in_axes=(0, 0, 0, 0, None, None, None, None, None, None, None)),
    static_argnums=(4, 5, 9, 10),
)
METHODS = ["crossings", "dda"]


def _random_poses(rooms, cell, radius, rng, per_room):
    """Random robot poses with clearance >= radius from walls, and goals at free cell centres."""
    g = rooms.shape[1]
    out = []
    for walls in rooms:
        free = np.argwhere(~walls)
        for _ in range(per_room):
            while True:
                r, c = free[rng.integers(len(free))]
                pos = (np.array([c, r]) + rng.uniform(0, 1, 2)) * cell
                if disc_wall_clearance(pos, walls, cell) >= radius:
                    break
            gr, gc = free[rng.integers(len(free))]
            goal = (np.array([gc, gr]) + 0.5) * cell
            out.append((walls, pos, rng.uniform(-np.pi, np.pi), goal))
    assert g == rooms.shape[2]
    return out


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    ("grid", "beams", "fov", "max_range"),
    [
        (16, 16, 360.0, 10.0),
        (8, 7, 120.0, 3.0),
        (32, 33, 270.0, 10.0),
        (40, 12, 360.0, 2.0),
        (64, 15, 270.0, 1.5),
    ],  # 40, 64: carved with return_prob 0.02 below; their range is a window of the grid's lines
)
def test_lidar__matches_brute_force(grid, beams, fov, max_range, method):
    cfg = EnvConfig(
        grid_size=grid, lidar_beams=beams, lidar_fov_deg=fov, lidar_max_range=max_range,
        robot_radius=min(0.15, 0.45 * 8.0 / grid), train_rooms=40,
        return_prob=0.05 if grid < 40 else 0.02,
    )  # fmt: skip
    rooms = make_room_bank(cfg, "train")
    rng = np.random.default_rng(grid)
    poses = _random_poses(rooms, cfg.cell_size, cfg.robot_radius, rng, per_room=10)
    walls = np.stack([p[0] for p in poses])
    pos = np.stack([p[1] for p in poses]).astype(np.float32)
    theta = np.array([p[2] for p in poses], np.float32)
    goal = np.stack([p[3] for p in poses]).astype(np.float32)
    angles = beam_angles(beams, fov)
    lines = cfg.lidar_lines  # what the env passes: the lines within range, or the whole grid
    assert (lines < grid - 1) == (grid >= 40), lines
    ranges, hits = cast_batch(
        pos, theta, goal, walls, beams, fov, cfg.cell_size, max_range, cfg.goal_radius, method,
        lines,
    )
    ranges, hits = np.asarray(ranges), np.asarray(hits)
    worst = 0.0
    for i in range(len(poses)):
        ref_r, ref_h = brute_force_lidar(
            pos[i], theta[i], goal[i], walls[i], np.asarray(angles), cfg.cell_size, max_range,
            cfg.goal_radius,
        )  # fmt: skip
        worst = max(worst, np.abs(ranges[i] - ref_r).max())
        assert (hits[i] == ref_h).all(), (i, hits[i], ref_h)
        # the NumPy twin's caster is held to the same reference
        np_r, np_h = cast_lidar_np(
            pos[i], theta[i], goal[i], walls[i], beam_angles(beams, fov), cfg.cell_size,
            max_range, cfg.goal_radius,
        )  # fmt: skip
        assert np.abs(np_r - ref_r).max() < 1e-4
        assert (np_h == ref_h).all()
    assert worst < 1e-4, worst
    # the sample exercised every hit type
    assert {HIT_WALL, HIT_GOAL} <= set(np.unique(hits)) or max_range > 5


@pytest.mark.parametrize("method", METHODS)
def test_lidar__short_range_reports_nothing_hit(method):
    walls = np.ones((8, 8), bool)
    walls[1:-1, 1:-1] = False
    ranges, hits = cast_lidar(
        jnp.array([4.0, 4.0]),
        jnp.float32(0.0),
        jnp.array([6.5, 6.5]),
        walls,
        4,
        360.0,
        1.0,
        1.5,
        0.3,
        method,
    )
    assert (np.asarray(hits) == HIT_NONE).all()
    assert np.allclose(np.asarray(ranges), 1.5)


@pytest.mark.parametrize("method", METHODS)
def test_lidar__hand_built_distances_and_goal(method):
    # 8x8 room of 1 m cells, free inside; robot at (2.5, 4.5) facing +x, goal at (5.5, 4.5)
    walls = np.ones((8, 8), bool)
    walls[1:-1, 1:-1] = False
    # 4 beams at 0, 90, 180, 270 degrees
    ranges, hits = cast_lidar(
        jnp.array([2.5, 4.5]),
        jnp.float32(0.0),
        jnp.array([5.5, 4.5]),
        walls,
        4,
        360.0,
        1.0,
        10.0,
        0.5,
        method,
    )
    np.testing.assert_allclose(np.asarray(ranges), [2.5, 2.5, 1.5, 3.5], atol=1e-5)
    assert list(np.asarray(hits)) == [HIT_GOAL, HIT_WALL, HIT_WALL, HIT_WALL]


def test_beam_angles__fov_ends_included_and_full_circle_even():
    a = np.rad2deg(np.asarray(beam_angles(5, 90.0)))
    np.testing.assert_allclose(a, [-45, -22.5, 0, 22.5, 45], atol=1e-4)
    b = np.rad2deg(np.asarray(beam_angles(4, 360.0)))
    np.testing.assert_allclose(b, [0, 90, 180, 270], atol=1e-4)
    assert np.asarray(beam_angles(1, 90.0)).tolist() == [0.0]


def test_lidar_method__auto_follows_the_measured_table_and_bad_names_are_refused():
    from quicknav_core.env.lidar import FASTEST_LIDAR, resolve_lidar_method

    assert resolve_lidar_method("auto", "cpu") == FASTEST_LIDAR["cpu"]
    assert resolve_lidar_method("dda", "cpu") == "dda"
    with pytest.raises(ValueError, match="allowed 'auto'"):
        resolve_lidar_method("raymarch")
    with pytest.raises(ValueError, match="lidar_method"):
        EnvConfig(lidar_method="raymarch")


def test_lidar_method__envs_step_identically_with_either_caster():
    """Whole env steps (reset, moves, auto-reset) give the same observations with both casters."""
    from quicknav_core.env.batch import BatchedEnv

    base = {"grid_size": 8, "lidar_beams": 12, "train_rooms": 16, "test_rooms": 8, "max_steps": 15}
    envs = {m: BatchedEnv(EnvConfig(**base, lidar_method=m), 32, seed=3) for m in METHODS}
    obs = {m: e.reset() for m, e in envs.items()}
    np.testing.assert_allclose(obs["crossings"], obs["dda"], atol=1e-5)
    rng = np.random.default_rng(0)
    for _ in range(30):
        actions = rng.uniform(-1, 1, (32, 2)).astype(np.float32)
        out = {m: e.step(actions) for m, e in envs.items()}
        np.testing.assert_allclose(out["crossings"].obs, out["dda"].obs, atol=1e-5)
        np.testing.assert_array_equal(out["crossings"].reward, out["dda"].reward)


@pytest.mark.parametrize("g,beams,fov,max_range,reach", [
    (64, 64, 360.0, 2.6, 11),  # 2 words per row
    (128, 64, 360.0, 2.6, 11),  # 4 words per row
    (96, 15, 270.0, 4.1, 17),  # unpaired beams: each one's own side of every line
    (100, 16, 360.0, 7.6, 31),  # a reach past one word: two words a side
    (200, 16, 360.0, 16.1, 65),  # three words a side
])  # fmt: skip
def test_lidar__range_window_sees_what_the_whole_grid_sees(g, beams, fov, max_range, reach):
    """The caster crosses only the lines within range of the robot (``lidar_window``), on each
    side of it only those the beam moving that way meets: on sparse walls, where many hits lie
    near the range's edge and near the grid's border, it returns exactly what crossing every line
    of the grid returns."""
    from quicknav_core.env.lidar import lidar_window, side_words

    cell = 0.25
    lines = lidar_window(g, cell, max_range)
    assert lines == 2 * reach + 3
    assert side_words(lines) == 1 + (reach > 30) + (reach > 62)  # a word a side up to 30 cells
    rng = np.random.default_rng(3)
    n = 25_600 // beams  # the same number of beams in every case
    # walls as sparse as the range is long: a beam's free path is about the range
    walls = rng.random((n, g, g)) < 0.04 * 2.6 / max_range
    walls[:, 0, :] = walls[:, -1, :] = walls[:, :, 0] = walls[:, :, -1] = True
    pos = rng.uniform(cell, (g - 1) * cell, (n, 2)).astype(np.float32)
    theta = rng.uniform(-np.pi, np.pi, n).astype(np.float32)
    goal = np.full((n, 2), -10.0, np.float32)  # off the grid: walls only
    args = (pos, theta, goal, walls, beams, fov, cell, max_range, 0.3, "crossings")
    window_r, window_h = map(np.asarray, cast_batch(*args, lines))
    whole_r, whole_h = map(np.asarray, cast_batch(*args, None))
    assert (window_h == whole_h).all()
    np.testing.assert_array_equal(window_r, whole_r)
    # the sample reaches the range's edge: walls hit in its last cell (its last 4 % for a long
    # range), and beams that see nothing
    hit, edge = whole_h == HIT_WALL, max(cell, 0.04 * max_range)
    assert (whole_r[hit] > max_range - edge).sum() > 200 and (whole_h == HIT_NONE).sum() > 200
