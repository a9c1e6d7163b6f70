"""Does the curriculum help? The same preset and budget trained with and without
`curriculum.enabled`, several seeds each, evaluated on the held-out test bank (200 episodes,
episode seed 0): success, SPL and success per difficulty bin (oracle path length), side by side.

    uv run python benchmarks/curriculum.py [--preset demo] [--steps 300000] [--seeds 3]

Writes benchmarks/results/curriculum_<preset>.json.
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
from quicknav_core.config import resolve_eval, resolve_train  # noqa: E402
from quicknav_core.eval.evaluate import run_eval  # noqa: E402
from quicknav_core.train.run import read_metrics, train_run  # noqa: E402


def one(preset: str, steps: int, seed: int, curriculum: bool, extra: dict) -> dict:
    cfg = resolve_train({"preset": preset, "overrides": {
        "seed": seed, "total_steps": steps, "curriculum.enabled": curriculum, **extra}})  # fmt: skip
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        train_run(cfg, Path(d))
        minutes = (time.perf_counter() - t0) / 60
        levels = [m.get("curriculum_level") for m in read_metrics(Path(d))]
        ecfg = resolve_eval({"run": d, "episodes": 200, "seed": 0},
                            trained_env=lambda _s: cfg.env)  # fmt: skip
        res, _ = run_eval(ecfg, None, run_dir=Path(d))
    return {"seed": seed, "curriculum": curriculum, "minutes": round(minutes, 2),
            "success": res["metrics"]["success_rate"], "spl": res["metrics"]["spl"],
            "steps_failures_as_limit": res["metrics"]["steps_to_goal_failures_as_limit"]["mean"],
            "by_path_length": {f"{b['path_m'][0]:g}-{b['path_m'][1] or 'inf'} m": round(b["success_rate"], 3)
                               for b in res["by_path_length"]},
            "levels": levels}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--steps", type=int, default=300_000)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], help="key=JSON override for both arms")
    args = ap.parse_args()
    extra = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    runs = []
    for seed in range(args.seeds):
        for cur in (False, True):
            r = one(args.preset, args.steps, seed, cur, extra)
            runs.append(r)
            print(f"seed {seed} curriculum {cur!s:5}: success {r['success']:.3f} SPL {r['spl']:.3f} "
                  f"bins {r['by_path_length']} ({r['minutes']} min)", flush=True)  # fmt: skip
    summary = {}
    for cur in (False, True):
        rs = [r for r in runs if r["curriculum"] is cur]
        summary["with" if cur else "without"] = {
            k: (statistics.mean(r[k] for r in rs), statistics.stdev(r[k] for r in rs) if len(rs) > 1 else 0.0)
            for k in ("success", "spl", "steps_failures_as_limit")
        }  # fmt: skip
    for arm, s in summary.items():
        print(f"{arm:8s} curriculum: " + ", ".join(f"{k} {m:.3f} ± {sd:.3f}" for k, (m, sd) in s.items()))
    out = ROOT / "benchmarks" / "results" / f"curriculum_{args.preset}.json"
    out.write_text(json.dumps({"machine": machine_info(), "preset": args.preset, "steps": args.steps,
                               "overrides": extra, "summary": summary, "runs": runs}, indent=2) + "\n")  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
