"""Trials per hour: the same sweep one trial at a time vs. batched (run: uv run python benchmarks/sweep_speed.py).

The space holds only traced hyperparameters (learning rate, gamma, entropy and clip coefficients,
two reward weights), so with --parallel K the K trials train in one vmapped program. Both runs use
the same sampler seed, hence the same trials; the JSON goes to benchmarks/results/sweep_speed.json.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

from quicknav_core.bench.machine import machine_info
from quicknav_core.config import SweepConfig, get_preset
from quicknav_core.sweep import run_sweep

TRIALS = int(sys.argv[1]) if len(sys.argv) > 1 else 8
STEPS = int(sys.argv[2]) if len(sys.argv) > 2 else 500_000

base = get_preset("demo").model_copy(update={"total_steps": STEPS})
space = {
    "algorithm.learning_rate": {"type": "log_float", "low": 1e-4, "high": 3e-3},
    "algorithm.gamma": {"type": "float", "low": 0.9, "high": 0.999},
    "algorithm.ent_coef": {"type": "float", "low": 0.0, "high": 0.02},
    "algorithm.clip_eps": {"type": "float", "low": 0.1, "high": 0.3},
    "env.reward.step_penalty": {"type": "float", "low": 0.01, "high": 0.5},
    "env.reward.progress_reward": {"type": "float", "low": 0.1, "high": 1.0},
}
results = {"machine": machine_info(), "trials": TRIALS, "steps_per_trial": STEPS, "runs": {}}
for parallel in (1, TRIALS):
    out = Path(f"/tmp/quicknav-sweep-speed-{parallel}")
    shutil.rmtree(out, ignore_errors=True)
    cfg = SweepConfig(base=base, space=space, trials=TRIALS, parallel=parallel, eval_episodes=50,
                      sampler="random", sampler_seed=0)  # fmt: skip
    t0 = time.perf_counter()
    summary = run_sweep(cfg, out)
    wall = time.perf_counter() - t0
    results["runs"][f"parallel={parallel}"] = {
        "wall_s": round(wall, 1), "trials_per_hour": round(TRIALS * 3600 / wall, 1),
        "best_value": summary["best_value"], "groups": summary["timings"],
    }  # fmt: skip
    print(f"parallel={parallel}: {wall:.1f} s for {TRIALS} trials -> {TRIALS * 3600 / wall:.0f} trials/hour",
          flush=True)  # fmt: skip
one, many = (results["runs"][f"parallel={p}"]["wall_s"] for p in (1, TRIALS))
results["speedup"] = round(one / many, 2)
print(f"speed-up batched over one at a time: {one / many:.2f}x")
path = Path(__file__).parent / "results" / "sweep_speed.json"
path.parent.mkdir(parents=True, exist_ok=True)
path.write_text(json.dumps(results, indent=2))
print(f"wrote {path}")
