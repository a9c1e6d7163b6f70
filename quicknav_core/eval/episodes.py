"""Running held-out episodes: all at once, vmapped, one ``lax.scan`` over the step limit.

Episode i starts from ``reset(fold_in(PRNGKey(seed), i))``, so two agents evaluated with the same
seed and env config face exactly the same rooms, starts and goals; finished episodes are frozen.
``replay_data`` turns the picture episodes into the browser replay's ``replay.json``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.config import EnvConfig, EvalConfig
from quicknav_core.config.eval import EVAL_BATCH, plan_batch
from quicknav_core.env.plan import shortest_path_length
from quicknav_core.eval.agents import Agent
from quicknav_core.runtime import Runtime, runtime_or_new

__all__ = ["PLAN_KEPT", "Episodes", "EvalStopped", "episode_plan", "outcome", "replay_data", "run_episodes"]

# the episodes whose plan field an evaluation keeps for its pictures (trajectories.png draws 9;
# the GIF and the replay the first ``gif_episodes``), at most a batch
PLAN_KEPT = 9


@dataclass
class Episodes:
    """Per-episode outcomes (numpy) and what the pictures need."""

    success: np.ndarray  # (N,) bool
    truncated: np.ndarray  # (N,) bool
    steps: np.ndarray  # (N,) int: steps taken (to the goal, or the limit)
    returns: np.ndarray  # (N,) float
    collisions: np.ndarray  # (N,) int
    path_length: np.ndarray  # (N,) float metres driven
    reference_length: np.ndarray  # (N,) float shortest path into the goal disc
    trajectories: np.ndarray  # (N, T+1, 2) positions (frozen after the end)
    walls: np.ndarray  # (N, g, g)
    goals: np.ndarray  # (N, 2)
    # first G episodes: theta, lidar ranges/hits, actions per step; with unmapped obstacles also
    # "obstacles" (G, T+1, M, 2), their centres at every step
    gif: dict[str, np.ndarray]
    # (N, M, 3) x, y, radius of each episode's unmapped obstacles at its start (radius 0: absent;
    # the env's static ones first, ``EnvConfig.obstacles``); None for an env without them
    obstacles: np.ndarray | None = None
    # (K, g, g) the env's plan field (cells to the goal's cell) of episodes 0..K-1, an
    # ``observe_plan`` env's: the plan the pictures draw (``PLAN_KEPT``); None otherwise
    plan_fields: np.ndarray | None = None


class EvalStopped(Exception):
    """``progress`` asked to stop between batches; ``done`` episodes of ``total`` had run."""

    def __init__(self, done: int, total: int):
        super().__init__(f"evaluation stopped after {done} of {total} episodes")
        self.done = done
        self.total = total


def _runner(env, agent: Agent, batch: int, gif: int, deterministic: bool, runtime: Runtime):
    """The compiled evaluation of ``batch`` episodes: f(keys, act_keys, env_params, payload),
    compiled once per runtime for agents with the same static key."""
    cache_key = ("eval-episodes", env, agent.static_key(), batch, gif, deterministic)
    return runtime.program(cache_key, lambda: jax.jit(_episodes_program(env, agent, batch, gif,
                                                                        deterministic)))  # fmt: skip


def _episodes_program(env, agent: Agent, batch: int, gif: int, deterministic: bool):
    n, g = batch, gif

    def run(keys, act_keys, params, payload):
        obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
        # the planners a few episodes at a time: their fields are (grid * 5)^2 nodes each
        ref = jax.lax.map(
            lambda a: shortest_path_length(
                a[0], a[1], a[2], params.room_size, params.robot_radius, params.goal_radius,
                reach=env.reach, cols=env.cols,
            ),
            (states.row_bits, states.pos, states.goal), batch_size=plan_batch(env.config.grid_shape, n),
        )
        agent_state = agent.init(env, params, states, payload)
        start = jnp.ones((n,), bool)
        done = jnp.zeros((n,), bool)
        zeros_i, zeros_f = jnp.zeros((n,), jnp.int32), jnp.zeros((n,), jnp.float32)
        carry0 = (states, obs, agent_state, start, done, zeros_i, zeros_f, zeros_i, zeros_f,
                  jnp.zeros((n,), bool), jnp.zeros((n,), bool))  # fmt: skip

        def step(carry, key):
            (states, obs, agent_state, start, done, steps, ret, coll, plen, success, trunc) = carry
            agent_state, action = agent.act(
                agent_state, obs, states, start, key, deterministic, payload
            )
            obs2, states2, reward, d, info = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))(
                keys, states, action, params
            )
            alive = ~done
            keep = lambda new, old: jnp.where(  # noqa: E731
                alive.reshape(alive.shape + (1,) * (new.ndim - 1)), new, old
            )
            states2 = jax.tree.map(keep, states2, states)
            obs2 = keep(obs2, obs)
            carry = (
                states2, obs2, agent_state, jnp.zeros_like(start), done | (alive & d),
                steps + alive, ret + jnp.where(alive, reward, 0.0),
                coll + (alive & info["collision"]),
                plen + jnp.where(alive, jnp.linalg.norm(states2.pos - states.pos, axis=-1), 0.0),
                success | (alive & info["goal_reached"]), trunc | (alive & info["truncated"]),
            )  # fmt: skip
            people = None if states2.obstacles is None else states2.obstacles.pos[:g]
            rec = (states2.pos, states2.theta[:g], states2.lidar_ranges[:g], states2.lidar_hits[:g],
                   action[:g], people)  # fmt: skip
            return carry, rec

        final, (pos, theta, ranges, hits, actions, moved) = jax.lax.scan(step, carry0, act_keys)
        _, _, _, _, _, steps, ret, coll, plen, success, trunc = final
        first = (states.theta[:g], states.lidar_ranges[:g], states.lidar_hits[:g])
        obstacles = None if states.obstacles is None else (
            states.obstacles.pos, states.obstacles.radius, moved)  # fmt: skip
        plans = None if states.plan is None else states.plan[: min(n, max(g, PLAN_KEPT))]
        return (states.pos, states.walls, states.goal, ref, steps, ret, coll, plen, success,
                trunc, pos, theta, ranges, hits, actions, first, obstacles, plans)  # fmt: skip

    return run


def run_episodes(
    env, params, agent: Agent, cfg: EvalConfig,
    progress: Callable[[int, int], bool | None] | None = None, runtime: Runtime | None = None,
) -> Episodes:  # fmt: skip
    """Run ``cfg.episodes`` fixed-seed episodes of ``agent``, ``EVAL_BATCH`` at a time (the
    compiled program kept in ``runtime``; without one it is compiled for this call).

    Episode i starts from ``reset(fold_in(PRNGKey(seed), i))`` whatever the batch; a stochastic
    agent's per-step keys are those of the one-batch evaluation in the first batch and fold in the
    batch index after it. ``progress(done, total)`` is called after every batch and may return
    True to stop (``EvalStopped``).
    """
    n = cfg.episodes
    batch = min(n, EVAL_BATCH)
    g_total = min(cfg.gif_episodes, n)
    g = min(g_total, batch)
    t_max = int(env.config.max_steps)
    runner = _runner(env, agent, batch, g, cfg.deterministic, runtime_or_new(runtime))
    base = jax.random.PRNGKey(cfg.seed)
    act_base = jax.random.fold_in(base, 2**30)
    parts: list[tuple] = []
    for b in range(math.ceil(n / batch)):
        index = jnp.arange(b * batch, (b + 1) * batch)
        keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(index)
        act_keys = jax.random.split(act_base if b == 0 else jax.random.fold_in(act_base, b), t_max)
        parts.append(jax.device_get(runner(keys, act_keys, params, agent.payload)))
        done = min((b + 1) * batch, n)
        if progress is not None and progress(done, n) and done < n:
            raise EvalStopped(done, n)
    start_pos, walls, goals, ref, steps, ret, coll, plen, success, trunc = (
        np.concatenate([np.asarray(p[i]) for p in parts])[:n] for i in range(10)
    )
    pos = np.concatenate([np.asarray(p[10]) for p in parts], axis=1)[:, :n]  # (T, N, 2)
    traj = np.concatenate([start_pos[None], pos], axis=0).swapaxes(0, 1)
    # the pictures' episodes: the first g of each batch, as far as the first g_total episodes
    # (with no picture episodes, the first batch's empty slices keep the shapes)
    gif_parts = [p for b, p in enumerate(parts) if b * batch < g_total] or parts[:1]
    take = lambda i, axis: np.concatenate([np.asarray(p[i]) for p in gif_parts], axis=axis)  # noqa: E731
    first = [np.concatenate([np.asarray(p[15][k]) for p in gif_parts]) for k in range(3)]
    gif = {
        "theta": np.concatenate([first[0][None], take(11, 1)], axis=0).swapaxes(0, 1)[:g_total],
        "lidar_ranges": np.concatenate([first[1][None], take(12, 1)], axis=0).swapaxes(0, 1)[:g_total],
        "lidar_hits": np.concatenate([first[2][None], take(13, 1)], axis=0).swapaxes(0, 1)[:g_total],
        # (G, T, 2): action t -> pose t+1
        "actions": np.asarray(take(14, 1), np.float32).swapaxes(0, 1)[:g_total],
    }
    obstacles = None
    if parts[0][16] is not None:  # unmapped obstacles: where each episode put them, who moved
        at_start = np.concatenate([np.asarray(p[16][0]) for p in parts])[:n]  # (N, M, 2)
        radius = np.concatenate([np.asarray(p[16][1]) for p in parts])[:n]  # (N, M)
        obstacles = np.concatenate([at_start, radius[..., None]], axis=-1).astype(np.float32)
        moved = np.concatenate([np.asarray(p[16][2]) for p in gif_parts], axis=1)  # (T, G, M, 2)
        first_pos = np.concatenate([np.asarray(p[16][0])[:g] for p in gif_parts])  # (G, M, 2)
        gif["obstacles"] = np.concatenate([first_pos[None], moved], axis=0).swapaxes(0, 1)[:g_total]
    # the first batch holds episodes 0..K-1, whose plans the pictures draw
    plans = None if parts[0][17] is None else np.asarray(parts[0][17])[: min(n, batch)]
    return Episodes(
        success=success, truncated=trunc, steps=steps, returns=ret, collisions=coll,
        path_length=plen, reference_length=ref, trajectories=traj, walls=walls, goals=goals,
        gif=gif, obstacles=obstacles, plan_fields=plans,
    )  # fmt: skip


def _map_placements(config: EnvConfig, runtime: Runtime | None) -> dict[str, Any]:
    """For maps: where each map's picture lies in the room (its lower-left corner at cell (1, 1),
    its size in metres), and under ``_rooms`` each map's wall grid."""
    from quicknav_core.env.maps import load_map
    from quicknav_core.env.room_sources import MapRooms, room_source

    source = room_source(config, runtime)
    if not isinstance(source, MapRooms):
        return {}
    out: dict[str, Any] = {"_rooms": {}}
    read = {k: v for k, v in source.read_options().items() if k != "unknown_free"}
    for split in ("train", "test"):
        for name, room in zip(source.files(split), source.rooms(split), strict=True):
            m = load_map(source.path(name), **read)
            width_m, height_m = m.size_m
            out[name] = {"x0": config.cell_size, "y0": config.cell_size,
                         "width_m": round(width_m, 6), "height_m": round(height_m, 6)}  # fmt: skip
            out["_rooms"][name] = np.asarray(room, dtype=bool)
    return out


