"""The global plan in the env (``observe_plan``): the shortest path on the known map, its waypoints in
the robot's frame, the path-progress reward, and the NumPy twin's identical plan."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import ConfigError, EnvConfig, resolve_train
from quicknav_core.env.batch import batched_step
from quicknav_core.env.numpy_env import QuickNavNumpyEnv
from quicknav_core.env.plan import INF, cell_field
from tests.core.env.reference import grid_dijkstra

PLAN = dict(rooms="floorplan", grid_size=16, room_size=8.0, train_rooms=32, test_rooms=8,
            lidar_beams=8, observe_plan=True, observe_pose=False, observe_goal=False, max_steps=80)  # fmt: skip


@pytest.fixture(scope="module")
def planned():
    cfg = EnvConfig(**PLAN)
    env, params = cfg.build("train")
    keys = jax.random.split(jax.random.PRNGKey(3), 16)
    obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    return cfg, env, params, obs, states


def test_plan__cell_field_equals_a_dijkstra_on_the_same_graph(planned):
    cfg, _, _, _, states = planned
    for i in range(8):
        walls = np.asarray(states.walls[i])
        goal_rc = tuple(np.floor(np.asarray(states.goal[i])[::-1] / cfg.cell_size).astype(int))
        ref = grid_dijkstra(~walls, {goal_rc: 0.0}, 1.0)
        got = np.asarray(states.plan[i])
        reached = np.isfinite(ref)
        np.testing.assert_allclose(got[reached], ref[reached], rtol=1e-5)
        assert (got[~reached] >= INF / 2).all()
        # what the env stores is the field of its goal's cell: a fresh computation agrees
        again = cell_field(jnp.asarray(~walls), jnp.asarray(goal_rc))
        np.testing.assert_array_equal(np.asarray(again), got)


def test_plan__waypoints_lie_down_the_path_in_the_robots_frame(planned):
    cfg, env, params, obs, states = planned
    n = cfg.plan_waypoints
    plan_part = np.asarray(obs)[:, -(2 * n + 1):]
    assert (np.abs(plan_part[:, :-1]) <= 1.0).all() and ((plan_part[:, -1] >= 0) & (plan_part[:, -1] < 1)).all()
    for i in range(8):
        s = jax.tree.map(lambda x, i=i: x[i], states)
        field = np.asarray(s.plan)
        r, c = np.asarray(s.cell)
        # undo the features: the first waypoint back in the room frame
        reach = (cfg.plan_lookahead + 1.0) * np.sqrt(2.0) * cfg.cell_size
        fwd, left = plan_part[i, 0] * reach, plan_part[i, 1] * reach
        th = float(s.theta)
        wp = np.asarray(s.pos) + np.array([np.cos(th) * fwd - np.sin(th) * left,
                                           np.sin(th) * fwd + np.cos(th) * left])  # fmt: skip
        wr, wc = np.floor(wp[::-1] / cfg.cell_size).astype(int)
        # the waypoint's cell is lookahead steps closer to the goal (or the goal's own cell)
        assert field[wr, wc] <= max(field[r, c] - cfg.plan_lookahead + 1e-4, 0.0), (i, field[r, c], field[wr, wc])
        # the path left, in metres, is what the observation says
        left_m = np.arctanh(plan_part[i, -1]) * 10.0
        assert left_m == pytest.approx(field[r, c] * cfg.cell_size, rel=1e-4, abs=1e-4)


def test_plan__the_twin_plans_the_same_and_steps_the_same(planned):
    cfg, env, params, _, states = planned
    twin = QuickNavNumpyEnv(cfg)
    rng = np.random.default_rng(0)
    step = jax.jit(env.step_env)
    for i in range(6):
        s = jax.tree.map(lambda x, i=i: x[i], states)
        o = twin.load(np.asarray(s.walls), np.asarray(s.pos), float(s.theta), np.asarray(s.goal))
        np.testing.assert_array_equal(twin.snapshot()["plan"], np.asarray(s.plan))
        for t in range(40):
            a = rng.uniform(-0.2, 1.0, 2).astype(np.float32)
            o_j, s, r_j, d_j, _ = step(jax.random.PRNGKey(t), s, jnp.asarray(a), params)
            o, r, term, trunc, _ = twin.step(a)
            assert np.abs(o - np.asarray(o_j)).max() < 1e-4, (i, t)
            assert abs(r - float(r_j)) < 1e-4, (i, t)
            if term or trunc:
                break


def test_plan__batched_step_plans_only_the_ended_envs_and_equals_vmapped_step():
    cfg = EnvConfig(**{**PLAN, "max_steps": 12, "final_obs": True})
    env, params = cfg.build("train")
    n = 32
    _, s_a = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), n), params)
    s_b = s_a
    vstep = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    bstep = jax.jit(lambda k, s, a: batched_step(env, k, s, a, params, reset_capacity=4))
    rng = np.random.default_rng(1)
    for t in range(30):  # synchronised truncations: every env ends at once, more than 4 a round
        keys = jax.random.split(jax.random.PRNGKey(100 + t), n)
        a = jnp.asarray(rng.uniform(-1, 1, (n, 2)), jnp.float32)
        o_a, s_a, r_a, d_a, _ = vstep(keys, s_a, a, params)
        o_b, s_b, r_b, info, _ = bstep(keys, s_b, a)
        # the same episodes and plans; numbers to float rounding (two programs fuse differently)
        np.testing.assert_array_equal(np.asarray(s_a.plan), np.asarray(s_b.plan))
        np.testing.assert_array_equal(np.asarray(s_a.cell), np.asarray(s_b.cell))
        np.testing.assert_allclose(np.asarray(o_a), np.asarray(o_b), atol=1e-5)
        np.testing.assert_allclose(np.asarray(r_a), np.asarray(r_b), atol=1e-5)


def test_plan__path_progress_pays_for_the_path_not_the_straight_line():
    """A robot facing its goal through a wall: driving at the wall shortens the straight line but
    not the path (no reward, a collision), driving along the path pays."""
    walls = np.zeros((8, 8), bool)
    walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = True
    walls[1:6, 4] = True  # a wall with a gap at the top, between the robot and the goal
    cfg = EnvConfig(grid_size=8, room_size=4.0, lidar_beams=8, train_rooms=4, test_rooms=2,
                    observe_plan=True, reward={"progress": "path", "step_penalty": 0.0})  # fmt: skip
    env, params = cfg.build("train")
    start, goal = np.array([1.75, 1.25], np.float32), np.array([3.25, 1.25], np.float32)
    step = jax.jit(env.step_env)
    _, s = env.load_state(walls, start, 0.0, goal, params)  # facing +x: the wall ahead
    for _ in range(3):
        _, s, r, _, info = step(jax.random.PRNGKey(0), s, jnp.array([1.0, 1.0]), params)
    assert bool(info["collision"]) and float(r) < 0  # into the wall: no progress, a penalty
    _, s = env.load_state(walls, start, np.pi / 2, goal, params)  # facing +y: along the path
    _, s, r, _, _ = step(jax.random.PRNGKey(0), s, jnp.array([1.0, 1.0]), params)
    assert float(r) == pytest.approx(float(params.progress_reward), rel=0.05)  # a full step of path


def test_plan__fields_that_need_the_plan_are_refused_without_it_and_rejax_is_refused_with_it():
    with pytest.raises(ValueError, match=r"reward\.progress='path'"):
        EnvConfig(reward={"progress": "path"})
    with pytest.raises(ConfigError) as e:
        resolve_train({"preset": "paper-ppo", "overrides": {"env.observe_plan": True}})
    assert e.value.items[0]["loc"] == ["overrides", "env.observe_plan"]
    assert "implementation='quicknav'" in e.value.items[0]["msg"]
    ok = resolve_train({"preset": "paper-ppo", "overrides": {
        "env.observe_plan": True, "algorithm.implementation": "quicknav"}})  # fmt: skip
    assert ok.trainer_kind == "recurrent-ppo"


def test_usable_nodes__grid_form_equals_the_disc_test_at_every_node():
    """The planner's usable nodes are computed on the unpacked grid (no per-node selection of
    packed rows, which held gigabytes on a large map): the same answer as the env's own disc test
    (``disc_overlaps_wall_bits``) at every node, narrow and wide robots, rows of 1 and 2 words."""
    from quicknav_core.env.bits import pack_rows
    from quicknav_core.env.dynamics import disc_overlaps_wall_bits
    from quicknav_core.env.plan import node_positions, usable_nodes

    # compiled, as the env runs them (op by op, this test compiled ~330 small programs)
    @partial(jax.jit, static_argnums=(3, 4))
    def disc_test(rb, room, r, k, reach):
        pts = node_positions(rb.shape[0], room, k).reshape(-1, 2)
        return jax.vmap(lambda p: disc_overlaps_wall_bits(p, rb, 0.5, r, reach))(pts)

    grid_form = jax.jit(usable_nodes, static_argnums=(3, 4))
    rng = np.random.default_rng(0)
    for g in (8, 40):  # one and two packed words a row
        for reach, radius in ((0, 0.15), (0, 0.24), (1, 0.4), (2, 0.9)):
            walls = rng.random((g, g)) < 0.25
            walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = True
            rb = pack_rows(jnp.asarray(walls))
            room, r = jnp.float32(g * 0.5), jnp.float32(radius)
            for k in (1, 3):
                want = ~np.asarray(disc_test(rb, room, r, k, reach)).reshape(g * k, g * k)
                got = np.asarray(grid_form(rb, room, r, k, reach))
                assert (got == want).all(), (g, reach, radius, k, int((got != want).sum()))
