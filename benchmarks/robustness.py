"""Trained with and without sensor randomisation: success, SPL and collisions at each perturbation level.

For each seed, trains `paper-ppo` (the plain env) and `paper-ppo-robust` (the same with
`EnvConfig.randomize`: noise, bias, dropout, wheel scales, latency) with `quicknav train`, then runs
`quicknav eval RUN --robustness` on the held-out test bank: every level on the same fixed-seed
episodes (`quicknav_core.eval.robustness.LEVELS`). Each command runs in a fresh process as a user
runs it; a run folder that already holds a finished training is reused (`--retrain` trains again).

    uv run python benchmarks/robustness.py [--seeds 3] [--episodes 200] [--runs runs/robustness]

Prints a Markdown table (mean over seeds, min-max) and writes benchmarks/results/robustness.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

from benchmarks.cli_runs import run, trained  # noqa: E402
from quicknav_core.bench.machine import machine_info, machine_line  # noqa: E402

PRESETS = ("paper-ppo", "paper-ppo-robust")
# the rows of the table first, then the harder levels
TABLE = ("none", "lidar_noise 2 %", "lidar_noise 5 %", "lidar_noise 10 %", "beam_dropout 5 %",
         "latency 1 steps", "latency 2 steps", "wheel_asymmetry 10 %", "lidar_noise 20 %",
         "beam_dropout 25 %", "lidar_bias -0.1 m", "lidar_bias 0.1 m", "latency 3 steps",
         "wheel_asymmetry 20 %")  # fmt: skip


def spread(values: list[float], fmt: str) -> str:
    """Mean over seeds, with min-max when there are several."""
    mean = statistics.fmean(values)
    if len(values) == 1:
        return fmt.format(mean)
    return f"{fmt.format(mean)} ({fmt.format(min(values))}-{fmt.format(max(values))})"


def table(results: dict) -> str:
    seeds = len(next(iter(results.values())))
    head = ("| level | " + " | ".join(f"{p}: success" for p in PRESETS) + " | "
            + " | ".join(f"{p}: SPL" for p in PRESETS) + " | "
            + " | ".join(f"{p}: collisions" for p in PRESETS) + " |")  # fmt: skip
    lines = [head, "|" + "---|" * (1 + 3 * len(PRESETS))]
    for label in TABLE:
        rows = {p: [next(r for r in seed["robustness"] if r["label"] == label)
                    for seed in results[p]] for p in PRESETS}  # fmt: skip
        cells = [spread([100 * r["success_rate"] for r in rows[p]], "{:.1f} %") for p in PRESETS]
        cells += [spread([r["spl"] for r in rows[p]], "{:.2f}") for p in PRESETS]
        cells += [spread([r["collisions_per_episode"] for r in rows[p]], "{:.2f}") for p in PRESETS]
        lines.append(f"| {label.replace('_', ' ')} | " + " | ".join(cells) + " |")
    episodes = next(iter(results.values()))[0]["robustness"][0]["episodes"]
    lines.append("")
    lines.append(f"{episodes} held-out episodes per level and seed, {seeds} seed(s), mean (min-max);"
                 f" machine: {machine_line()}.")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "robustness")
    ap.add_argument("--retrain", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "robustness.json")
    args = ap.parse_args()
    quicknav = ["uv", "run", "quicknav"]
    results: dict[str, list[dict]] = {p: [] for p in PRESETS}
    timings: dict[str, list[dict]] = {p: [] for p in PRESETS}
    for seed in range(args.seeds):
        for preset in PRESETS:
            run_dir = args.runs / f"{preset}-s{seed}"
            train_s = None
            if args.retrain or not trained(run_dir, preset):
                train_s = run([*quicknav, "train", "--preset", preset, "--seed", str(seed),
                               "--out", str(run_dir)])  # fmt: skip
            out = run_dir / "eval-robust"
            eval_s = run([*quicknav, "eval", str(run_dir), "--episodes", str(args.episodes),
                          "--robustness", "--out", str(out)])  # fmt: skip
            result = json.loads((out / "eval.json").read_text())
            results[preset].append({"seed": seed, "run": str(run_dir.relative_to(ROOT)),
                                    "robustness": result["robustness"]})  # fmt: skip
            timings[preset].append({"seed": seed, "train_s": train_s, "eval_s": round(eval_s, 1)})
            print(f"{preset} seed {seed}: trained in {train_s and round(train_s)} s (None: reused),"
                  f" evaluated in {eval_s:.0f} s", flush=True)  # fmt: skip
    text = table(results)
    print(text)
    args.out.write_text(json.dumps({"machine": machine_info(), "episodes": args.episodes,
                                    "results": results, "timings": timings, "table": text},
                                   indent=1))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
