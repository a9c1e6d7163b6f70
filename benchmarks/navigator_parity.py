"""The robot's stack without JAX against QuickNav's own evaluation, on the same episodes.

A trained policy is evaluated on a map by the JAX env (`evaluate`, as `quicknav eval RUN --map`
runs it), and exported with the map (`quicknav export RUN --map`). The same episodes (episode i
starts from the JAX env's `reset(fold_in(PRNGKey(seed), i))`: the same room, start pose and goal)
are then driven by the SDK's `Navigator` (onnxruntime, SciPy's Dijkstra on `map.npz`; no JAX)
in the NumPy twin: the twin moves the robot and casts a lidar that sees the walls only, as a
real scanner does; the Navigator gets the scan, the pose in the map frame and the goal. Without
unmapped obstacles. Prints both success rates, how many episodes end alike, and writes them into
benchmarks/results/navigator_parity.json (one entry per map). `--shield`: both sides through the
safety layer (`quicknav eval --shield`, `Navigator(shield=True)`; the entry's key gains " +shield").

    uv run python benchmarks/navigator_parity.py --run runs/buildings/building \
        [--map examples/maps/office.yaml] [--episodes 100] [--shield]

QuickNav's target: the two success rates within 2 points.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))


def drive(nav, twin, cfg, walls, start, theta, goal) -> dict:
    """One episode in the twin, driven by the Navigator from the scan and the map-frame pose."""
    import numpy as np

    from quicknav_core.env.constants import HIT_NONE
    from quicknav_core.env.numpy_env import cast_lidar_np

    angles = np.asarray(nav.policy.manifest["lidar"]["beam_angles_rad"], np.float32)
    corner, cell = np.asarray(nav.frame["grid_corner_in_map"]), float(nav.frame["cell_m"])
    obs = twin.load(walls, start, theta, goal)
    nav.set_goal(np.asarray(goal) + corner)
    path_m = nav.planner.path_length_m(float(start[0]), float(start[1]))
    worst, steps, info, done = 0.0, 0, {}, False
    while not done:
        s = twin.snapshot()
        # a real lidar: the walls only (the goal is no object), no return is inf
        ranges, hits = cast_lidar_np(s["pos"], s["theta"], np.full(2, -1e4, np.float32), s["walls"],
                                     angles, cell, cfg.lidar_max_range, cfg.goal_radius)  # fmt: skip
        scan = np.where(hits == HIT_NONE, np.inf, ranges)
        pose = (float(s["pos"][0] + corner[0]), float(s["pos"][1] + corner[1]), float(s["theta"]))
        mine = nav.observation(scan, pose)
        worst = max(worst, float(np.abs(mine - obs).max()))
        left, right = nav.policy.act_on(mine)
        if nav.shield:  # the safety layer on the scan the Navigator was given
            left, right = nav.shielded_command(scan, left, right)
        obs, _, terminated, truncated, info = twin.step(np.array([left, right]) / cfg.max_wheel_speed)
        done, steps = terminated or truncated, steps + 1
    end = twin.snapshot()["pos"]
    # the share of the plan's length the robot covered (1 at the goal; none for going backwards)
    left_m = 0.0 if info["goal_reached"] else nav.planner.path_length_m(float(end[0]), float(end[1]))
    return {"success": bool(info["goal_reached"]), "steps": steps, "max_obs_error": worst,
            "collisions": int(twin.snapshot()["collisions"]),
            "progress": float(np.clip(1.0 - left_m / path_m, 0.0, 1.0))}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a trained run folder (observe_plan)")
    ap.add_argument("--map", default="examples/maps/office.yaml")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--shield", action="store_true", help="both sides through the safety layer")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "navigator_parity.json")
    args = ap.parse_args()

    import jax
    import numpy as np
    from quicknav_client.navigate import Navigator

    from quicknav_core.bench.machine import machine_info, machine_line
    from quicknav_core.config import EnvConfig
    from quicknav_core.config.eval import EvalConfig
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv
    from quicknav_core.eval.agents import agent_from_run
    from quicknav_core.eval.evaluate import evaluate
    from quicknav_core.eval.map_fit import fit_map
    from quicknav_core.eval.shield import ShieldedAgent
    from quicknav_core.runtime import Runtime

    runtime = Runtime()
    agent, env, _ = agent_from_run(args.run)
    fit = fit_map(env, args.map)
    cfg = EnvConfig.model_validate({**env.model_dump(), **fit.env_overrides(args.map), "obstacles": None})
    if args.shield:
        agent = ShieldedAgent(agent, cfg)
    t0 = time.perf_counter()
    result, ep = evaluate(cfg, agent, EvalConfig(episodes=args.episodes, seed=args.seed, pictures=False,
                                                 gif_episodes=0), runtime=runtime)  # fmt: skip
    jax_s = time.perf_counter() - t0
    # the episodes' starts: the JAX env's own resets
    jenv, params = cfg.build("test", runtime)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(args.seed), i))(np.arange(args.episodes))
    _, states = jax.vmap(jenv.reset, in_axes=(0, None))(keys, params)
    pos, theta, goal = (np.asarray(a) for a in (states.pos, states.theta, states.goal))
    assert np.allclose(pos, ep.trajectories[:, 0]) and np.allclose(goal, ep.goals), "not the same episodes"
    with tempfile.TemporaryDirectory() as tmp:
        robot = Path(tmp) / "robot"
        subprocess.run(["uv", "run", "quicknav", "export", str(args.run), "--map", args.map, "--out",
                        str(robot)], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)  # fmt: skip
        nav = Navigator.load(robot, shield=args.shield)
        walls = nav.planner.walls
        assert walls.shape == ep.walls.shape[1:] and all((w == walls).all() for w in ep.walls), \
            "the exported map is not the room the JAX env drove"  # fmt: skip
        twin = QuickNavNumpyEnv(cfg, split="test")
        t0 = time.perf_counter()
        rows = [drive(nav, twin, cfg, walls, pos[i], float(theta[i]), goal[i]) for i in range(args.episodes)]
        sdk_s = time.perf_counter() - t0
    jax_ok = np.asarray(ep.success, bool)
    sdk_ok = np.array([r["success"] for r in rows])
    doc = {
        "machine": machine_info(), "run": str(args.run), "map": args.map, "episodes": args.episodes,
        "seed": args.seed, "env": {"grid_size": cfg.grid_size, "cell_m": cfg.cell_size,
                                   "max_steps": cfg.max_steps, "end_on_collision": cfg.end_on_collision},
        "jax_eval": {"success_rate": float(jax_ok.mean()), "collisions_per_episode":
                     float(np.mean(ep.collisions)), "seconds": round(jax_s, 1)},
        "sdk_in_twin": {"success_rate": float(sdk_ok.mean()), "collisions_per_episode":
                        float(np.mean([r["collisions"] for r in rows])), "seconds": round(sdk_s, 1),
                        "steps": int(sum(r["steps"] for r in rows)),
                        "max_obs_error": max(r["max_obs_error"] for r in rows),
                        "shielded_steps": nav.shielded if args.shield else None},
        "shield": args.shield, "same_outcome": int((jax_ok == sdk_ok).sum()),
        "difference_points": round(100 * abs(float(jax_ok.mean()) - float(sdk_ok.mean())), 1),
    }  # fmt: skip
    # one entry per map: a run on another map keeps the others
    kept = json.loads(args.out.read_text()).get("maps", {}) if args.out.exists() else {}
    key = args.map + (" +shield" if args.shield else "")
    args.out.write_text(json.dumps({"maps": {**kept, key: doc}}, indent=1))
    print(f"{args.map}, {args.episodes} episodes (seed {args.seed}), grid {cfg.grid_size} at"
          f" {cfg.cell_size:g} m, {cfg.max_steps}-step limit; {machine_line()}")
    print(f"  JAX eval:                     {100 * jax_ok.mean():5.1f} % success")
    print(f"  Navigator (no JAX) in twin:   {100 * sdk_ok.mean():5.1f} % success,"
          f" observation error at most {doc['sdk_in_twin']['max_obs_error']:.1e}")
    print(f"  same outcome in {doc['same_outcome']} of {args.episodes} episodes; difference"
          f" {doc['difference_points']} points (target: within 2)")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
