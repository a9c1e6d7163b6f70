"""`quicknav env`: look at the environment: a demo episode (PNG + GIF) and generated rooms."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from quicknav_cli.common import (
    EnvSetOpt,
    admitted,
    console,
    enable_compilation_cache,
    fail,
    read_json,
    sets,
)
from quicknav_core.config import EnvConfig

app = typer.Typer(
    help="Look at the environment: demo episodes and generated rooms.", no_args_is_help=True
)

ConfigOpt = Annotated[
    Path | None,
    typer.Option("--config", help="EnvConfig JSON file (fields not given keep defaults)."),
]
# the demo's policies: a scripted one (the oracle: shortest disc path, real drive) or random
DEMO_POLICIES = ("oracle", "scripted", "random")


def env_config(config: Path | None, overrides: list[str] | None, on_map: Path | None = None) -> EnvConfig:
    """EnvConfig from an optional JSON file plus --set overrides, laid on ``on_map`` as
    ``quicknav eval --map`` lays it; exits with a clear message if bad."""
    from quicknav_cli.common import resolved
    from quicknav_core.config import resolve_eval

    data = read_json(config) if config else {}
    # the env of a baseline evaluation is resolved exactly like this: one path for every door
    request = {"policy": "random", "env": {**data, **sets(overrides)}}
    if on_map is None:
        return resolved(resolve_eval, request).env
    from quicknav_cli.eval import map_layer

    request["map"] = str(on_map)
    return resolved(resolve_eval, request, flags={"map": "--map"}, map_env=map_layer()).env


@dataclass
class DemoResult:
    png: Path
    gif: Path
    steps: int
    goal_reached: bool
    episode_return: float
    collisions: int


def run_demo(config: EnvConfig, out_dir: Path, policy: str = "oracle", seed: int = 0,
             runtime=None) -> DemoResult:  # fmt: skip
    """One episode in a train room, driven by the oracle (``scripted``) or at random, drawn."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.env import render
    from quicknav_core.eval.episodes import episode_plan
    from quicknav_core.eval.evaluate import run_episodes
    from quicknav_core.eval.pictures import episode_snapshot
    from quicknav_core.eval.scripted import baseline_agent

    if policy not in DEMO_POLICIES:
        raise ValueError(f"policy={policy!r}: allowed values are {', '.join(DEMO_POLICIES)}")
    agent = baseline_agent("random" if policy == "random" else "oracle", config)
    env, params = config.build("train", runtime)
    cfg = EvalConfig(episodes=1, seed=seed, split="train", gif_episodes=1, pictures=False)
    ep = run_episodes(env, params, agent, cfg, runtime=runtime)
    steps = int(ep.steps[0])
    plan = episode_plan(ep, config, 0)  # drawn when the env observes a plan; obstacles too
    snaps = [episode_snapshot(ep, config, 0, t, plan) for t in range(steps + 1)]
    reached = bool(ep.success[0])
    ret = float(ep.returns[0])
    out_dir.mkdir(parents=True, exist_ok=True)
    title = f"{policy} policy: {'goal reached' if reached else 'timed out'}, return {ret:.1f}"
    traj = ep.trajectories[0, : steps + 1]
    view = [render.room_view(ep.walls[0], config)]  # a long narrow map: frames of its shape
    png = render.save_png(render.render_frame(snaps[-1], config, traj, title=title,
                                              size_px=render.gif_frame_size(view, 480)), out_dir / "demo.png")  # fmt: skip
    frames = render.episode_frames(snaps[:: max(1, len(snaps) // 150)], config, title=policy,
                                   size_px=render.gif_frame_size(view, 360))  # fmt: skip
    gif = render.save_gif(frames, out_dir / "demo.gif", fps=12)
    return DemoResult(png, gif, steps, reached, ret, int(ep.collisions[0]))


def draw_rooms(
    out: Path, grid_sizes=(4, 8, 16), per_row: int = 5, seed: int = 0, room_size: float = 8.0
) -> Path:
    """The paper's Figure 1: generated rooms for several grid sizes, written to ``out`` (a PNG;
    ``.png`` added to a name without a suffix, as the picture is drawn)."""
    from quicknav_core.env import render
    from quicknav_core.env.room_sources import make_room_bank

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
    out = Path(out)
    return render.rooms_figure(rooms, room_size, out if out.suffix else out.with_suffix(".png"))


@app.command("demo")
def demo(
    out: Annotated[Path, typer.Option(help="Folder for demo.png and demo.gif.")] = Path("demo"),
    policy: Annotated[
        str,
        typer.Option(help="'oracle' (alias 'scripted': shortest disc path, real drive) or 'random'."),
    ] = "oracle",
    seed: Annotated[int, typer.Option(min=0, help="Seed of the episode.")] = 0,
    config: ConfigOpt = None,
    set_: EnvSetOpt = None,
    on_map: Annotated[
        Path | None,
        typer.Option("--map", help="On this map (a map_server .yaml, or a .png/.pgm with --set"
                     " maps.resolution=M_PER_PX), laid as quicknav eval --map"
                     " lays it: the grid follows the map at the env's cell size (room_size /"
                     " grid_size), the step limit its longest path."),
    ] = None,
) -> None:
    """Run one episode and write a PNG of its trajectory and a GIF with lidar rays."""
    cfg = env_config(config, set_, on_map)
    if policy not in DEMO_POLICIES:
        fail(f"--policy {policy!r}: allowed values are {', '.join(DEMO_POLICIES)}")
    enable_compilation_cache()
    from quicknav_core.admission import RolloutRequest
    from quicknav_core.runtime import Runtime

    runtime = Runtime()
    # a map that cannot be used, a robot that fits in no room: said, not raised
    admitted(RolloutRequest(cfg, num_envs=1), runtime)
    with console.status("running one episode and drawing it..."):
        result = run_demo(cfg, out, policy=policy, seed=seed, runtime=runtime)
    outcome = "reached the goal" if result.goal_reached else "timed out"
    console.print(
        f"{policy} policy {outcome} after {result.steps} steps, return {result.episode_return:.1f},"
        f" {result.collisions} wall collisions"
    )
    console.print(f"wrote {result.png}\nwrote {result.gif}")


@app.command("rooms")
def rooms(
    out: Annotated[Path, typer.Option(help="PNG file to write.")] = Path("rooms.png"),
    grid: Annotated[
        list[int] | None, typer.Option("--grid", help="Grid sizes (default 4 8 16).")
    ] = None,
    per_row: Annotated[int, typer.Option(min=1, max=12, help="Rooms per grid size.")] = 5,
    seed: Annotated[int, typer.Option(min=0, help="Room seed.")] = 0,
) -> None:
    """Draw generated rooms for several grid sizes (the paper's room-generation figure)."""
    from quicknav_cli.common import checked_grids

    grids = checked_grids(grid, (4, 8, 16))
    path = draw_rooms(out, tuple(grids), per_row=per_row, seed=seed)
    console.print(f"wrote {path}")

