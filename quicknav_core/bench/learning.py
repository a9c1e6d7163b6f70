"""`quicknav bench learning`: the paper's Tables 1 and 2 as a reproducible benchmark.

Every row trains a preset with several seeds under a wall-clock cap, evaluates each run on 100
held-out episodes (test bank, episode seed 0, deterministic actions), and reports mean ± std across
seeds beside the paper's numbers, together with the oracle and random baselines on the same
episodes. Runs are resumable: a (row, seed) whose eval.json exists is not trained again, so the
benchmark can be completed over several sessions. Nothing is tuned on the test bank: the presets
are fixed before evaluation.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quicknav_core.config import EnvConfig, get_preset, resolve_eval, resolve_train


@dataclass(frozen=True)
class Row:
    name: str
    table: int
    preset: str
    total_steps: int
    max_minutes: float
    paper: str  # the paper's figure for this row


ROWS = (
    Row("PPO (MLP 2x128)", 1, "paper-ppo", 20_000_000, 30, "reward 96.87 ± 8.50"),
    Row("SAC (MLP 2x128)", 1, "paper-sac", 4_000_000, 30, "reward 73.52 ± 51.59"),
    Row("TD3 (MLP 2x128)", 1, "paper-td3", 8_000_000, 30, "reward 85.99 ± 36.22"),
    # Table 2 budgets: the target allows 60 min per run; the step budgets (the learning rate anneals
    # over them) keep one seed near 8-12 min on 2 cores (MLP and LSTM train at ~90-130k steps/s,
    # GTrXL at ~14k steps/s).
    Row("PPO + MLP with memory", 2, "paper-mlp", 60_000_000, 60, "steps 214.61 ± 94.53"),
    Row("PPO + LSTM", 2, "paper-lstm", 60_000_000, 60, "steps 126.60 ± 75.71"),
    Row("PPO + GTrXL", 2, "paper-gtrxl", 6_000_000, 60, "steps 133.90 ± 88.94"),
)
NOTES = (
    "Configs: `quicknav presets` / `quicknav_core/config/presets.py`; each seed is the preset with "
    "`seed` = 0, 1, 2 and the row's step budget; a seed stops at its step budget or its time cap. "
    "Nothing was tuned on the test bank.",
    "Table 1 TD3 exploits the paper's sign-of-progress reward (+λp for any step that shortens the "
    "distance, however little): it collects a higher return than the oracle by wiggling towards the "
    'goal without reaching it. `reward.progress="linear"` removes the exploit; the row keeps the '
    "paper's reward.",
    "Table 2 presets use 64-step rollouts, 16 minibatches of whole env sequences and 4 epochs "
    "(QuickNav's choice): with the paper's 512-step rollouts recurrent PPO made 16 gradient steps per "
    "131k env steps and every memory agent stayed at the random policy. Rewards and other PPO values "
    "are the paper's tuned ones.",
    "PPO + GTrXL is undertrained: its 6M-step budget was set from seed 0's ~14k steps/s; seeds 1-2 "
    "ran at ~5.5k steps/s on another machine (see Machines). At 6M steps the three seeds are early "
    "in learning (held-out success 0 %, 2 %, 17 %); MLP and LSTM got 60M. A 60-min budget per "
    "seed is the next run to make.",
    "Seeds with 'machine not recorded' ran before the report stored machines, on this project's "
    "2-core CPU VMs.",
    "The paper reports means over 10 episodes of one agent; the rows here are 100 held-out episodes "
    "per seed, mean ± std across seeds. Its Table 2 'steps to finish' is compared with our steps with "
    "failures counted as the 300-step limit (the stricter figure) and with steps over successes.",
)
EVAL_EPISODES = 100
EVAL_SEED = 0


def _slug(row: Row) -> str:
    return row.preset


def run_one(row: Row, seed: int, runs_dir: Path, scale: float = 1.0, say=print) -> dict[str, Any]:
    """Train (or finish training) one seed of a row and evaluate it; returns its eval result."""
    from quicknav_core.eval.evaluate import run_eval
    from quicknav_core.train.run import CONFIG_FILE, checkpoint_dir, read_meta, train_run

    run_dir = runs_dir / f"{_slug(row)}-s{seed}"
    eval_path = run_dir / "eval" / "eval.json"
    if eval_path.exists():
        return json.loads(eval_path.read_text())
    steps = max(int(row.total_steps * scale), get_preset(row.preset).steps_per_update)
    cfg = resolve_train(
        {"preset": row.preset, "overrides": {"seed": seed, "total_steps": steps}}
    )
    cap_s = row.max_minutes * 60 * scale
    started = time.perf_counter()
    elapsed_before = 0.0
    marker = run_dir / "train_seconds.json"
    if marker.exists():
        elapsed_before = json.loads(marker.read_text())["seconds"]

    def stop(result) -> bool:
        spent = elapsed_before + time.perf_counter() - started
        marker.write_text(json.dumps({"seconds": spent}))
        say(f"  {row.preset} s{seed}: {result.env_steps:,} steps, {spent / 60:.1f} min, "
            f"success {result.metrics.get('success_rate', float('nan')):.0%}")  # fmt: skip
        return spent >= cap_s

    resume = (run_dir / CONFIG_FILE).exists() and checkpoint_dir(run_dir) is not None
    run_dir.mkdir(parents=True, exist_ok=True)
    summary = train_run(cfg, run_dir, callback=stop, resume=resume)
    eval_cfg = resolve_eval(
        {"run": str(run_dir), "episodes": EVAL_EPISODES, "seed": EVAL_SEED},
        trained_env=lambda _source: cfg.env,
    )
    result, _ = run_eval(eval_cfg, run_dir / "eval", run_dir=run_dir)
    meta = read_meta(run_dir)
    result["training"] = {
        "env_steps": meta["env_steps"],
        "machine": _machine(),
        "minutes": json.loads(marker.read_text())["seconds"] / 60 if marker.exists() else None,
        "stopped_by_time_cap": summary["stopped"],
        "seed": seed,
    }
    eval_path.write_text(json.dumps(result, indent=2))
    return result


def _machine() -> str:
    """Where a seed trained, in words (its minutes are only comparable on the same machine)."""
    from quicknav_core.bench.machine import machine_line

    return machine_line()


def baselines(runs_dir: Path) -> dict[str, dict[str, Any]]:
    """Oracle and random on the Table 1 and Table 2 episodes."""
    from quicknav_core.eval.evaluate import run_eval

    out = {}
    for table, preset in ((1, "paper-ppo"), (2, "paper-lstm")):
        env_cfg: EnvConfig = get_preset(preset).env
        for policy in ("oracle", "random"):
            path = runs_dir / f"baseline-{policy}-table{table}" / "eval.json"
            if path.exists():
                out[f"{policy}-table{table}"] = json.loads(path.read_text())
                continue
            cfg = resolve_eval({"policy": policy, "env": env_cfg.model_dump(mode="json"),
                                "episodes": EVAL_EPISODES, "seed": EVAL_SEED})  # fmt: skip
            result, _ = run_eval(cfg, path.parent)
            out[f"{policy}-table{table}"] = result
    return out


def _agg(values: list[float]) -> str:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    if not vals:
        return "n/a"
    if len(vals) == 1:
        return f"{vals[0]:.3g}"
    return f"{statistics.mean(vals):.3g} ± {statistics.stdev(vals):.2g}"


def build_report(
    results: dict[str, list[dict[str, Any]]], base: dict[str, dict[str, Any]], seeds: int
) -> tuple[str, dict]:
    """Markdown + JSON of everything finished so far, and which targets are met."""
    lines = ["# QuickNav learning benchmark: the paper's Tables 1 and 2", "",
             f"Each row: {seeds} training seeds, each evaluated on {EVAL_EPISODES} held-out test episodes "
             f"(episode seed {EVAL_SEED}, deterministic actions); mean ± std across seeds.", ""]  # fmt: skip
    data: dict[str, Any] = {"rows": {}, "baselines": {}, "targets": []}
    for table in (1, 2):
        oracle = base.get(f"oracle-table{table}", {}).get("metrics", {})
        oracle_steps = oracle.get("steps_to_goal_successes", {}).get("mean")
        lines += [f"## Table {table}" + (": goal observed" if table == 1 else ": goal hidden (lidar, pose, memory)"), "",
                  "| row | seeds done | success | SPL | steps to goal (successes) | steps (failures = 300) | "
                  "steps / oracle | return | collisions/ep | train min | env steps | paper |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for row in ROWS:
            if row.table != table:
                continue
            rs = results.get(row.preset, [])
            ms = [r["metrics"] for r in rs]
            steps = [m["steps_to_goal_successes"]["mean"] for m in ms]
            ratio = [s / oracle_steps for s in steps] if oracle_steps else []
            tr = [r.get("training", {}) for r in rs]
            lines.append(
                f"| {row.name} | {len(rs)}/{seeds} | {_agg([m['success_rate'] for m in ms])} | "
                f"{_agg([m['spl'] for m in ms])} | {_agg(steps)} | "
                f"{_agg([m['steps_to_goal_failures_as_limit']['mean'] for m in ms])} | {_agg(ratio)} | "
                f"{_agg([m['return']['mean'] for m in ms])} | {_agg([m['collisions_per_episode'] for m in ms])} | "
                f"{_agg([t.get('minutes') for t in tr])} | {_agg([t.get('env_steps') for t in tr])} | {row.paper} |"
            )  # fmt: skip
            data["rows"][row.preset] = {"name": row.name, "table": table, "paper": row.paper,
                                        "runs": [{"metrics": m, "training": t} for m, t in zip(ms, tr, strict=True)]}  # fmt: skip
        for policy in ("oracle", "random"):
            m = base.get(f"{policy}-table{table}", {}).get("metrics")
            if m:
                data["baselines"][f"{policy}-table{table}"] = m
                lines.append(
                    f"| {policy} (baseline) | - | {m['success_rate']:.3g} | {m['spl']:.3g} | "
                    f"{m['steps_to_goal_successes']['mean']:.3g} | {m['steps_to_goal_failures_as_limit']['mean']:.3g} | "
                    f"{'1' if policy == 'oracle' else '-'} | {m['return']['mean']:.3g} | {m['collisions_per_episode']:.3g} | - | - | - |"
                )  # fmt: skip
        lines.append("")
    # targets
    ppo = [r["metrics"] for r in results.get("paper-ppo", [])]
    if ppo:
        succ = statistics.mean(m["success_rate"] for m in ppo)
        spl_ = statistics.mean(m["spl"] for m in ppo)
        mins = [r.get("training", {}).get("minutes") or 0 for r in results["paper-ppo"]]
        met = succ >= 0.95 and spl_ >= 0.80 and max(mins) <= 30
        data["targets"].append({"target": "Table 1 PPO: success >= 95%, SPL >= 0.80, <= 30 min",
                                "measured": {"success": succ, "spl": spl_, "max_minutes": max(mins)}, "met": met})  # fmt: skip
    best = None
    for preset in ("paper-mlp", "paper-lstm", "paper-gtrxl"):
        ms = [r["metrics"] for r in results.get(preset, [])]
        if ms:
            steps = statistics.mean(m["steps_to_goal_failures_as_limit"]["mean"] for m in ms)
            succ = statistics.mean(m["success_rate"] for m in ms)
            mins = max(r.get("training", {}).get("minutes") or 0 for r in results[preset])
            if best is None or steps < best[1]:
                best = (preset, steps, succ, mins)
    if best:
        data["targets"].append({"target": "Table 2 best memory network: <= 100 steps (failures = limit), success >= 90%, <= 60 min",
                                "measured": {"preset": best[0], "steps": best[1], "success": best[2], "max_minutes": best[3]},
                                "met": best[1] <= 100 and best[2] >= 0.9 and best[3] <= 60})  # fmt: skip
    lines += ["## Targets", ""]
    for t in data["targets"]:
        shown = ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in t["measured"].items()
        )
        lines.append(f"- {t['target']}: {'MET' if t['met'] else 'NOT met'} ({shown})")
    if not data["targets"]:
        lines.append("- no row finished yet")
    machines: dict[str, list[str]] = {}
    for row in ROWS:
        for run in results.get(row.preset, []):
            seed = (run.get("training") or {}).get("seed")
            where = (run.get("training") or {}).get("machine") or "machine not recorded"
            machines.setdefault(where, []).append(f"{row.preset} s{seed}")
    lines += ["", "## Machines (train minutes compare only within one machine)", ""]
    lines += [f"- {where}: {', '.join(runs)}" for where, runs in machines.items()]
    lines += ["", "## Notes", ""] + [f"- {note}" for note in NOTES]
    data["notes"] = list(NOTES)
    return "\n".join(lines) + "\n", data


def run_learning_bench(out_dir: Path, runs_dir: Path, rows: list[str] | None, seeds: int = 3,
                       scale: float = 1.0, say=print) -> tuple[str, dict]:  # fmt: skip
    """Train/evaluate what is missing, then write report.md and report.json into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    runs_dir.mkdir(parents=True, exist_ok=True)
    say("baselines (oracle, random)")
    base = baselines(runs_dir)
    # Seeds finished on another machine or in an earlier checkout survive in the committed
    # report.json even when their run folders (git-ignored) are gone: keep them.
    kept: dict[tuple[str, int], dict[str, Any]] = {}
    previous = out_dir / "report.json"
    if previous.exists():
        for preset, row_data in json.loads(previous.read_text()).get("rows", {}).items():
            for run in row_data.get("runs", []):
                seed = (run.get("training") or {}).get("seed")
                if seed is not None:
                    kept[(preset, int(seed))] = run
    # Until a row is reached, the report shows what was kept for it, so a report written mid-run
    # (after every seed) never drops a finished seed.
    results: dict[str, list[dict[str, Any]]] = {
        row.preset: [kept[(row.preset, s)] for s in range(seeds) if (row.preset, s) in kept]
        for row in ROWS
    }

    def write() -> None:
        markdown, data = build_report(results, base, seeds)
        (out_dir / "report.md").write_text(markdown)
        (out_dir / "report.json").write_text(json.dumps(data, indent=2))

    for row in ROWS:
        done: list[dict[str, Any]] = []
        for seed in range(seeds):
            path = runs_dir / f"{_slug(row)}-s{seed}" / "eval" / "eval.json"
            if path.exists():
                done.append(json.loads(path.read_text()))
            elif (row.preset, seed) in kept:
                done.append(kept[(row.preset, seed)])
            elif not rows or row.preset in rows:
                say(f"{row.name}, seed {seed}")
                done.append(run_one(row, seed, runs_dir, scale, say))
                results[row.preset] = done + [
                    kept[(row.preset, s)] for s in range(seed + 1, seeds) if (row.preset, s) in kept
                ]
                write()
        results[row.preset] = done
    write()
    return build_report(results, base, seeds)
