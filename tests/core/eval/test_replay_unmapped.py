"""The pictures and the browser replay show what an episode drove among: the global plan of an env
that observes one, and the obstacles the map does not show, at every step, the ones its lidar saw.

Checked against the env itself: every wall return of the replayed lidar ends at a wall cell or at
an obstacle the replay shows at that step (a replay without them leaves returns in open floor),
boxes stand still and people walk no faster than their top speed, and the drawn plan is as long as
the JAX env's own plan field says from the start's cell.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from quicknav_core.config import EnvConfig, EvalConfig
from quicknav_core.env.constants import HIT_WALL

CFG = EnvConfig(rooms="floorplan", grid_size=16, room_size=8.0, train_rooms=16, test_rooms=8,
                lidar_beams=32, max_steps=60, observe_plan=True,
                obstacles={"static": 4, "moving": 3})  # fmt: skip
SEED = 3


@pytest.fixture(scope="module")
def replayed():
    from quicknav_core.eval.episodes import replay_data, run_episodes
    from quicknav_core.eval.scripted import baseline_agent

    env, params = CFG.build("test")
    ep = run_episodes(env, params, baseline_agent("random", CFG),
                      EvalConfig(episodes=6, gif_episodes=4, seed=SEED, pictures=False))  # fmt: skip
    return env, params, ep, replay_data(ep, CFG, "random")


def _at_wall(walls: list[str], p: np.ndarray, tol: float) -> bool:
    """Whether ``p`` lies within ``tol`` of a wall cell (or outside the grid)."""
    cell, g = CFG.cell_size, len(walls)
    r0, c0 = np.floor(p[::-1] / cell).astype(int)
    for r in range(r0 - 1, r0 + 2):
        for c in range(c0 - 1, c0 + 2):
            if 0 <= r < g and 0 <= c < g and walls[r][c] != "#":
                continue
            gap = np.maximum(np.abs(p - (np.array([c, r]) + 0.5) * cell) - cell / 2, 0.0)
            if np.hypot(*gap) <= tol:
                return True
    return False


def test_replay__every_wall_return_ends_at_a_wall_or_an_obstacle_it_shows(replayed):
    _, _, _, data = replayed
    angles = np.asarray(data["beam_angles"])
    on_obstacles = 0
    for e in data["episodes"]:
        for t in range(len(e["x"])):
            pos, th = np.array([e["x"][t], e["y"][t]]), e["theta"][t]
            discs = [(np.array(b[:2]), b[2]) for b in e["boxes"]]
            discs += [(np.array([p["x"][t], p["y"][t]]), p["radius"]) for p in e["people"]]
            for a, r, hit in zip(angles, e["ranges"][t], e["hits"][t], strict=True):
                if hit != HIT_WALL:
                    continue
                end = pos + r * np.array([np.cos(th + a), np.sin(th + a)])
                if _at_wall(e["walls"], end, 0.004):  # poses and ranges are rounded to mm
                    continue
                assert any(abs(np.linalg.norm(end - c) - rad) <= 0.004 for c, rad in discs), (
                    f"episode {e['index']} step {t}: a return at {end} in open floor")
                on_obstacles += 1
    assert on_obstacles > 50, on_obstacles  # the obstacles were in sight, not just listed


def test_replay__boxes_stand_still_and_people_walk_at_most_their_top_speed(replayed):
    _, _, ep, data = replayed
    o = CFG.obstacles
    people_moved = 0
    for i, e in enumerate(data["episodes"]):
        present = ep.obstacles[i, :, 2] > 0
        assert len(e["boxes"]) == present[: o.static].sum() and len(e["people"]) == present[o.static:].sum()
        boxes = ep.gif["obstacles"][i, : len(e["x"]), : o.static][:, present[: o.static]]  # (n, K, 2)
        assert np.array_equal(boxes, np.broadcast_to(boxes[:1], boxes.shape))  # never moved
        for x, y, r in e["boxes"]:
            assert o.static_radius_m[0] - 1e-3 <= r <= o.static_radius_m[1] + 1e-3
            assert np.abs(boxes[0] - [x, y]).sum(axis=1).min() < 2e-3  # shown where it stands
        for p in e["people"]:
            assert o.moving_radius_m[0] - 1e-3 <= p["radius"] <= o.moving_radius_m[1] + 1e-3
            assert len(p["x"]) == len(e["x"])  # a position at every step of the episode
            step = np.hypot(np.diff(p["x"]), np.diff(p["y"]))
            assert step.max() <= o.speed_mps[1] * CFG.dt + 2e-3, step.max()
            people_moved += step.sum() > 0.1
    assert people_moved > 0


def test_replay__the_plan_runs_from_the_start_down_the_envs_plan_field_to_the_goal(replayed):
    from quicknav_core.eval.episodes import episode_plan, plan_path

    env, params, ep, data = replayed
    cell = CFG.cell_size
    for e in data["episodes"]:
        i = e["index"]
        # the JAX env's own plan field of this episode (the eval's key for episode i)
        _, state = env.reset(jax.random.fold_in(jax.random.PRNGKey(SEED), i), params)
        field = np.asarray(state.plan)
        plan = np.asarray(e["plan"])
        np.testing.assert_allclose(plan[0], ep.trajectories[i, 0], atol=2e-3)
        np.testing.assert_allclose(plan[-1], e["goal"], atol=2e-3)
        start_rc = np.floor(plan[0][::-1] / cell).astype(int)
        goal_cell = (np.floor(plan[-1] / cell) + 0.5) * cell
        cells = np.vstack([(start_rc[::-1] + 0.5) * cell, plan[1:-1], goal_cell])
        steps = np.linalg.norm(np.diff(cells, axis=0), axis=1) / cell
        assert np.all(steps <= np.sqrt(2) + 1e-6), steps  # neighbouring cells, 8-connected
        # each step goes one neighbour down the field, so their lengths add up to its value
        assert abs(steps.sum() - field[start_rc[0], start_rc[1]]) < 1e-3, (steps.sum(), field[tuple(start_rc)])
        for x, y in plan[1:-1]:
            assert e["walls"][int(y / cell)][int(x / cell)] == "."
        # drawn from the env's own field, the same plan as the NumPy twin's planner gives
        np.testing.assert_allclose(episode_plan(ep, CFG, i), plan_path(CFG, ep.walls[i], ep.trajectories[i, 0],
                                                                       ep.goals[i]), atol=1e-5)  # fmt: skip
    assert ep.plan_fields is not None and ep.plan_fields.shape[0] == 6  # all six episodes kept


def test_pictures__the_gif_and_trajectories_draw_the_plan_boxes_and_people(replayed, tmp_path):
    """The eval's pictures of this env show the plan and the obstacles in their colours (where
    exactly: test_render_cli's drawer test), and the GIF's frames hold the obstacles present at
    their step."""
    from matplotlib.colors import to_rgb
    from PIL import Image

    from quicknav_core.env import render
    from quicknav_core.eval.pictures import draw_gif, draw_trajectories, episode_snapshot

    _, _, ep, _ = replayed
    snap = episode_snapshot(ep, CFG, 0, 5)
    present = ep.obstacles[0, :, 2] > 0
    assert len(snap["boxes"]) + len(snap["people"]) == present.sum() > 0
    np.testing.assert_allclose(snap["people"][:, :2], ep.gif["obstacles"][0, 5][CFG.obstacles.static:][
        present[CFG.obstacles.static:]], atol=1e-6)  # fmt: skip
    gif = Image.open(draw_gif(ep, CFG, tmp_path / "e.gif", max_frames=4))
    frames = []
    for i in range(gif.n_frames):  # every frame, side by side: the GIF keeps the colours exactly
        gif.seek(i)
        frames.append(np.asarray(gif.convert("RGB")))
    trajectories = np.asarray(Image.open(draw_trajectories(ep, CFG, tmp_path / "t.png")).convert("RGB"))
    for name, picture in (("trajectories", trajectories), ("gif", np.concatenate(frames, axis=1))):
        rgb = picture.astype(np.float64) / 255
        for colour in (render.PLAN_COLOUR, render.BOX_COLOUR, render.PERSON_COLOUR):
            near = np.abs(rgb - to_rgb(colour)).sum(axis=-1) < 0.1
            assert near.sum() >= 4, (name, colour, near.sum())
