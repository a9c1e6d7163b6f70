"""Held-out evaluation with navigation metrics: success (95% CI), steps to goal, SPL, collisions.

Episodes run on the ``test`` room bank with fixed episode seeds: episode i starts from
``reset(fold_in(PRNGKey(seed), i))``, so two agents evaluated with the same seed and env config
face exactly the same rooms, starts and goals. All episodes run at once (vmapped, one ``lax.scan``
over the step limit); finished episodes are frozen. Actions are deterministic unless asked.

SPL (Anderson et al. 2018) = mean_i S_i * l_i / max(p_i, l_i), with p_i the path the robot drove
until it reached the goal disc and l_i the shortest disc path into the goal disc
(``planning.shortest_path_length``).

``run_eval(EvalConfig)`` runs what a resolved config names (a trained policy or a baseline);
``evaluate(env_config, agent, cfg)`` runs any ``Agent`` (``scripted`` holds the baselines).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.config import EnvConfig, EvalConfig
from quicknav_core.config.eval import EVAL_BATCH
from quicknav_core.eval.agents import Agent, PolicyAgent, agent_from_run
from quicknav_core.eval.planning import shortest_path_length
from quicknav_core.eval.scripted import baseline_agent

__all__ = ["Agent", "Episodes", "PolicyAgent", "agent_from_run", "by_path_length", "evaluate",
           "make_agent", "run_episodes", "run_eval", "spl", "summarize", "wilson_interval"]  # fmt: skip


# --------------------------------------------------------------------------- episodes
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
    gif: dict[str, np.ndarray]  # first G episodes: theta, lidar ranges/hits per step


_RUNNERS: dict[Any, Any] = {}


class EvalStopped(Exception):
    """``progress`` asked to stop between batches; ``done`` episodes of ``total`` had run."""

    def __init__(self, done: int, total: int):
        super().__init__(f"evaluation stopped after {done} of {total} episodes")
        self.done = done
        self.total = total


def _runner(env, agent: Agent, batch: int, gif: int, deterministic: bool):
    """The compiled evaluation of ``batch`` episodes: f(keys, act_keys, env_params, payload)."""
    cache_key = (env, agent.static_key(), batch, gif, deterministic)
    if cache_key in _RUNNERS:
        return _RUNNERS[cache_key]
    n, g = batch, gif

    def run(keys, act_keys, params, payload):
        obs, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
        ref = jax.vmap(
            lambda rb, s, goal: shortest_path_length(
                rb, s, goal, params.room_size, params.robot_radius, params.goal_radius
            )
        )(states.row_bits, states.pos, states.goal)
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
            rec = (states2.pos, states2.theta[:g], states2.lidar_ranges[:g], states2.lidar_hits[:g],
                   action[:g])  # fmt: skip
            return carry, rec

        final, (pos, theta, ranges, hits, actions) = jax.lax.scan(step, carry0, act_keys)
        _, _, _, _, _, steps, ret, coll, plen, success, trunc = final
        first = (states.theta[:g], states.lidar_ranges[:g], states.lidar_hits[:g])
        return (states.pos, states.walls, states.goal, ref, steps, ret, coll, plen, success,
                trunc, pos, theta, ranges, hits, actions, first)  # fmt: skip

    _RUNNERS[cache_key] = jax.jit(run)
    return _RUNNERS[cache_key]


def run_episodes(
    env, params, agent: Agent, cfg: EvalConfig,
    progress: Callable[[int, int], bool | None] | None = None,
) -> Episodes:  # fmt: skip
    """Run ``cfg.episodes`` fixed-seed episodes of ``agent``, ``EVAL_BATCH`` at a time.

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
    runner = _runner(env, agent, batch, g, cfg.deterministic)
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
    return Episodes(
        success=success, truncated=trunc, steps=steps, returns=ret, collisions=coll,
        path_length=plen, reference_length=ref, trajectories=traj, walls=walls, goals=goals,
        gif=gif,
    )  # fmt: skip


# --------------------------------------------------------------------------- metrics
def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def spl(success: np.ndarray, path_length: np.ndarray, reference_length: np.ndarray) -> float:
    """Success weighted by (normalised inverse) path length."""
    s = success.astype(np.float64)
    ref = reference_length.astype(np.float64)
    denom = np.maximum(np.maximum(path_length, ref), 1e-9)
    return float(np.mean(s * ref / denom))


def _mean_std(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"mean": math.nan, "std": math.nan}
    return {"mean": float(np.mean(x)), "std": float(np.std(x))}