def _unmapped(ep: Episodes, config: EnvConfig, i: int, n: int) -> dict[str, Any]:
    """Picture episode ``i``'s global plan (``plan``: [x, y] points, an ``observe_plan`` env) and
    its unmapped obstacles present (``boxes``: [x, y, radius] each; ``people``: radius and x, y
    at each of the ``n`` steps), in metres."""
    out: dict[str, Any] = {}
    if (path := episode_plan(ep, config, i)) is not None:
        out["plan"] = np.round(path.astype(np.float64), 3).tolist()
    if ep.obstacles is not None and "obstacles" in ep.gif:
        n_static = config.obstacles.static
        at = ep.gif["obstacles"][i, :n].astype(np.float64)  # (n, M, 2)
        radius = ep.obstacles[i, :, 2].astype(np.float64)
        out["boxes"] = [[round(float(x), 3), round(float(y), 3), round(float(r), 3)]
                        for (x, y), r in zip(at[0, :n_static], radius[:n_static], strict=True) if r > 0]
        out["people"] = [{"radius": round(float(radius[k]), 3), "x": np.round(at[:, k, 0], 3).tolist(),
                          "y": np.round(at[:, k, 1], 3).tolist()}
                         for k in range(n_static, radius.shape[0]) if radius[k] > 0]  # fmt: skip
    return out


