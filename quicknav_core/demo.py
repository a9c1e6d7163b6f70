"""`quicknav env demo` and `quicknav env rooms`: one episode as PNG + GIF, and the rooms figure."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quicknav_core.config import EnvConfig


@dataclass
class DemoResult:
    png: Path
    gif: Path
    steps: int
    goal_reached: bool
    episode_return: float
    collisions: int


def run_demo(
    config: EnvConfig, out_dir: Path, policy: str = "scripted", seed: int = 0
) -> DemoResult:
    """Run one episode of the JAX env (train rooms) and draw it."""
    import jax

    from quicknav_core.env import render
    from quicknav_core.scripted import GridPathFollower

    if policy not in ("scripted", "random"):
        raise ValueError(f"policy={policy!r}: allowed values are 'scripted' and 'random'")
    env, params = config.build("train")
    step = jax.jit(env.step_env)
    key = jax.random.PRNGKey(seed)
    key, k_reset = jax.random.split(key)
    _, state = env.reset(k_reset, params)
    rng = np.random.default_rng(seed)
    follower = GridPathFollower(np.asarray(state.walls), np.asarray(state.goal), config.cell_size)
    snaps = [render.as_snapshot(state)]
    total, done, info = 0.0, False, {}
    while not done:
        if policy == "scripted":
            action = follower(np.asarray(state.pos), float(state.theta))
        else:
            action = rng.uniform(-1.0, 1.0, 2).astype(np.float32)
        key, k = jax.random.split(key)
        _, state, reward, done, info = step(k, state, action, params)
        total += float(reward)
        done = bool(done)
        snaps.append(render.as_snapshot(state))
    out_dir.mkdir(parents=True, exist_ok=True)
    reached = bool(info["goal_reached"])
    title = f"{policy} policy: {'goal reached' if reached else 'timed out'}, return {total:.1f}"
    traj = np.array([s["pos"] for s in snaps])
    png = render.save_png(
        render.render_frame(snaps[-1], config, traj, title=title, size_px=480), out_dir / "demo.png"
    )
    frames = render.episode_frames(snaps[:: max(1, len(snaps) // 150)], config, title=policy)
    gif = render.save_gif(frames, out_dir / "demo.gif", fps=12)
    return DemoResult(png, gif, int(state.time), reached, total, int(state.collisions))


def draw_rooms(
    out: Path, grid_sizes=(4, 8, 16), per_row: int = 5, seed: int = 0, room_size: float = 8.0
) -> Path:
    """The paper's Figure 1: generated rooms for several grid sizes."""
    from quicknav_core.env import render
    from quicknav_core.env.rooms import make_room_bank

    rooms = {}
    for g in grid_sizes:
        radius = min(0.15, 0.45 * room_size / g)
        cfg = EnvConfig(
            grid_size=g,
            room_size=room_size,
            room_seed=seed,
            train_rooms=per_row,
            robot_radius=radius,
            max_wheel_speed=min(1.0, room_size / g / 0.1),
        )
        rooms[g] = list(make_room_bank(cfg, "train"))
    return render.rooms_figure(rooms, room_size, out)