def summarize(ep: Episodes, max_steps: int, step_length: float) -> dict[str, Any]:
    """All metrics of a set of episodes."""
    n = int(ep.success.size)
    k = int(ep.success.sum())
    lo, hi = wilson_interval(k, n)
    steps_all = np.where(ep.success, ep.steps, max_steps)
    lower_bound = np.ceil(ep.reference_length / step_length)
    return {
        "episodes": n,
        "success_rate": k / n,
        "success_ci95": [lo, hi],
        "steps_to_goal_successes": _mean_std(ep.steps[ep.success]),
        "steps_to_goal_failures_as_limit": _mean_std(steps_all),
        "return": _mean_std(ep.returns),
        "collisions_per_episode": float(np.mean(ep.collisions)),
        "timeout_rate": float(np.mean(ep.truncated)),
        "spl": spl(ep.success, ep.path_length, ep.reference_length),
        "path_length_successes": _mean_std(ep.path_length[ep.success]),
        "reference_length": _mean_std(ep.reference_length),
        "steps_lower_bound": _mean_std(lower_bound),
    }


# Difficulty bins: the oracle's shortest path to the goal disc, as fractions of the room's side
PATH_BIN_EDGES = (0.0, 0.25, 0.5, 0.75, 1.0, math.inf)


def by_path_length(ep: Episodes, room_size: float, max_steps: int) -> list[dict[str, Any]]:
    """Success, its 95 % interval, SPL and steps (failures as the limit) per difficulty bin: the
    episodes grouped by the oracle's shortest-path length (metres). Empty bins are left out."""
    edges = [e * room_size for e in PATH_BIN_EDGES]
    rows = []
    for lo, hi in itertools.pairwise(edges):
        inside = (ep.reference_length >= lo) & (ep.reference_length < hi)
        n = int(inside.sum())
        if n == 0:
            continue
        k = int(ep.success[inside].sum())
        steps = np.where(ep.success[inside], ep.steps[inside], max_steps)
        rows.append({
            "path_m": [round(lo, 3), None if math.isinf(hi) else round(hi, 3)],
            "episodes": n, "success_rate": k / n, "success_ci95": list(wilson_interval(k, n)),
            "spl": spl(ep.success[inside], ep.path_length[inside], ep.reference_length[inside]),
            "steps_failures_as_limit": float(np.mean(steps)),
        })  # fmt: skip
    return rows


def draw_difficulty(rows: list[dict[str, Any]], path: Path, title: str = "") -> Path:
    """Success (with its 95 % interval) and SPL against the oracle's path length, per bin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['path_m'][0]:g}-{r['path_m'][1]:g} m" if r["path_m"][1] is not None
              else f">= {r['path_m'][0]:g} m" for r in rows]  # fmt: skip
    x = np.arange(len(rows))
    success = np.array([r["success_rate"] for r in rows])
    ci = np.array([r["success_ci95"] for r in rows]).reshape(-1, 2)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.errorbar(x, success, yerr=[success - ci[:, 0], ci[:, 1] - success], marker="o",
                capsize=4, label="success rate (95 % CI)", color="tab:green")  # fmt: skip
    ax.plot(x, [r["spl"] for r in rows], marker="s", label="SPL", color="tab:blue")
    for xi, r in zip(x, rows, strict=True):
        ax.annotate(f"n={r['episodes']}", (xi, 0.98), ha="center", va="top", fontsize=8, color="0.4")
    ax.set_xticks(x, labels)
    ax.set_ylim(0, 1.05)
    ax.set_xlabel("oracle shortest path to the goal")
    ax.set_title(f"{title}: by difficulty" if title else "by difficulty", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="center right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def evaluate(
    env_config: EnvConfig, agent: Agent, cfg: EvalConfig, out_dir: Path | None = None,
    progress: Callable[[int, int], bool | None] | None = None,
) -> tuple[dict[str, Any], Episodes]:  # fmt: skip
    """Evaluate ``agent``; with ``out_dir`` write eval.json (with success and SPL per difficulty
    bin), replay.json, trajectories.png, difficulty.png and episodes.gif.

    ``progress(done, total)`` after every batch of episodes may return True to stop
    (``EvalStopped``: nothing is written).
    """
    env, params = env_config.build(cfg.split)
    ep = run_episodes(env, params, agent, cfg, progress)
    step_length = env_config.max_wheel_speed * env_config.dt
    result = {
        "agent": agent.name,
        "eval_config": cfg.model_dump(mode="json"),
        "env_config": env_config.model_dump(mode="json"),
        "metrics": summarize(ep, env_config.max_steps, step_length),
        "by_path_length": by_path_length(ep, env_config.room_size, env_config.max_steps),
        "per_episode": {
            "success": ep.success.tolist(),
            "steps": ep.steps.tolist(),
            "return": [round(float(r), 4) for r in ep.returns],
            "collisions": ep.collisions.tolist(),
            "path_length": [round(float(p), 4) for p in ep.path_length],
            "reference_length": [round(float(r), 4) for r in ep.reference_length],
        },
    }
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "eval.json").write_text(json.dumps(result, indent=2))
        if ep.gif["theta"].shape[0]:
            (out_dir / "replay.json").write_text(json.dumps(replay_data(ep, env_config, agent.name)))
        if cfg.pictures:
            draw_trajectories(ep, env_config, out_dir / "trajectories.png", title=agent.name)
            draw_difficulty(result["by_path_length"], out_dir / "difficulty.png", title=agent.name)
            if cfg.gif_episodes:
                draw_gif(ep, env_config, out_dir / "episodes.gif", title=agent.name)
    return result, ep


def replay_data(ep: Episodes, config: EnvConfig, agent_name: str) -> dict[str, Any]:
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
            "steps": int(ep.steps[i]),
            "return": round(float(ep.returns[i]), 4),
            "walls": ["".join("#" if w else "." for w in row) for row in walls],
            "goal": [round(float(v), 4) for v in ep.goals[i]],
            "x": np.round(ep.trajectories[i, :n, 0], 3).tolist(),
            "y": np.round(ep.trajectories[i, :n, 1], 3).tolist(),
            "theta": np.round(ep.gif["theta"][i, :n], 4).tolist(),
            "ranges": np.round(ep.gif["lidar_ranges"][i, :n], 3).tolist(),
            "hits": ep.gif["lidar_hits"][i, :n].astype(int).tolist(),
        })  # fmt: skip
    return {
        "agent": agent_name,
        "room_size": config.room_size,
        "grid_size": config.grid_size,
        "robot_radius": config.robot_radius,
        "goal_radius": config.goal_radius,
        "dt": config.dt,
        "beam_angles": np.round(beam_angles(config.lidar_beams, config.lidar_fov_deg), 5).tolist(),
        "hit_codes": {"none": HIT_NONE, "wall": HIT_WALL, "goal": HIT_GOAL},
        "episodes": episodes,
    }


def make_agent(cfg: EvalConfig, run_dir: Path | str | None = None) -> tuple[Agent, EnvConfig]:
    """The agent an EvalConfig names and the env it runs in: a baseline in ``cfg.env`` (default
    env if unset), or the trained policy of ``run_dir`` (default: ``cfg.source`` read as a run
    folder) in ``cfg.env`` or else the run's own env."""
    if cfg.policy != "trained":
        env = cfg.env or EnvConfig()
        return baseline_agent(cfg.policy, env), env
    where = run_dir if run_dir is not None else cfg.source
    if where is None:
        raise ValueError("policy='trained' needs a source: the run folder of the trained policy")
    agent, run_env, _ = agent_from_run(Path(where))
    return agent, cfg.env or run_env


