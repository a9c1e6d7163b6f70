"""Why do the paper-size memory agents not learn under the shaped reward? A diagnosis on the
train bank only (training success and the critic's explained variance per chunk; the test bank is
never touched).

The learning report had PPO + LSTM 2x15 at 0.87 held-out success under the paper's reward (0.90 on
the rerun seeds) and 0.00 under potential-based shaping (memory MLP: 0.94 and 0.93). Each arm
below trains the paper-lstm preset with one change, same seed and budget, so the arms differ in one
thing each:

- paper: the paper's sign-of-progress reward (the control);
- shaped: Φ = -distance, γ 0.96 (the learning report's shaped row);
- shaped, γ 0.99: shaping with the trainer's discount and the shaping's γ both 0.99;
- paper, γ 0.99: the same discount under the paper's reward (does γ alone change learning?);
- shaped, LSTM 1x32: the tuned-lstm network (does capacity decide it?);
- shaped, goal seen: the goal observed (does the critic's view of the distance decide it?).

    uv run python benchmarks/shaped_memory.py [--steps 20000000] [--seed 0] [--arm NAME ...]

Writes benchmarks/results/shaped_memory.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

from quicknav_core.bench.machine import machine_info  # noqa: E402
from quicknav_core.config import resolve_train  # noqa: E402
from quicknav_core.train.run import read_metrics, train_run  # noqa: E402

SHAPED = {"env.reward.progress": "potential", "env.reward.potential_gamma": 0.96}
ARMS: dict[str, dict] = {
    "paper": {},
    "shaped": SHAPED,
    "shaped, γ 0.99": {**SHAPED, "env.reward.potential_gamma": 0.99, "algorithm.gamma": 0.99},
    "paper, γ 0.99": {"algorithm.gamma": 0.99},
    "shaped, LSTM 1x32": {**SHAPED, "network.num_layers": 1, "network.hidden_size": 32},
    "shaped, goal seen": {**SHAPED, "env.observe_goal": True},
}


def one(arm: str, steps: int, seed: int) -> dict:
    cfg = resolve_train({"preset": "paper-lstm",
                         "overrides": {"seed": seed, "total_steps": steps, **ARMS[arm]}})  # fmt: skip
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        train_run(cfg, Path(d))
        minutes = (time.perf_counter() - t0) / 60
        rows = read_metrics(Path(d))
    last = rows[-3:]
    return {
        "arm": arm, "overrides": ARMS[arm], "seed": seed, "minutes": round(minutes, 2),
        "train_success_last3": statistics.mean(r["success_rate"] for r in last),
        "explained_variance_last3": statistics.mean(r["explained_variance"] for r in last),
        "curve": [{k: round(r[k], 4) for k in ("env_steps", "success_rate", "explained_variance",
                                                "value_loss", "mean_return", "mean_length")}
                  for r in rows],
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=20_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arm", action="append", choices=list(ARMS), help="default: every arm")
    args = ap.parse_args()
    out = ROOT / "benchmarks" / "results" / "shaped_memory.json"
    done = json.loads(out.read_text())["runs"] if out.exists() else []
    for arm in args.arm or list(ARMS):
        if any(r["arm"] == arm and r["seed"] == args.seed and r["curve"][-1]["env_steps"] >= args.steps
               for r in done):  # fmt: skip
            continue  # resumable: a finished arm is kept
        r = one(arm, args.steps, args.seed)
        done = [x for x in done if not (x["arm"] == arm and x["seed"] == args.seed)] + [r]
        out.write_text(json.dumps({"machine": machine_info(), "preset": "paper-lstm",
                                   "runs": done}, indent=1) + "\n")  # fmt: skip
        print(f"{arm:20s} seed {args.seed}: training success (last 3 chunks) "
              f"{r['train_success_last3']:.2f}, explained variance {r['explained_variance_last3']:.2f} "
              f"({r['minutes']} min)", flush=True)  # fmt: skip
    print("\narm                  | seed | success by chunk (every 4th)          | expl. var. by chunk")
    for r in done:
        succ = " ".join(f"{c['success_rate']:.2f}" for c in r["curve"][::4])
        ev = " ".join(f"{c['explained_variance']:.2f}" for c in r["curve"][::4])
        print(f"{r['arm']:20s} | {r['seed']:4d} | {succ:38s} | {ev}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
