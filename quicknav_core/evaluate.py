"""Held-out evaluation with navigation metrics: success (95% CI), steps to goal, SPL, collisions.

Episodes run on the ``test`` room bank with fixed episode seeds: episode i starts from
``reset(fold_in(PRNGKey(seed), i))``, so two agents evaluated with the same seed and env config
face exactly the same rooms, starts and goals. All episodes run at once (vmapped, one ``lax.scan``
over the step limit); finished episodes are frozen. Actions are deterministic unless asked.

SPL (Anderson et al. 2018) = mean_i S_i * l_i / max(p_i, l_i), with p_i the path the robot drove
until it reached the goal disc and l_i the shortest disc path into the goal disc
(``planning.shortest_path_length``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from quicknav_core.config import EnvConfig
from quicknav_core.planning import oracle_action, oracle_plan, shortest_path_length


class EvalConfig(BaseModel):
    """How to evaluate."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    episodes: int = Field(100, ge=1, le=100_000)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    split: Literal["train", "test"] = "test"
    deterministic: bool = True
    gif_episodes: int = Field(
        3, ge=0, le=1024, description="episodes whose per-step poses, lidar and actions are kept"
    )
    pictures: bool = True


# --------------------------------------------------------------------------- agents
class Agent:
    """What evaluation needs from a policy: per-episode state and a batched act.

    ``payload`` is the traced data (network parameters); everything else is static and named by
    ``static_key()``, so agents that differ only in payload share one compiled evaluation.
    """

    name = "agent"

    @property
    def payload(self) -> Any:
        return ()

    def static_key(self) -> Any:
        return (type(self).__name__,)

    def init(self, env, params, states, payload) -> Any:
        return ()

    def act(self, agent_state, obs, states, start, key, deterministic: bool, payload):
        raise NotImplementedError


class RandomAgent(Agent):
    name = "random"

    def act(self, agent_state, obs, states, start, key, deterministic, payload):
        return agent_state, jax.random.uniform(key, (obs.shape[0], 2), minval=-1.0, maxval=1.0)


class OracleAgent(Agent):
    """Follows the shortest disc path with the real differential drive (``planning``)."""

    name = "oracle"

    def __init__(self, room_size: float, goal_radius: float):
        self.room_size = room_size
        self.goal_radius = goal_radius

    def static_key(self):
        return ("oracle", self.room_size, self.goal_radius)

    def init(self, env, params, states, payload):
        plan = jax.vmap(lambda rb, g: oracle_plan(rb, g, params.room_size, params.robot_radius))
        return plan(states.row_bits, states.goal)

    def act(self, plans, obs, states, start, key, deterministic, payload):
        act = jax.vmap(
            lambda pl, p, th, g: oracle_action(pl, p, th, g, self.room_size, self.goal_radius)
        )
        return plans, act(plans, states.pos, states.theta, states.goal)


class PolicyAgent(Agent):
    """A trained policy (``quicknav_core.train.Policy``)."""

    def __init__(self, policy, name: str = "policy"):
        self.policy = policy
        self.name = name

    @property
    def payload(self):
        return self.policy.params

    def static_key(self):
        return ("policy", self.policy.kind, self.policy.module)

    def _policy(self, payload):
        return dataclasses.replace(self.policy, params=payload)

    def init(self, env, params, states, payload):
        return self.policy.initial_carry(states.pos.shape[0])

    def act(self, carry, obs, states, start, key, deterministic, payload):
        return self._policy(payload).act(carry, obs, start, key, deterministic)


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


