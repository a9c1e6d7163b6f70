"""Obstacles the map does not show (``env.obstacles``): placed where they block no passage, seen by
the lidar as walls, collided with, people that walk and yield; the NumPy twin does the same."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.numpy_env import QuickNavNumpyEnv

OBST = dict(rooms="floorplan", grid_size=16, room_size=8.0, train_rooms=32, test_rooms=8,
            lidar_beams=32, max_steps=120, obstacles={"static": 4, "moving": 3})  # fmt: skip


@pytest.fixture(scope="module")
def episodes():
    cfg = EnvConfig(**OBST)
    env, params = cfg.build("train")
    obs, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(5), 32), params)
    return cfg, env, params, obs, states


def test_obstacles__placed_in_open_cells_clear_of_start_and_goal(episodes):
    cfg, _, _, _, states = episodes
    o = cfg.obstacles
    present_total = 0
    for i in range(32):
        walls = np.asarray(states.walls[i])
        pos, goal = np.asarray(states.pos[i]), np.asarray(states.goal[i])
        ob = jax.tree.map(lambda x, i=i: np.asarray(x[i]), states.obstacles)
        present = ob.radius > 0
        present_total += present.sum()
        for j in np.flatnonzero(present):
            r, c = np.floor(ob.pos[j][::-1] / cfg.cell_size).astype(int)
            assert not walls[r - 1 : r + 2, c - 1 : c + 2].any(), "an obstacle in a passage"
            assert np.linalg.norm(ob.pos[j] - pos) >= ob.radius[j] + o.clearance_m - 1e-5
            assert np.linalg.norm(ob.pos[j] - goal) >= ob.radius[j] + o.clearance_m - 1e-5
            lo, hi = o.moving_radius_m if j >= o.static else o.static_radius_m
            assert lo <= ob.radius[j] <= hi
        assert (ob.vel[: o.static] == 0).all()  # boxes stand still
        assert (ob.pos[~present] < -1e3).all()  # absent ones are parked far away
    assert present_total >= 32  # about one of every few is placed: a density, not a count


def test_obstacles__the_lidar_sees_them_as_walls(episodes):
    """Each beam's return against a brute-force march through walls and discs."""
    cfg, env, params, _, states = episodes
    angles = np.deg2rad(np.arange(cfg.lidar_beams) * 360.0 / cfg.lidar_beams)
    seen_obstacle = 0
    for i in range(16):
        s = jax.tree.map(lambda x, i=i: x[i], states)
        walls, pos, th = np.asarray(s.walls), np.asarray(s.pos), float(s.theta)
        ob = jax.tree.map(np.asarray, s.obstacles)
        march = np.arange(0.0, cfg.lidar_max_range, 0.002)  # every point of the beam, 2 mm apart
        for b, a in enumerate(angles):
            d = np.array([np.cos(th + a), np.sin(th + a)])
            p = pos + march[:, None] * d
            rc = np.floor(p[:, ::-1] / cfg.cell_size).astype(int)
            rc = np.clip(rc, 0, np.array(walls.shape) - 1)  # past the first hit only: the ring is walls
            in_disc = np.any((ob.radius > 0) & (np.linalg.norm(p[:, None] - ob.pos, axis=2) <= ob.radius), axis=1)
            hit = walls[rc[:, 0], rc[:, 1]] | in_disc
            t_hit = cfg.lidar_max_range
            if hit.any():  # the first point of the march in a wall or a disc
                first = int(np.argmax(hit))
                t_hit, seen_obstacle = march[first], seen_obstacle + int(in_disc[first])
            assert float(s.lidar_ranges[b]) == pytest.approx(t_hit, abs=0.01), (i, b)
    assert seen_obstacle >= 3  # beams that met a disc before any wall


def test_obstacles__the_robot_does_not_drive_into_one_and_people_yield():
    walls = np.zeros((8, 8), bool)
    walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = True
    cfg = EnvConfig(grid_size=8, room_size=4.0, lidar_beams=8, train_rooms=4, test_rooms=2,
                    obstacles={"static": 1, "moving": 1})  # fmt: skip
    env, params = cfg.build("train")
    box = {"pos": [[2.25, 1.25], [3.25, 3.25]], "vel": [[0.0, 0.0], [-0.5, 0.0]], "radius": [0.2, 0.2]}
    _, s = env.load_state(walls, [1.25, 1.25], 0.0, [1.25, 3.25], params, obstacles=box)
    step = jax.jit(env.step_env)
    collided = 0
    for _ in range(12):
        _, s, _, _, info = step(jax.random.PRNGKey(0), s, jnp.array([1.0, 1.0]), params)
        collided += int(info["collision"])
        gap = np.linalg.norm(np.asarray(s.pos) - np.asarray(s.obstacles.pos[0]))
        assert gap >= 0.15 + 0.2 - 1e-5  # never inside the box
    assert collided >= 5 and float(s.pos[0]) < 2.25 - 0.35 + 0.01  # stopped in front of it
    # the person walked left, then turned at the wall and walks back
    person = np.asarray(s.obstacles.pos[1])
    assert person[0] < 3.25 and float(s.obstacles.vel[1][0]) != 0.0


def test_obstacles__the_twin_steps_the_same_episodes(episodes):
    cfg, env, params, _, states = episodes
    twin = QuickNavNumpyEnv(cfg)
    step = jax.jit(env.step_env)
    rng = np.random.default_rng(2)
    collisions = 0
    for i in range(8):
        s = jax.tree.map(lambda x, i=i: x[i], states)
        twin.load(np.asarray(s.walls), np.asarray(s.pos), float(s.theta), np.asarray(s.goal),
                  obstacles=s.obstacles)  # fmt: skip
        for t in range(80):
            a = rng.uniform(-0.5, 1.0, 2).astype(np.float32)
            o_j, s, r_j, _, info = step(jax.random.PRNGKey(t), s, jnp.asarray(a), params)
            o, r, term, trunc, inf = twin.step(a)
            assert np.abs(o - np.asarray(o_j)).max() < 1e-4, (i, t)
            np.testing.assert_allclose(twin.snapshot()["obstacles"]["pos"], np.asarray(s.obstacles.pos), atol=1e-5)
            assert inf["collision"] == bool(info["collision"]) and abs(r - float(r_j)) < 1e-4
            collisions += inf["collision"]
            if term or trunc:
                break
    assert collisions > 0


def test_obstacles__config_errors_name_the_field():
    with pytest.raises(ValueError, match=r"obstacles.static_radius_m=\[0.1, 0.3\].*below 0.25"):
        EnvConfig(obstacles={"static": 1, "static_radius_m": [0.1, 0.3]})
    with pytest.raises(ValueError, match=r"speed_mps=\[0.5, 0.2\]: a range is \[low, high\]"):
        EnvConfig(obstacles={"moving": 1, "speed_mps": [0.5, 0.2]})
    assert EnvConfig().obstacle_counts is None and EnvConfig(obstacles={}).obstacle_counts is None
    assert EnvConfig(obstacles={"static": 2}).compile_key() != EnvConfig(obstacles={"static": 3}).compile_key()
