"""A robot as wide as a cell or wider (a building at fine cells): its disc against a brute-force
test, where it may start and end (against a BFS), the JAX env against its NumPy twin, the oracle.
"""

from __future__ import annotations

from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.bits import pack_rows_np
from quicknav_core.env.clearance import check_fit, reach_cells, spawn_cells, spawn_region
from quicknav_core.env.dynamics import disc_overlaps_wall_bits
from quicknav_core.env.numpy_env import QuickNavNumpyEnv, disc_overlaps_wall_np
from quicknav_core.env.room_sources import room_source

# 0.25 m cells, a 0.4 m wide robot, floor plans with doors and a corridor 3 cells (0.75 m) wide
WIDE = dict(rooms="floorplan", grid_size=32, room_size=8.0, robot_radius=0.2, train_rooms=64,
            test_rooms=32, max_steps=400, lidar_beams=16,
            floorplan={"min_room": 8, "max_room": 20, "door_width": 3, "corridor_width": 3})  # fmt: skip


def brute_overlaps(pos, walls, cell, radius) -> bool:
    """Distance from the disc's centre to every wall square, no shortcuts."""
    rows, cols = np.nonzero(walls)
    gx = np.maximum(np.maximum(cols * cell - pos[0], pos[0] - (cols + 1) * cell), 0.0)
    gy = np.maximum(np.maximum(rows * cell - pos[1], pos[1] - (rows + 1) * cell), 0.0)
    return bool(np.any(gx * gx + gy * gy < radius * radius))


@pytest.fixture(scope="module")
def wide():
    cfg = EnvConfig(**WIDE)
    env, params = cfg.build("train")
    return cfg, env, params


@pytest.mark.parametrize("radius", [0.1, 0.2, 0.3, 0.55])
def test_disc_test__matches_brute_force_for_any_width(wide, radius):
    cfg, _, params = wide
    cell = cfg.cell_size
    rooms = np.asarray(params.rooms)[:8]
    reach = 0 if 2 * radius < cell else reach_cells(radius, cell)
    rng = np.random.default_rng(int(radius * 100))
    pos = rng.uniform(0.0, cfg.room_size, (8, 300, 2)).astype(np.float32)
    bits = jnp.asarray(pack_rows_np(rooms))
    test = jax.jit(jax.vmap(jax.vmap(lambda p, b: disc_overlaps_wall_bits(p, b, cell, radius, reach),
                                     in_axes=(0, None))))  # fmt: skip
    got = np.asarray(test(jnp.asarray(pos), bits))
    want = np.array([[brute_overlaps(p, r, cell, radius) for p in ps] for ps, r in zip(pos, rooms, strict=True)])
    twin = np.array([[disc_overlaps_wall_np(p, r, cell, radius) for p in ps] for ps, r in zip(pos, rooms, strict=True)])
    assert np.array_equal(got, want) and np.array_equal(twin, want)
    assert 0.05 < want.mean() < 0.95  # the positions test both answers


def test_spawn_region__the_disc_fits_at_every_cell_and_the_region_is_one_drivable_piece(wide):
    cfg, _, params = wide
    cell, radius = cfg.cell_size, cfg.robot_radius
    for walls in np.asarray(params.rooms)[:6]:
        region = spawn_region(walls, cell, radius)
        g = walls.shape[0]
        centre = lambda r, c: np.array([(c + 0.5) * cell, (r + 0.5) * cell])  # noqa: E731
        fits = np.array([[not walls[r, c] and not brute_overlaps(centre(r, c), walls, cell, radius)
                          for c in range(g)] for r in range(g)])  # fmt: skip
        assert not np.any(region & ~fits)
        # BFS over side neighbours where the disc fits, from one region cell: exactly the region
        start = tuple(np.argwhere(region)[0])
        seen, queue = {start}, deque([start])
        while queue:
            r, c = queue.popleft()
            for nr, nc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                if 0 <= nr < g and 0 <= nc < g and fits[nr, nc] and (nr, nc) not in seen:
                    seen.add((nr, nc))
                    queue.append((nr, nc))
        reached = np.zeros_like(region)
        reached[tuple(np.array(sorted(seen)).T)] = True
        assert np.array_equal(reached, region)
        assert region.sum() > 0.3 * (~walls).sum()  # the wide doors let it reach most of the floor


