"""Non-square rooms: a map's grid follows its shape (rows x cols), not a square around it.

The reference is the square env the same map was laid in before (``grid_size`` a side, the map
padded with wall to a square): a map's cells sit at the same rows and columns in both grids, the
free cells are listed in the same (row-major) order, so the same keys draw the same episodes and
every step must give the same observation, reward and end (to float rounding: the two shapes
compile to different programs, whose fused multiply-adds may round apart): lidar (the bit-scan
search below 32 cells, the windowed caster above), collisions, the plan the policy follows, the
obstacles, the oracle's reference path. The NumPy twin is held to the JAX env on the non-square
room as on square ones.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.numpy_env import QuickNavNumpyEnv
from quicknav_core.eval.map_fit import fit_map
from tests.core.env.test_room_sources import write_map

CELL = 0.5
# the building preset's kind of env: plan, obstacles, end on collision
ENV = {"rooms": "maps", "train_rooms": 2, "test_rooms": 2, "lidar_beams": 16, "max_steps": 60,
       "observe_plan": True, "plan_lookahead": 1, "plan_waypoints": 3,
       "obstacles": {"static": 2, "moving": 2}, "lidar_max_range": 3.0, "end_on_collision": True}  # fmt: skip


def _map(folder, rows: int, cols: int, seed: int):
    """A map of rows x cols pixels of 0.5 m: a room with a few wall blocks inside."""
    rng = np.random.default_rng(seed)
    drawn = np.zeros((rows, cols), bool)
    for _ in range(rows * cols // 40):
        r, c = rng.integers(0, rows - 1), rng.integers(0, cols - 1)
        drawn[r : r + 2, c : c + 1] = True
    folder.mkdir(parents=True, exist_ok=True)
    return write_map(folder, drawn, CELL)


def _envs(path, **extra):
    """(the non-square env on the map, the square one it replaces)."""
    probe = EnvConfig(**{**ENV, "maps": {"train": [str(path)]}, "grid_size": 64, "room_size": 32.0})
    fit = fit_map(probe, path)
    side = fit.grid_size
    base = {**ENV, **extra, "maps": {"train": [str(path)]}, "grid_size": side, "room_size": side * CELL}
    rect = EnvConfig(**base, **fit.shape_fields())
    square = EnvConfig(**base)
    return rect, square


def _roll(config: EnvConfig, steps: int, n: int = 6):
    env, params = config.build("train")
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    out = [np.asarray(obs)]
    rng = np.random.default_rng(1)
    for t in range(steps):
        action = jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32)
        obs, state, reward, done, _ = step(jax.random.split(jax.random.PRNGKey(100 + t), n), state,
                                           action, params)  # fmt: skip
        out += [np.asarray(obs), np.asarray(reward)[:, None], np.asarray(done)[:, None]]
    return out, env, params, state


# a tall map (below 32 cells: the lidar's bit-scan search) and a wide one above 32 (the windowed
# caster, its short axis under the window)
@pytest.mark.parametrize("rows,cols", [(22, 9), (8, 46)], ids=["tall", "wide-windowed"])
def test_nonsquare__steps_as_the_square_room_the_map_was_padded_to(tmp_path, rows, cols):
    rect, square = _envs(_map(tmp_path, rows, cols, seed=rows), **(
        {"lidar_max_range": 2.0} if cols > 32 else {}))  # fmt: skip
    assert rect.grid_shape == (rows + 2, cols + 2) and square.grid_shape == (rect.grid_size,) * 2
    if cols > 32:  # the windowed caster, an axis shorter than the window
        assert rect.lidar_lines < rect.grid_size - 1 and rect.lidar_lines > rows + 1
    got, env, params, state = _roll(rect, 40)
    want, _, square_params, _ = _roll(square, 40)
    assert (env.rows, env.cols) == rect.grid_shape
    assert params.rooms.shape[1:] == rect.grid_shape and state.plan.shape[1:] == rect.grid_shape
    assert params.free_cells.shape[1] == (rows + 2) * (cols + 2)  # the square held side * side
    assert square_params.free_cells.shape[1] == rect.grid_size**2
    for a, b in zip(got, want, strict=True):
        if a.dtype == bool:  # the ends: exactly
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=0, atol=2e-5)
    # the episodes ended and restarted inside the run (a rollout that never reset tests less)
    assert any(d.any() for d in got[3::3])


def test_nonsquare__the_twin_steps_as_the_jax_env(tmp_path):
    rect, _ = _envs(_map(tmp_path, 7, 19, seed=5), obstacles=None)
    env, params = rect.build("train")
    twin = QuickNavNumpyEnv(rect, rooms=np.asarray(params.rooms))
    rng = np.random.default_rng(0)
    step = jax.jit(env.step_env)
    compared = 0
    for episode in range(3):
        obs, state = env.reset(jax.random.PRNGKey(episode), params)
        walls = np.asarray(state.walls)
        assert walls.shape == rect.grid_shape
        t_obs, _ = twin.reset(options={"walls": walls, "pos": np.asarray(state.pos),
                                       "theta": float(state.theta), "goal": np.asarray(state.goal)})  # fmt: skip
        np.testing.assert_allclose(t_obs, np.asarray(obs), atol=1e-5)
        for _ in range(40):
            action = rng.uniform(-1, 1, 2).astype(np.float32)
            obs, state, reward, done, _ = step(jax.random.PRNGKey(0), state, jnp.asarray(action), params)
            t_obs, t_reward, t_term, t_trunc, _ = twin.step(action)
            np.testing.assert_allclose(t_obs, np.asarray(obs), atol=1e-5)
            assert t_reward == pytest.approx(float(reward), abs=1e-4)
            compared += 1
            if bool(done):
                assert t_term or t_trunc
                break
    assert compared >= 30, compared  # the episodes were stepped, not ended at once


def test_nonsquare__a_long_corridor_takes_its_own_cells_and_the_oracle_drives_it(tmp_path):
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import run_eval

    drawn = np.zeros((2, 40), bool)  # a 20 m x 1 m corridor
    path = write_map(tmp_path, drawn, CELL)
    probe = EnvConfig(**{**ENV, "obstacles": None, "maps": {"train": [str(path)]}, "grid_size": 64,
                         "room_size": 32.0})  # fmt: skip
    fit = fit_map(probe, path)
    assert fit.grid_shape == (4, 42) and fit.grid_size == 42  # a square held 42 x 42 cells
    env = EnvConfig.model_validate({**probe.model_dump(), **fit.env_overrides(str(path))})
    assert env.grid_shape == (4, 42) and env.inner_cells == 2 * 40
    result, _ = run_eval(EvalConfig(policy="oracle", env=env, episodes=8, gif_episodes=0))
    assert result["metrics"]["success_rate"] == 1.0, result["metrics"]


def test_nonsquare__the_pictures_plan_is_the_square_rooms(tmp_path):
    """The plan the pictures and the replay draw (``episodes.plan_path``, from a start far along
    the long side, beyond the short side's count of cells)."""
    from quicknav_core.eval.episodes import plan_path

    rect, square = _envs(_map(tmp_path, 6, 20, seed=6), obstacles=None)
    walls = rect.build("train")[1].rooms[0]
    padded = np.ones(square.grid_shape, bool)
    padded[: walls.shape[0], : walls.shape[1]] = np.asarray(walls)
    free = np.argwhere(~np.asarray(walls))
    start_rc, goal_rc = free[np.argmax(free[:, 1])], free[np.argmin(free[:, 1])]
    assert start_rc[1] >= walls.shape[0]  # a column the short side does not have
    start, goal = (start_rc[::-1] + 0.5) * CELL, (goal_rc[::-1] + 0.5) * CELL
    got, want = plan_path(rect, np.asarray(walls), start, goal), plan_path(square, padded, start, goal)
    assert len(got) > 2 and np.array_equal(got, want)


def test_nonsquare__a_grid_too_small_for_the_map_names_rows_and_cols(tmp_path):
    from quicknav_core.env.maps import MapError, load_map, to_cells

    m = load_map(write_map(tmp_path, np.zeros((6, 20), bool), CELL))  # 10 m x 3 m
    assert to_cells(m, CELL, (8, 22)).shape == (8, 22)
    with pytest.raises(MapError, match=r"grid_rows x grid_cols = 8 x 21 holds 19 x 6\. Set grid_rows"
                                       r" >= 8 and grid_cols >= 22 with grid_size the larger"):
        to_cells(m, CELL, (8, 21))


def test_nonsquare__refused_where_it_cannot_be_honoured():
    with pytest.raises(ValueError, match=r"grid_rows/grid_cols .* apply only with rooms=.maps."):
        EnvConfig(grid_size=16, grid_rows=8)
    with pytest.raises(ValueError, match=r"the longer side must be grid_size=16"):
        EnvConfig(rooms="maps", maps={"train": ["x.yaml"]}, grid_size=16, grid_rows=8, grid_cols=12)
    assert EnvConfig(rooms="maps", maps={"train": ["x.yaml"]}, grid_size=16,
                     grid_rows=8).grid_shape == (8, 16)  # fmt: skip