def episode_plan(ep: Episodes, config: EnvConfig, i: int) -> np.ndarray | None:
    """Episode ``i``'s global plan from its start ((K, 2) points), None for an env that does not
    observe one: down the env's own plan field where the evaluation kept it (``PLAN_KEPT``),
    else planned again in NumPy (``plan_path``)."""
    if not config.observe_plan:
        return None
    start, goal = ep.trajectories[i, 0], ep.goals[i]
    if ep.plan_fields is not None and i < ep.plan_fields.shape[0]:
        from quicknav_core.env.plan_np import plan_polyline_np

        cell = config.cell_size
        return plan_polyline_np(ep.plan_fields[i], _cell_of(start, cell, ep.plan_fields.shape[1:]),
                                start, goal, cell)  # fmt: skip
    return plan_path(config, ep.walls[i], start, goal)


def plan_path(config: EnvConfig, walls: np.ndarray, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """(K, 2) x, y of the global plan an ``observe_plan`` env gives an episode that starts at
    ``start``: the centres of the cells down the plan's field from the start's cell (the NumPy
    twin's planner, the env's rule: cells the robot's disc fits in, 8-connected, no corner
    cutting), then the goal. Just the start when the goal cannot be reached."""
    from quicknav_core.env.clearance import disc_fits
    from quicknav_core.env.numpy_env import cell_field_np
    from quicknav_core.env.plan_np import plan_polyline_np

    walls = np.asarray(walls, dtype=bool)
    cell = config.cell_size
    usable = disc_fits(walls, cell, config.robot_radius) if config.collision_reach else ~walls
    field = cell_field_np(usable, _cell_of(goal, cell, walls.shape))
    return plan_polyline_np(field, _cell_of(start, cell, walls.shape), start, goal, cell)


def _cell_of(xy, cell: float, shape: tuple[int, ...]) -> np.ndarray:
    """(row, col) of the cell holding the point ``xy`` on a (rows, cols) grid of ``cell`` m."""
    rc = np.floor(np.asarray(xy, np.float64)[::-1] / cell).astype(np.int64)
    return np.clip(rc, 0, np.asarray(shape[:2]) - 1)


def outcome(ep: Episodes, i: int, config: EnvConfig) -> str:
    """How episode ``i`` ended, in words: reached, collided (when a collision ends an episode) or
    timed out (the pictures' titles and the browser's replay say it so)."""
    if ep.success[i]:
        return "reached"
    if config.end_on_collision and ep.collisions[i] > 0 and ep.steps[i] < config.max_steps:
        return "collided"
    return "timed out"


def replay_data(ep: Episodes, config: EnvConfig, agent_name: str, runtime: Runtime | None = None
                ) -> dict[str, Any]:  # fmt: skip
    """The picture episodes step by step, for the browser's replay (``replay.json``): walls as
    rows of '#'/'.' (row = y), poses and lidar ranges rounded to millimetres, hit codes."""
    from quicknav_core.env.constants import HIT_GOAL, HIT_NONE, HIT_WALL, beam_angles

    episodes = []
    for i in range(ep.gif["theta"].shape[0]):
        n = int(ep.steps[i]) + 1  # the start pose and one pose per step taken
        walls = ep.walls[i]
        episodes.append({
            "index": i,
            "success": bool(ep.success[i]),
            "outcome": outcome(ep, i, config),
            "steps": int(ep.steps[i]),
            "return": round(float(ep.returns[i]), 4),
            "walls": ["".join("#" if w else "." for w in row) for row in walls],
            "goal": [round(float(v), 4) for v in ep.goals[i]],
            "x": np.round(ep.trajectories[i, :n, 0], 3).tolist(),
            "y": np.round(ep.trajectories[i, :n, 1], 3).tolist(),
            "theta": np.round(ep.gif["theta"][i, :n], 4).tolist(),
            "ranges": np.round(ep.gif["lidar_ranges"][i, :n], 3).tolist(),
            "hits": ep.gif["lidar_hits"][i, :n].astype(int).tolist(),
            **_unmapped(ep, config, i, n),
        })  # fmt: skip
    maps = _map_placements(config, runtime)
    if maps:  # which map each episode drove in (its walls are that map's room)
        rooms = {name: room.tobytes() for name, room in maps.pop("_rooms").items()}
        for e, walls in zip(episodes, ep.walls, strict=False):
            e["map"] = next((n for n, r in rooms.items() if r == np.asarray(walls, dtype=bool).tobytes()), None)
    return {
        "agent": agent_name,
        **({"maps": maps} if maps else {}),
        "room_size": config.room_size,
        "grid_size": config.grid_size,
        "robot_radius": config.robot_radius,
        "goal_radius": config.goal_radius,
        "dt": config.dt,
        "beam_angles": np.round(beam_angles(config.lidar_beams, config.lidar_fov_deg), 5).tolist(),
        "hit_codes": {"none": HIT_NONE, "wall": HIT_WALL, "goal": HIT_GOAL},
        "episodes": episodes,
    }