def run_eval(
    cfg: EvalConfig, out_dir: Path | None = None, run_dir: Path | str | None = None,
    progress: Callable[[int, int], bool | None] | None = None,
) -> tuple[dict[str, Any], Episodes]:  # fmt: skip
    """Evaluate what a (resolved) EvalConfig names; see ``make_agent`` and ``evaluate``."""
    agent, env = make_agent(cfg, run_dir)
    return evaluate(env, agent, cfg, out_dir, progress)


# --------------------------------------------------------------------------- pictures
def draw_trajectories(ep: Episodes, config: EnvConfig, path: Path, title: str = "") -> Path:
    """3x3 grid of episodes with their trajectories (the paper's trajectory figures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from quicknav_core.env.render import GOAL_COLOUR, PATH_COLOUR, draw_room

    count = min(9, ep.success.size)
    fig, axes = plt.subplots(3, 3, figsize=(9, 9.4))
    for i, ax in enumerate(axes.flat):
        if i >= count:
            ax.axis("off")
            continue
        draw_room(ax, ep.walls[i], config.room_size)
        traj = ep.trajectories[i, : ep.steps[i] + 1]
        ax.plot(traj[:, 0], traj[:, 1], color=PATH_COLOUR, lw=1.6)
        ax.plot(*traj[0], "o", color=PATH_COLOUR, ms=6)
        ax.add_patch(plt.Circle(ep.goals[i], config.goal_radius, color=GOAL_COLOUR, alpha=0.4))
        ax.plot(*ep.goals[i], "*", color=GOAL_COLOUR, ms=12)
        outcome = "reached" if ep.success[i] else "timed out"
        ax.set_title(f"episode {i + 1}: {outcome}, {ep.steps[i]} steps", fontsize=9)
    fig.suptitle(f"{title}: held-out test rooms", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def draw_gif(
    ep: Episodes, config: EnvConfig, path: Path, title: str = "", max_frames: int = 60
) -> Path:
    """A GIF of the first episodes with lidar rays, one after the other."""
    from quicknav_core.env.render import render_frame, save_gif

    frames = []
    for i in range(ep.gif["theta"].shape[0]):
        length = int(ep.steps[i]) + 1
        stride = max(1, math.ceil(length / max_frames))
        for t in [*range(0, length, stride), length - 1]:
            snap = {
                "walls": ep.walls[i], "pos": ep.trajectories[i, t], "theta": ep.gif["theta"][i, t],
                "goal": ep.goals[i], "lidar_ranges": ep.gif["lidar_ranges"][i, t],
                "lidar_hits": ep.gif["lidar_hits"][i, t],
            }  # fmt: skip
            frames.append(render_frame(snap, config, ep.trajectories[i, : t + 1],
                                       title=f"{title} episode {i + 1}  t={t}", size_px=320))  # fmt: skip
    return save_gif(frames, path, fps=10)
