"""The compiled reference the env step is measured against (``benchmarks/numba_env.py``) computes
the same env: its lidar against the NumPy twin beam by beam, and its step (dynamics with sliding,
cycle counting, reward, observation) against the twin step by step in the same rooms. An anchor
that computed less would flatter nobody."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import numba_env as ref
from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import beam_angles
from quicknav_core.env.numpy_env import QuickNavNumpyEnv, cast_lidar_np

CONFIG = EnvConfig(grid_size=12, lidar_beams=24, train_rooms=16, test_rooms=8, max_steps=40)


def test_lidar__matches_the_twin_beam_by_beam():
    batch = ref.NumbaBatch(CONFIG, 4)
    rng = np.random.default_rng(0)
    cell = CONFIG.room_size / CONFIG.grid_size
    angles = batch.angles
    checked = 0
    for room in batch.rooms[:8]:
        free = np.argwhere(~room)  # (row, col)
        picks = free[rng.integers(len(free), size=64)]
        poses = np.column_stack([(picks[:, 1] + rng.uniform(0.2, 0.8, 64)) * cell,
                                 (picks[:, 0] + rng.uniform(0.2, 0.8, 64)) * cell,
                                 rng.uniform(-np.pi, np.pi, 64)]).astype(np.float32)  # fmt: skip
        goals = ((free[rng.integers(len(free), size=64)][:, ::-1] + 0.5) * cell).astype(np.float32)
        ranges = np.zeros((64, len(angles)), np.float32)
        hits = np.zeros((64, len(angles)), np.int32)
        ref.lidar_only(room, poses, goals, angles, np.float32(cell), np.float32(CONFIG.lidar_max_range),
                       np.float32(CONFIG.goal_radius), ranges, hits)  # fmt: skip
        for i in range(64):
            want_r, want_h = cast_lidar_np(poses[i, :2], poses[i, 2], goals[i], room,
                                           beam_angles(CONFIG.lidar_beams, CONFIG.lidar_fov_deg),
                                           cell, CONFIG.lidar_max_range, CONFIG.goal_radius)  # fmt: skip
            np.testing.assert_allclose(ranges[i], want_r, rtol=1e-4, atol=1e-4)
            np.testing.assert_array_equal(hits[i], want_h)
            checked += len(angles)
    assert checked == 8 * 64 * 24


@pytest.mark.parametrize("seed", [0, 1])
def test_step__matches_the_twin_step_by_step(seed):
    """Every env of the reference, after its spawn, replayed in the twin from the same room, pose
    and goal with the same actions until its episode ends."""
    n, steps = 16, 60
    batch = ref.NumbaBatch(CONFIG, n, seed=seed)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (steps, n, 2)).astype(np.float32)
    actions[:, :4] = np.abs(actions[:, :4])  # a few envs drive forward into walls: sliding
    batch.step(np.zeros((n, 2), np.float32))  # every env spawns on the first step
    twins, alive = [], np.ones(n, bool)
    for i in range(n):
        twin = QuickNavNumpyEnv(CONFIG, rooms=batch.rooms)
        f = batch.state_f[i].copy()  # the reference steps its arrays in place
        obs = twin.load(batch.rooms[batch.state_i[i, 0]], f[:2], f[2], f[3:5])
        np.testing.assert_allclose(batch.obs[i], obs, rtol=1e-4, atol=1e-4)
        twins.append(twin)
    compared = 0
    for t in range(steps):
        obs, reward, done = batch.step(actions[t])
        for i in np.flatnonzero(alive):
            o, r, term, trunc, _ = twins[i].step(actions[t, i])
            assert bool(done[i]) == (term or trunc), (t, i)
            assert reward[i] == pytest.approx(r, abs=1e-4), (t, i)
            if done[i]:
                alive[i] = False  # the reference has respawned it; the twin does not
                continue
            np.testing.assert_allclose(obs[i], o, rtol=1e-4, atol=1e-4, err_msg=f"step {t}, env {i}")
            compared += 1
    assert compared > n * 20 and not alive.all()
