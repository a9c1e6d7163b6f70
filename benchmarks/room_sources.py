"""Env steps/s by room source, same run: carved 16x16 (the paper's), generated floor plans at 16, 64,
128 and 256 cells, the shipped office map (map_server YAML + PGM) at 48 cells, and a 30 m floor plan at
0.25 m cells (120) with a robot narrower than a cell and one wider.

    uv run python -m benchmarks.room_sources [--batch 1024] [--out benchmarks/results/room_sources.json]

Every row but the last two: the same robot (radius 0.15 m) and cells of 0.5 m (room side = grid x
0.5 m), so larger grids are larger buildings; 16 lidar beams, random actions, the whole observation
consumed, ``batch`` envs inside one jitted lax.scan (the method of `quicknav bench`), stepped two ways: gymnax's
``vmap(env.step)`` (every env computes a reset every step, a select keeps it or not) and
``env.batch.batched_step`` (only the envs that ended are reset; QuickNav's PPO steps this way).
The bank's build time and the compile time are printed beside the rates.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def configs():
    from quicknav_core.config import EnvConfig

    common = {"lidar_beams": 16, "final_obs": False, "train_rooms": 64, "test_rooms": 8}
    office = str(ROOT / "examples" / "maps" / "office.yaml")
    fine = {"min_room": 12, "max_room": 40, "door_width": 4, "corridor_width": 4}
    return [
        ("carved 16", EnvConfig(grid_size=16, room_size=8.0, **common)),
        ("floorplan 16", EnvConfig(rooms="floorplan", grid_size=16, room_size=8.0, **common)),
        ("floorplan 64", EnvConfig(rooms="floorplan", grid_size=64, room_size=32.0, **common)),
        ("floorplan 128", EnvConfig(rooms="floorplan", grid_size=128, room_size=64.0, **common)),
        ("floorplan 256", EnvConfig(rooms="floorplan", grid_size=256, room_size=128.0, **common)),
        ("map office 48",
         EnvConfig(rooms="maps", maps={"train": [office]}, grid_size=48, room_size=24.0, **common)),
        # a 30 m floor at 0.25 m cells (the building), doors 1 m wide: a robot narrower than
        # a cell, then one wider (0.4 m across: the collision test reads the 3x3 cells around it)
        ("floorplan 120 narrow", EnvConfig(rooms="floorplan", grid_size=120, room_size=30.0,
                                           robot_radius=0.1, floorplan=fine, **common)),
        ("floorplan 120 wide", EnvConfig(rooms="floorplan", grid_size=120, room_size=30.0,
                                         robot_radius=0.2, floorplan=fine, **common)),
    ]


def measure(config, batch: int, steps: int, repeats: int, batched: bool = False) -> dict:
    import jax

    from quicknav_core.bench.env import make_scan_rollout

    t0 = time.perf_counter()
    env, params = config.build("train")
    bank_s = time.perf_counter() - t0
    length = max(steps // batch, 8)
    key = jax.random.PRNGKey(0)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, batch), params)
    rollout = make_scan_rollout(env, params, batch, length, False, batched)
    t0 = time.perf_counter()
    compiled = jax.jit(rollout, donate_argnums=(1,)).lower(key, state).compile()
    compile_s = time.perf_counter() - t0
    carry = [key, state]
    times = []
    for _ in range(repeats + 1):  # the first call warms up
        t0 = time.perf_counter()
        carry[0], carry[1], total = compiled(carry[0], carry[1])
        total.block_until_ready()
        times.append(time.perf_counter() - t0)
    best = sorted(times[1:])[len(times[1:]) // 2]
    return {"steps_per_s": round(length * batch / best), "bank_build_s": round(bank_s, 2),
            "compile_s": round(compile_s, 1), "batch": batch, "steps_timed": length * batch}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=400_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    import jax

    rows = []
    print(f"{'rooms':<22} {'vmap(step)/s':>13} {'batched/s':>12} {'bank s':>8} {'compile s':>10}")
    for name, cfg in configs():
        plain = measure(cfg, args.batch, args.steps, args.repeats)
        batched = measure(cfg, args.batch, args.steps, args.repeats, batched=True)
        r = {"rooms": name, "grid": cfg.grid_size, "lidar_lines": cfg.lidar_lines, **plain,
             "batched_steps_per_s": batched["steps_per_s"]}  # fmt: skip
        rows.append(r)
        print(f"{name:<22} {r['steps_per_s']:>13,} {r['batched_steps_per_s']:>12,}"
              f" {r['bank_build_s']:>8} {r['compile_s']:>10}", flush=True)  # fmt: skip
    from quicknav_core.bench.machine import machine_info, machine_line

    doc = {"machine": f"{machine_line()}, jax {jax.__version__}", "machine_info": machine_info(),
           "batch": args.batch, "rows": rows}  # fmt: skip
    if args.out:
        args.out.write_text(json.dumps(doc, indent=2) + "\n")
        print("wrote", args.out)


if __name__ == "__main__":
    main()