def test_env__starts_and_goals_where_the_disc_fits_and_it_never_enters_a_wall(wide):
    cfg, env, params = wide
    cell, radius = cfg.cell_size, cfg.robot_radius
    assert env.reach == 1
    n = 256
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), n), params)
    rooms = np.asarray(params.rooms)
    regions = spawn_cells(rooms, cfg, "train")
    room_i = np.asarray(state.room_index)
    for i in range(n):
        for point in (np.asarray(state.pos[i]), np.asarray(state.goal[i])):
            r, c = (point[::-1] // cell).astype(int)
            assert regions[room_i[i], r, c], (i, point)
        assert not brute_overlaps(np.asarray(state.pos[i]), rooms[room_i[i]], cell, radius)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    rng = np.random.default_rng(1)
    for t in range(60):
        keys = jax.random.split(jax.random.PRNGKey(100 + t), n)
        before = state.room_index
        obs, state, *_ = step(keys, state, jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32), params)
        pos, room_now = np.asarray(state.pos), np.asarray(state.room_index)
        assert all(not brute_overlaps(pos[i], rooms[room_now[i]], cell, radius) for i in range(n))
        del before


def test_twin__steps_a_wide_robot_as_the_jax_env_does(wide):
    cfg, env, params = wide
    twin = QuickNavNumpyEnv(cfg, rooms=np.asarray(params.rooms))
    obs, state = env.reset(jax.random.PRNGKey(5), params)
    twin_obs = twin.load(np.asarray(params.rooms)[int(state.room_index)], np.asarray(state.pos),
                         float(state.theta), np.asarray(state.goal))  # fmt: skip
    np.testing.assert_allclose(twin_obs, np.asarray(obs), rtol=1e-5, atol=1e-5)
    rng = np.random.default_rng(2)
    step = jax.jit(env.step_env)
    collided = 0
    for t in range(120):
        a = (0.8 + rng.uniform(-0.3, 0.3, 2)).astype(np.float32)  # both wheels forward: into walls
        obs, state, reward, done, info = step(jax.random.PRNGKey(t), state, jnp.asarray(a), params)
        t_obs, t_reward, t_term, t_trunc, t_info = twin.step(a)
        np.testing.assert_allclose(t_obs, np.asarray(obs), rtol=1e-4, atol=1e-4)
        assert t_reward == pytest.approx(float(reward), abs=1e-4)
        collided += bool(info["collision"])
        if bool(done):
            break
    assert collided > 0  # the walk hit walls, with the wide disc


def test_oracle__reaches_every_goal_with_the_wide_robot(wide, optimized):
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import run_episodes
    from quicknav_core.eval.scripted import baseline_agent

    cfg, env, params = wide
    test_env, test_params = cfg.build("test")
    ep = run_episodes(test_env, test_params, baseline_agent("oracle", cfg),
                      EvalConfig(episodes=100, seed=0, split="test", pictures=False))  # fmt: skip
    assert ep.success.mean() >= 0.98, ep.success.mean()
    assert np.all(ep.reference_length < 1e8)  # every goal reachable by the disc


def test_a_robot_that_fits_in_no_room_is_refused_naming_its_radius():
    with pytest.raises(ValueError, match=r"robot_radius: a robot of radius 0\.9 m fits in fewer than two cells"):
        wide = EnvConfig(grid_size=8, robot_radius=0.9, train_rooms=64, test_rooms=16)
        check_fit(wide, room_source(wide))
    # a narrow robot: nothing built here, nothing to refuse
    check_fit(EnvConfig(grid_size=8), room_source(EnvConfig(grid_size=8)))