def _runner(env, agent: Agent, cfg: EvalConfig):
    """The compiled evaluation for (env, agent's static part, cfg): f(keys, env_params, payload)."""
    cache_key = (
        env,
        agent.static_key(),
        cfg.episodes,
        cfg.seed,
        cfg.deterministic,
        cfg.gif_episodes,
    )
    if cache_key in _RUNNERS:
        return _RUNNERS[cache_key]
    n = cfg.episodes
    g = min(cfg.gif_episodes, n)
    t_max = int(env.config.max_steps)

    def run(keys, params, payload):
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
        act_keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(cfg.seed), 2**30), t_max)

        def step(carry, key):
            (states, obs, agent_state, start, done, steps, ret, coll, plen, success, trunc) = carry
            agent_state, action = agent.act(
                agent_state, obs, states, start, key, cfg.deterministic, payload
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
        return (
            states,
            ref,
            steps,
            ret,
            coll,
            plen,
            success,
            trunc,
            pos,
            theta,
            ranges,
            hits,
            actions,
            first,
        )

    _RUNNERS[cache_key] = jax.jit(run)
    return _RUNNERS[cache_key]


def run_episodes(env, params, agent: Agent, cfg: EvalConfig) -> Episodes:
    """Run ``cfg.episodes`` fixed-seed episodes of ``agent`` at once."""
    n = cfg.episodes
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(cfg.seed), i))(jnp.arange(n))
    out = jax.device_get(_runner(env, agent, cfg)(keys, params, agent.payload))
    (states, ref, steps, ret, coll, plen, success, trunc, pos, theta, ranges, hits, actions,
     first) = out  # fmt: skip
    traj = np.concatenate([np.asarray(states.pos)[None], np.asarray(pos)], axis=0).swapaxes(0, 1)
    gif = {
        "theta": np.concatenate([first[0][None], theta], axis=0).swapaxes(0, 1),
        "lidar_ranges": np.concatenate([first[1][None], ranges], axis=0).swapaxes(0, 1),
        "lidar_hits": np.concatenate([first[2][None], hits], axis=0).swapaxes(0, 1),
        "actions": np.asarray(actions, np.float32).swapaxes(
            0, 1
        ),  # (G, T, 2): action t -> pose t+1
    }
    return Episodes(
        success=np.asarray(success), truncated=np.asarray(trunc), steps=np.asarray(steps),
        returns=np.asarray(ret), collisions=np.asarray(coll), path_length=np.asarray(plen),
        reference_length=np.asarray(ref), trajectories=traj, walls=np.asarray(states.walls),
        goals=np.asarray(states.goal), gif=gif,
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


def agent_for(policy: str, env_config: EnvConfig) -> Agent:
    """A built-in baseline: 'random' or 'oracle'."""
    if policy == "random":
        return RandomAgent()
    if policy == "oracle":
        return OracleAgent(env_config.room_size, env_config.goal_radius)
    raise ValueError(f"policy={policy!r}: allowed values are 'random' and 'oracle'")


def agent_from_run(path: Path) -> tuple[Agent, EnvConfig, dict[str, Any]]:
    """The trained policy of a run folder (or its checkpoint folder), with the run's env config."""
    from quicknav_core.train.run import CHECKPOINT_DIR, load_run

    path = Path(path)
    run_dir = path.parent if path.name == CHECKPOINT_DIR else path
    config, trainer, state, meta = load_run(run_dir)
    return (
        PolicyAgent(trainer.policy(state), name=f"{config.trainer_kind}:{run_dir.name}"),
        config.env,
        meta,
    )


def evaluate(
    env_config: EnvConfig, agent: Agent, cfg: EvalConfig, out_dir: Path | None = None
) -> tuple[dict[str, Any], Episodes]:
    """Evaluate ``agent``; with ``out_dir`` write eval.json, trajectories.png and episodes.gif."""
    env, params = env_config.build(cfg.split)
    ep = run_episodes(env, params, agent, cfg)
    step_length = env_config.max_wheel_speed * env_config.dt
    result = {
        "agent": agent.name,
        "eval_config": cfg.model_dump(),
        "env_config": env_config.model_dump(mode="json"),
        "metrics": summarize(ep, env_config.max_steps, step_length),
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
        if cfg.pictures:
            draw_trajectories(ep, env_config, out_dir / "trajectories.png", title=agent.name)
            if cfg.gif_episodes:
                draw_gif(ep, env_config, out_dir / "episodes.gif", title=agent.name)
    return result, ep


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
