"""Trained on caves or on floor plans, evaluated on held-out caves, held-out floor plans and a map.

For each preset (`paper-ppo`, `paper-lstm`), trains once on the paper's carved rooms and once on
generated floor plans (`--set env.rooms=floorplan`) with `quicknav train`, then runs `quicknav eval`
on the held-out test bank of each room source: carved caves, floor plans (plans no training saw),
and the shipped office map (`examples/maps/office.yaml`, 48 cells of 0.5 m; the map's own episodes,
held out by seed). The oracle (shortest path on the disc-reachable grid) runs on each source with
the same episodes; SPL is measured against its paths. Every command runs in a fresh process as a
user runs it; a run folder that already holds a finished training is reused (`--retrain` trains
again).

    uv run python benchmarks/generalisation.py [--seeds 1] [--episodes 200] [--preset paper-ppo]

Prints a Markdown table and writes benchmarks/results/generalisation.json.
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

PRESETS = ("paper-ppo", "paper-lstm")
TRAIN_ON = {"carved": [], "floorplan": ["--set", "env.rooms=floorplan"]}
OFFICE = "examples/maps/office.yaml"
# what `quicknav eval --set` changes to put a policy in each room source
EVAL_ON = {
    "carved": ["--set", "rooms=carved"],
    "floorplan": ["--set", "rooms=floorplan"],
    "office map": ["--set", "rooms=maps", "--set", f'maps.train=["{OFFICE}"]',
                   "--set", "grid_size=48", "--set", "room_size=24", "--set", "max_steps=600"],
}  # fmt: skip


def evaluate(target: list[str], out: Path, episodes: int, run_dir: Path | None) -> dict:
    """``quicknav eval`` of a run (or the oracle) on one room source; its eval.json."""
    who = [str(run_dir)] if run_dir is not None else ["--policy", "oracle"]
    seconds = run(["uv", "run", "quicknav", "eval", *who, "--episodes", str(episodes),
                   *target, "--out", str(out)])  # fmt: skip
    m = json.loads((out / "eval.json").read_text())["metrics"]
    return {"seconds": round(seconds, 1), "success_rate": m["success_rate"],
            "success_ci95": m["success_ci95"], "spl": m["spl"],
            "mean_steps": m["steps_to_goal_failures_as_limit"]["mean"],
            "collisions_per_episode": m["collisions_per_episode"]}  # fmt: skip


def cell(rows: list[dict]) -> str:
    """Success (mean over seeds, min-max), SPL and steps of one table cell."""
    success = [100 * r["success_rate"] for r in rows]
    text = f"{statistics.fmean(success):.1f} %"
    if len(rows) > 1:
        text += f" ({min(success):.1f}-{max(success):.1f})"
    spl = statistics.fmean(r["spl"] for r in rows)
    steps = statistics.fmean(r["mean_steps"] for r in rows)
    return f"{text}, SPL {spl:.2f}, {steps:.0f} steps"


def table(results: dict, oracle: dict, episodes: int, seeds: int) -> str:
    lines = ["| policy | trained on | " + " | ".join(f"on {t}" for t in EVAL_ON) + " |",
             "|" + "---|" * (2 + len(EVAL_ON))]  # fmt: skip
    lines.append("| oracle (shortest path) | - | "
                 + " | ".join(cell([oracle[t]]) for t in EVAL_ON) + " |")  # fmt: skip
    for preset, by_source in results.items():
        for source, runs in by_source.items():
            cells = [cell([r["eval"][t] for r in runs]) for t in EVAL_ON]
            lines.append(f"| `{preset}` | {source} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"{episodes} held-out episodes per cell and seed, {seeds} seed(s); machine:"
                 f" {machine_line()}.")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--preset", action="append", choices=PRESETS, help="default: both")
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "generalisation")
    ap.add_argument("--retrain", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "generalisation.json")
    args = ap.parse_args()
    oracle = {t: evaluate(target, args.runs / "oracle" / t.replace(" ", "-"), args.episodes, None)
              for t, target in EVAL_ON.items()}  # fmt: skip
    print("oracle:", {t: r["success_rate"] for t, r in oracle.items()}, flush=True)
    results: dict[str, dict[str, list[dict]]] = {}
    for preset in args.preset or PRESETS:
        results[preset] = {}
        for source, sets in TRAIN_ON.items():
            runs = results[preset][source] = []
            for seed in range(args.seeds):
                run_dir = args.runs / f"{preset}-{source}-s{seed}"
                train_s = None
                if args.retrain or not trained(run_dir, preset):
                    train_s = run(["uv", "run", "quicknav", "train", "--preset", preset, *sets,
                                   "--seed", str(seed), "--out", str(run_dir)])  # fmt: skip
                evals = {t: evaluate(target, run_dir / "eval-on" / t.replace(" ", "-"),
                                     args.episodes, run_dir)
                         for t, target in EVAL_ON.items()}  # fmt: skip
                runs.append({"seed": seed, "run": str(run_dir.relative_to(ROOT)),
                             "train_s": train_s and round(train_s, 1), "eval": evals})  # fmt: skip
                print(f"{preset} on {source}, seed {seed}: trained in"
                      f" {train_s and round(train_s)} s (None: reused);",
                      {t: e["success_rate"] for t, e in evals.items()}, flush=True)  # fmt: skip
    text = table(results, oracle, args.episodes, args.seeds)
    print(text)
    args.out.write_text(json.dumps({"machine": machine_info(), "episodes": args.episodes,
                                    "oracle": oracle, "results": results, "table": text},
                                   indent=1))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
