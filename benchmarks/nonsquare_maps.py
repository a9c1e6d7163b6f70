"""What a map's own grid saves over the square it used to be padded to: the building preset's env
laid on real maps (``quicknav eval --map`` lays them: the map's rows x cols at the policy's 0.5 m
cells), beside the same env on the smallest square that holds the map (``grid_rows`` and
``grid_cols`` unset, the rest of the square wall), in one run on one machine.

Per map and grid: the env's steps per second (``batched_step``, the call QuickNav's PPO and the
Rollout server make: 1,024 envs, random actions, auto-reset with a fresh plan for the envs that
ended), the time of one reset of 256 envs (room, poses, the plan over the whole grid, first scan),
and the evaluation's admission estimate (100 episodes of the oracle, ``eval_memory``).

    uv run python benchmarks/nonsquare_maps.py [--out benchmarks/results/nonsquare_maps.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import jax

from quicknav_core.bench.machine import machine_info, machine_line
from quicknav_core.config import EvalConfig, resolve_env
from quicknav_core.config.presets import get_preset
from quicknav_core.env.batch import batched_step
from quicknav_core.eval.map_fit import env_on_map
from quicknav_core.train.memory import MB, eval_memory

ROOT = Path(__file__).resolve().parents[1]
MAPS = ("examples/maps/office.yaml", "examples/maps/slam/warehouse.yaml", "examples/maps/slam/depot.yaml")
ENVS, STEPS, RESETS = 1024, 200, 256


def _timed(fn, repeats: int = 3) -> float:
    jax.block_until_ready(fn())  # compile and warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(env_config) -> dict:
    env, params = env_config.build("test")
    keys = jax.random.split(jax.random.PRNGKey(0), ENVS)
    _, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)

    @jax.jit
    def run(state, key):
        def one(carry, k):
            s, key = carry
            a_key, s_key, key = jax.random.split(key, 3)
            action = jax.random.uniform(a_key, (ENVS, 2), minval=-1.0, maxval=1.0)
            _, s, _, _, _ = batched_step(env, jax.random.split(s_key, ENVS), s, action, params)
            return (s, key), None

        (state, _), _ = jax.lax.scan(one, (state, key), None, STEPS)
        return state

    step_s = _timed(lambda: run(state, jax.random.PRNGKey(1)))
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    reset_keys = jax.random.split(jax.random.PRNGKey(2), RESETS)
    reset_s = _timed(lambda: reset(reset_keys, params))
    est = eval_memory(EvalConfig(policy="oracle", env=env_config, episodes=100))
    return {"grid": list(env_config.grid_shape), "cells": env_config.grid_shape[0] * env_config.grid_shape[1],
            "steps_per_s": round(ENVS * STEPS / step_s), "reset_256_ms": round(1000 * reset_s, 1),
            "eval_estimate_mb": round(est.total / MB)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/nonsquare_maps.json")
    args = ap.parse_args()
    building = get_preset("building").env
    rows = []
    print(machine_line())
    for name in MAPS:
        own = env_on_map(building, str(ROOT / name))
        square = resolve_env({"grid_rows": None, "grid_cols": None}, own)
        row = {"map": name, "own": measure(own), "square": measure(square)}
        rows.append(row)
        o, s = row["own"], row["square"]
        print(f"{name}: own grid {o['grid'][0]} x {o['grid'][1]} ({o['cells']} cells), square"
              f" {s['grid'][0]} x {s['grid'][1]} ({s['cells']}): steps/s {o['steps_per_s']:,} vs"
              f" {s['steps_per_s']:,}; reset of {RESETS} {o['reset_256_ms']} vs {s['reset_256_ms']} ms;"
              f" eval estimate {o['eval_estimate_mb']} vs {s['eval_estimate_mb']} MB", flush=True)  # fmt: skip
    args.out.write_text(json.dumps({"machine": machine_info(), "envs": ENVS, "steps": STEPS,
                                    "resets": RESETS, "rows": rows}, indent=2) + "\n")  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
