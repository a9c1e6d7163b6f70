"""`quicknav bench learning`: the paper's Tables 1 and 2 as a reproducible benchmark.

Every row trains a preset with several seeds under a wall-clock cap, evaluates each run on 100
held-out episodes (test bank, episode seed 0, deterministic actions), and reports mean ± std across
seeds beside the paper's numbers, together with the oracle and random baselines on the same
episodes. Runs are resumable: a (row, seed) whose eval.json exists is not trained again, so the
benchmark can be completed over several sessions. Nothing is tuned on the test bank: the presets
are fixed before evaluation.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import re
import shutil
import statistics
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from quicknav_core.config import EnvConfig, get_preset, resolve_eval, resolve_train
from quicknav_core.layout import EVAL, RunFolder
from quicknav_core.runtime import Runtime

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np


REWARDS = {
    "paper": "the paper's reward (sign of progress)",
    "shaped": "potential-based shaping, Φ = -distance to goal, γ = the trainer's discount",
}


@dataclass(frozen=True)
class Row:
    name: str
    table: int
    preset: str
    total_steps: int
    max_minutes: float
    paper: str  # the paper's figure for this row
    reward: str = "paper"  # a key of REWARDS
    overrides: tuple[tuple[str, Any], ...] = ()  # extra TrainConfig overrides (dotted keys)
    family: str = ""  # the paper row this one answers (the targets group by it); "" = name
    variant: str = ""  # a key suffix for rows that share a preset and reward (e.g. "curriculum")

    @property
    def key(self) -> str:
        """The row's name in report.json and its run folders: the preset, its variant, '-shaped'."""
        key = self.preset + (f"-{self.variant}" if self.variant else "")
        return key if self.reward == "paper" else f"{key}-{self.reward}"

    @property
    def label(self) -> str:
        return self.name if self.reward == "paper" else f"{self.name}, shaped reward"

    def request(self, seed: int, total_steps: int) -> dict[str, Any]:
        """The train request of one seed: the preset, the row's reward and overrides, the budget."""
        overrides: dict[str, Any] = {"seed": seed, "total_steps": total_steps}
        if self.reward == "shaped":
            gamma = get_preset(self.preset).algorithm.gamma
            overrides |= {"env.reward.progress": "potential", "env.reward.potential_gamma": gamma}
        overrides |= dict(self.overrides)
        return {"preset": self.preset, "overrides": overrides}


def _both(name, table, preset, steps, minutes, paper) -> tuple[Row, Row]:
    return (Row(name, table, preset, steps, minutes, paper),
            Row(name, table, preset, steps, minutes, paper, reward="shaped"))  # fmt: skip


ROWS = (
    *_both("PPO (MLP 2x128)", 1, "paper-ppo", 20_000_000, 30, "reward 96.87 ± 8.50"),
    *_both("SAC (MLP 2x128)", 1, "paper-sac", 4_000_000, 30, "reward 73.52 ± 51.59"),
    *_both("TD3 (MLP 2x128)", 1, "paper-td3", 8_000_000, 30, "reward 85.99 ± 36.22"),
    # Table 2 budgets: the target allows 60 min per run; the step budgets (the learning rate anneals
    # over them) keep one seed near 8-12 min on 2 cores (MLP and LSTM train at ~90-130k steps/s,
    # GTrXL at ~14k steps/s).
    *_both("PPO + MLP with memory", 2, "paper-mlp", 60_000_000, 60, "steps 214.61 ± 94.53"),
    *_both("PPO + LSTM", 2, "paper-lstm", 60_000_000, 60, "steps 126.60 ± 75.71"),
    *_both("PPO + GTrXL", 2, "paper-gtrxl", 6_000_000, 60, "steps 133.90 ± 88.94"),
    # tuned on the train bank (the preset's notes say how)
    Row("PPO + LSTM, tuned 1x32", 2, "tuned-lstm", 60_000_000, 60, "steps 126.60 ± 75.71",
        family="PPO + LSTM"),
    Row("PPO + LSTM, tuned 1x32, curriculum", 2, "tuned-lstm", 60_000_000, 60, "steps 126.60 ± 75.71",
        family="PPO + LSTM", variant="curriculum", overrides=(("curriculum.enabled", True),)),
    # the paper's GTrXL with the budget of the other Table 2 rows, now that it trains 3.7x faster
    Row("PPO + GTrXL, 60M steps", 2, "paper-gtrxl", 60_000_000, 60, "steps 133.90 ± 88.94",
        family="PPO + GTrXL", variant="60m"),
    # tuned on the train bank under the shaped reward: policy delay 2 (the preset's notes)
    Row("TD3 (MLP 2x128), tuned", 1, "tuned-td3", 6_000_000, 30, "reward 85.99 ± 36.22",
        reward="shaped", family="TD3 (MLP 2x128)"),
    # tuned on the train bank: embedding 16 and a higher learning rate (the preset's notes)
    Row("PPO + GTrXL, tuned embed 16", 2, "tuned-gtrxl", 20_000_000, 60, "steps 133.90 ± 88.94",
        family="PPO + GTrXL"),
)
ROW_KEYS = tuple(r.key for r in ROWS)
NOTES = (
    "Configs: `quicknav presets` / `quicknav_core/config/presets.py`; each seed is the preset with "
    "`seed` = 0, 1, 2 and the row's step budget; a seed stops at its step budget or its time cap. "
    "Nothing was tuned on the test bank: tuned presets come from sweeps scored on the train bank "
    "(`benchmarks/sweeps/`, results in `benchmarks/results/sweeps/`).",
    "Rewards. 'paper': the paper's formula with its sign-of-progress term (+λp for any step that "
    "shortens the distance, however little). Under it TD3 collects a higher return than the oracle by "
    "wiggling towards the goal without reaching it (`tests/core/test_reward.py` shows a circling "
    "policy out-earning the oracle). 'shaped': the same weights with `reward.progress=\"potential\"` "
    "(λp·(d_{t-1} - γ·d_t)/step, d = 0 at the goal, γ = the trainer's discount): potential-based "
    "shaping (Ng, Harada, Russell 1999), whose optimal policy is the one of the reward without the "
    "progress term. Returns of shaped rows are not comparable with the paper-reward baselines.",
    "Shaped rows of the goal-hidden agents. The LSTM and GTrXL at the paper's sizes learned to stand "
    "still under shaping (0 % on every seed; the 'return' column is high because a parked robot "
    "collects λp·(1-γ)·d/(v·dt) per step, which discounting cancels). A one-change diagnosis on "
    "the train bank (`benchmarks/shaped_memory.py`, results in `benchmarks/results/shaped_memory.json`, 20M "
    "steps each): the paper reward 0.81 training success; shaped 0.00 with an accurate critic "
    "(explained variance 0.87); shaped with γ 0.99 0.00; the paper reward with γ 0.99 0.00 (parked "
    "from 5M steps on); shaped with the tuned LSTM 1x32 0.00; shaped with the goal observed 0.00 "
    "(explained variance 0.92), so the hidden goal is not the cause. Shaping telescopes: by hand, "
    "for a straight 8 m drive at full speed (80 steps, no collisions) under the LSTM preset's "
    "weights and γ 0.96, the discounted value of reaching the goal beats standing still by 2.3 "
    "(γ^T·λg less the saved step penalties) where the sign term gives 13.0. That thin margin is "
    "the same for the MLP agents, which learn under shaping at the same γ 0.96, so it does not "
    "explain the difference alone; what we know is that the recurrent networks park and the "
    "feed-forward ones do not. Table 2's ≥90 % rows for the LSTM and GTrXL use the paper's reward.",
    "Table 2 presets use 64-step rollouts, 16 minibatches of whole env sequences and 4 epochs "
    "(QuickNav's choice): with the paper's 512-step rollouts recurrent PPO made 16 gradient steps per "
    "131k env steps and every memory agent stayed at the random policy. Rewards and other PPO values "
    "are the paper's tuned ones.",
    "PPO + GTrXL (paper row) is undertrained: its 6M-step budget was set when it trained at 5-14k "
    "steps/s. The GTrXL replay now runs a whole rollout as one banded attention per layer "
    "(`benchmarks/gtrxl_replay.py`: 12.6k -> 46.9k env steps/s on 2 cores); the 60M-step and tuned "
    "GTrXL rows train with that. The tuned row's embedding 16 and learning rate come from a "
    "train-bank sweep stopped after 2 trials (`benchmarks/results/sweeps/README.md`).",
    "Seeds with 'machine not recorded' ran before the report stored machines, on this project's "
    "2-core CPU VMs. Seeds' minutes on one VM compare only when nothing else ran beside them; many "
    "later seeds trained two at a time on the 2 cores (TD3 beside GTrXL seeds; the shaped GTrXL, "
    "LSTM and memory-MLP seeds beside each other and a test run), so their minutes are upper bounds.",
    "The paper reports means over 10 episodes of one agent; the rows here are 100 held-out episodes "
    "per seed, mean ± std across seeds. Its Table 2 'steps to finish' is compared with our steps with "
    "failures counted as the 300-step limit (the stricter figure) and with steps over successes.",
)
EVAL_EPISODES = 100
EVAL_SEED = 0


def run_one(row: Row, seed: int, runs_dir: Path, scale: float = 1.0, say=print) -> dict[str, Any]:
    """Train (or finish training) one seed of a row and evaluate it; returns its eval result."""
    from quicknav_core.eval.evaluate import run_eval
    from quicknav_core.layout import RunFolder
    from quicknav_core.train.run import read_meta, train_run

    run_dir = runs_dir / f"{row.key}-s{seed}"
    eval_path = RunFolder(run_dir).eval_result
    if eval_path.exists():
        return json.loads(eval_path.read_text())
    steps = max(int(row.total_steps * scale), get_preset(row.preset).steps_per_update)
    cfg = resolve_train(row.request(seed, steps))
    cap_s = row.max_minutes * 60 * scale
    started = time.perf_counter()
    elapsed_before = 0.0
    marker = run_dir / "train_seconds.json"
    if marker.exists():
        elapsed_before = json.loads(marker.read_text())["seconds"]

    def stop(result) -> bool:
        spent = elapsed_before + time.perf_counter() - started
        marker.write_text(json.dumps({"seconds": spent}))
        say(f"  {row.key} s{seed}: {result.env_steps:,} steps, {spent / 60:.1f} min, "
            f"success {result.metrics.get('success_rate', float('nan')):.0%}")  # fmt: skip
        return spent >= cap_s

    run = RunFolder(run_dir)
    resume = run.config.exists() and run.checkpoint() is not None
    run_dir.mkdir(parents=True, exist_ok=True)
    runtime = Runtime()  # one for the run and its evaluation (banks built once)
    summary = train_run(cfg, run_dir, callback=stop, resume=resume, runtime=runtime)
    eval_cfg = resolve_eval(
        {"run": str(run_dir), "episodes": EVAL_EPISODES, "seed": EVAL_SEED},
        trained_env=lambda _source: cfg.env,
    )
    result, _ = run_eval(eval_cfg, run_dir / "eval", run_dir=run_dir, runtime=runtime)
    meta = read_meta(run_dir)
    result["training"] = {
        "env_steps": meta["env_steps"],
        "machine": _machine(),
        "minutes": json.loads(marker.read_text())["seconds"] / 60 if marker.exists() else None,
        "stopped_by_time_cap": summary["stopped"],
        "seed": seed,
        "total_steps": steps,
        "time_cap_minutes": cap_s / 60,
        "reward": row.reward,
        # what trained it: a later version can tell a seed that needs training again
        "quicknav": _version(),
        "network": cfg.network.model_dump(mode="json"),
    }
    eval_path.write_text(json.dumps(result, indent=2))
    return result


def _version() -> str:
    import quicknav_core

    return quicknav_core.__version__


def _why_rerun(recorded: dict[str, Any], scoreless: bool, before: str | None) -> str | None:
    """Why a recorded seed of a chosen row trains again, or None."""
    if scoreless and not recorded.get("per_episode"):
        return "no per-episode scores"
    if before and _older_than(recorded, before):
        return f"trained before QuickNav {before}"
    return None


def _older_than(recorded: dict[str, Any], version: str) -> bool:
    """Whether a recorded seed was trained by a QuickNav older than ``version`` (or unstamped)."""

    def parts(v: str) -> tuple[int, ...]:
        return tuple(int(p) for p in v.split("+")[0].split(".") if p.isdigit())

    stamp = recorded.get("training", {}).get("quicknav")
    return stamp is None or parts(stamp) < parts(version)


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
            path = runs_dir / f"baseline-{policy}-table{table}" / EVAL.result
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


def episode_scores(result: dict[str, Any], max_steps: int) -> dict[str, list[float]] | None:
    """Per-episode success, SPL and steps (failures as the limit) of one seed's eval, or None when
    the seed was recorded before the report kept episodes."""
    per = result.get("per_episode")
    if not per:
        return None
    if "spl" in per:  # already reduced (a run kept in report.json)
        return {k: list(per[k]) for k in ("success", "spl", "steps")}
    success = [bool(s) for s in per["success"]]
    spl = [float(s) * r / max(p, r, 1e-9)
           for s, p, r in zip(success, per["path_length"], per["reference_length"], strict=True)]  # fmt: skip
    steps = [int(n) if s else max_steps for s, n in zip(success, per["steps"], strict=True)]
    return {"success": [int(s) for s in success], "spl": [round(x, 4) for x in spl], "steps": steps}


def _matrix(runs: list[dict[str, Any]], field: str) -> np.ndarray | None:
    """(seeds, episodes) scores of a row, or None unless every seed kept the same episodes."""
    import numpy as np

    per = [r.get("per_episode") for r in runs]
    if not per or any(p is None for p in per) or len({len(p[field]) for p in per}) != 1:
        return None
    return np.asarray([p[field] for p in per], dtype=np.float64)


def _ci(point: float, lo: float, hi: float, fmt: str = ".3f") -> str:
    if math.isnan(lo):
        return f"{point:{fmt}}"
    return f"{point:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def aggregate_row(runs: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Mean and IQM with stratified-bootstrap 95 % intervals over seeds x episodes, or None."""
    from quicknav_core.eval.aggregate import interval, iqm, mean

    success, spl, steps = (_matrix(runs, f) for f in ("success", "spl", "steps"))
    if success is None or spl is None or steps is None:
        return None
    out: dict[str, Any] = {"seeds": int(success.shape[0]), "episodes": int(success.shape[1])}
    for name, scores, statistic in (("success_mean", success, mean), ("spl_mean", spl, mean),
                                    ("spl_iqm", spl, iqm), ("steps_iqm", steps, iqm),
                                    ("steps_mean", steps, mean)):  # fmt: skip
        point, lo, hi = interval(scores, statistic)
        out[name] = {"point": point, "ci95": [lo, hi]}
    return out


def _targets(results: dict[str, list[dict[str, Any]]], seeds: int) -> list[dict[str, Any]]:
    """The issue's targets: the paper's two, then each algorithm/network at >= 90 % success."""
    targets = []
    ppo = [r["metrics"] for r in results.get("paper-ppo", [])]
    if ppo:
        succ = statistics.mean(m["success_rate"] for m in ppo)
        spl_ = statistics.mean(m["spl"] for m in ppo)
        mins = [r.get("training", {}).get("minutes") or 0 for r in results["paper-ppo"]]
        met = succ >= 0.95 and spl_ >= 0.80 and max(mins) <= 30
        targets.append({"target": "Table 1 PPO: success >= 95%, SPL >= 0.80, <= 30 min",
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
        targets.append({"target": "Table 2 best memory network: <= 100 steps (failures = limit), success >= 90%, <= 60 min",
                        "measured": {"preset": best[0], "steps": best[1], "success": best[2], "max_minutes": best[3]},
                        "met": best[1] <= 100 and best[2] >= 0.9 and best[3] <= 60})  # fmt: skip
    # Every algorithm (Table 1) and memory network (Table 2): some row of it, under either reward,
    # with all seeds done, mean success >= 90 % (Table 2 also <= 100 steps, failures = limit).
    for name, table, preset in ((r.name, r.table, r.preset) for r in ROWS if r.reward == "paper" and not r.family):
        candidates = []
        for row in ROWS:
            runs = results.get(row.key, [])
            if (row.family or row.name) != name or len(runs) < seeds:
                continue
            succ = statistics.mean(r["metrics"]["success_rate"] for r in runs)
            steps = statistics.mean(r["metrics"]["steps_to_goal_failures_as_limit"]["mean"] for r in runs)
            ok = succ >= 0.9 and (table == 1 or steps <= 100)
            candidates.append((ok, succ, -steps, row.key, steps))
        rule = "success >= 90%" + (", <= 100 steps (failures = limit)" if table == 2 else "")
        t = {"target": f"{name}: a row with {seeds} seeds, {rule}", "met": False, "measured": {}}
        if candidates:
            ok, succ, _, key, steps = max(candidates)
            t["met"] = ok
            t["measured"] = {"row": key, "success": succ} | ({"steps": steps} if table == 2 else {})
        else:
            t["measured"] = {"row": f"no row of {preset} with {seeds} seeds yet"}
        targets.append(t)
    return targets


def _num(value) -> str:
    """A number as the report prints it; an undefined one (no successes: null in report.json,
    NaN before it is written) as '-'."""
    if value is None or value != value:
        return "-"
    return f"{value:.3g}"


def build_report(
    results: dict[str, list[dict[str, Any]]], base: dict[str, dict[str, Any]], seeds: int,
    profile_path: Path | None = None,
) -> tuple[str, dict]:  # fmt: skip
    """Markdown + JSON of everything finished so far, and which targets are met; with
    ``profile_path``, also the performance-profile plot of the rows that kept their episodes."""
    lines = ["# QuickNav learning benchmark: the paper's Tables 1 and 2", "",
             f"Each row: {seeds} training seeds, each evaluated on {EVAL_EPISODES} held-out test episodes "
             f"(episode seed {EVAL_SEED}, deterministic actions); mean ± std across seeds. "
             "Rewards: 'paper' = " + REWARDS["paper"] + "; 'shaped' = " + REWARDS["shaped"] + ".", ""]  # fmt: skip
    data: dict[str, Any] = {"rows": {}, "baselines": {}, "targets": [], "rewards": REWARDS}
    agg_lines: list[str] = []
    panels = []
    for table in (1, 2):
        oracle = base.get(f"oracle-table{table}", {}).get("metrics", {})
        oracle_steps = oracle.get("steps_to_goal_successes", {}).get("mean")
        lines += [f"## Table {table}" + (": goal observed" if table == 1 else ": goal hidden (lidar, pose, memory)"), "",
                  "| row | reward | seeds done | success | SPL | steps to goal (successes) | steps (failures = 300) | "
                  "steps / oracle | return | collisions/ep | train min | env steps | budget | paper |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        agg_lines += [f"### Table {table}", "",
                      "| row | reward | seeds x episodes | success: mean [95% CI] | SPL: IQM [95% CI] | "
                      "SPL: mean [95% CI] | steps (failures = 300): IQM [95% CI] |",
                      "|---|---|---|---|---|---|---|"]  # fmt: skip
        profile_rows = []
        for row in ROWS:
            if row.table != table:
                continue
            rs = results.get(row.key, [])
            ms = [r["metrics"] for r in rs]
            steps = [m["steps_to_goal_successes"]["mean"] for m in ms]
            ratio = [s / oracle_steps for s in steps] if oracle_steps else []
            tr = [r.get("training", {}) for r in rs]
            lines.append(
                f"| {row.label} | {row.reward} | {len(rs)}/{seeds} | {_agg([m['success_rate'] for m in ms])} | "
                f"{_agg([m['spl'] for m in ms])} | {_agg(steps)} | "
                f"{_agg([m['steps_to_goal_failures_as_limit']['mean'] for m in ms])} | {_agg(ratio)} | "
                f"{_agg([m['return']['mean'] for m in ms])} | {_agg([m['collisions_per_episode'] for m in ms])} | "
                f"{_agg([t.get('minutes') for t in tr])} | {_agg([t.get('env_steps') for t in tr])} | "
                f"{row.total_steps / 1e6:g}M steps or {row.max_minutes:g} min | "
                f"{row.paper if row.reward == 'paper' else '-'} |"
            )  # fmt: skip
            max_steps = get_preset(row.preset).env.max_steps
            runs_out = []
            for r in rs:
                kept = {"metrics": r["metrics"], "training": r.get("training", {})}
                per = episode_scores(r, max_steps)
                if per is not None:
                    kept["per_episode"] = per
                runs_out.append(kept)
            agg = aggregate_row(runs_out) if runs_out else None
            data["rows"][row.key] = {"name": row.label, "table": table, "preset": row.preset,
                                     "reward": row.reward, "paper": row.paper,
                                     "aggregate": agg, "runs": runs_out}  # fmt: skip
            if agg:
                agg_lines.append(
                    f"| {row.label} | {row.reward} | {agg['seeds']} x {agg['episodes']} | "
                    f"{_ci(agg['success_mean']['point'], *agg['success_mean']['ci95'])} | "
                    f"{_ci(agg['spl_iqm']['point'], *agg['spl_iqm']['ci95'])} | "
                    f"{_ci(agg['spl_mean']['point'], *agg['spl_mean']['ci95'])} | "
                    f"{_ci(agg['steps_iqm']['point'], *agg['steps_iqm']['ci95'], fmt='.1f')} |"
                )  # fmt: skip
                profile_rows.append((f"{row.label}", _matrix(runs_out, "spl"), row.reward != "paper"))
            elif rs:
                agg_lines.append(f"| {row.label} | {row.reward} | - | n/a: these seeds were recorded "
                                 "before the report kept per-episode scores | | | |")  # fmt: skip
        for policy in ("oracle", "random"):
            m = base.get(f"{policy}-table{table}", {}).get("metrics")
            if m:
                data["baselines"][f"{policy}-table{table}"] = m
                lines.append(
                    f"| {policy} (baseline) | paper | - | {_num(m['success_rate'])} | {_num(m['spl'])} | "
                    f"{_num(m['steps_to_goal_successes']['mean'])} | {_num(m['steps_to_goal_failures_as_limit']['mean'])} | "
                    f"{'1' if policy == 'oracle' else '-'} | {_num(m['return']['mean'])} | {_num(m['collisions_per_episode'])} | - | - | - | - |"
                )  # fmt: skip
        lines.append("")
        agg_lines.append("")
        oracle_run = base.get(f"oracle-table{table}")
        oracle_scores = episode_scores(oracle_run, 300) if oracle_run and profile_rows else None
        if oracle_scores is not None:  # the reference curve: the planner driving the robot
            profile_rows.append(("oracle (baseline)", _matrix([{"per_episode": oracle_scores}], "spl"), True))
        panels.append((f"Table {table}" + (": goal observed" if table == 1 else ": goal hidden"), profile_rows))
    lines += ["## Aggregates over seeds x episodes (rliable protocol)", "",
              "Point estimates over all seeds x held-out episodes pooled; 95 % intervals from the stratified "
              "bootstrap (each episode a stratum, seeds resampled within it; 2,000 resamples, percentile "
              "intervals; `scipy.stats.bootstrap`, `quicknav_core/eval/aggregate.py`). IQM = mean of the middle "
              "50 % of scores. Success is 0/1 per episode, so it is given as a mean (its IQM would only say "
              "whether more than 75 % succeeded).", ""]  # fmt: skip
    lines += agg_lines
    if profile_path is not None:
        from quicknav_core.eval.pictures import draw_profiles

        draw_profiles(panels, profile_path)
        lines += [f"Performance profiles (SPL): `{profile_path.name}`.", ""]
    data["targets"] = _targets(results, seeds)
    lines += ["## Targets", ""]
    for t in data["targets"]:
        shown = ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in t["measured"].items()
        )
        lines.append(f"- {t['target']}: {'MET' if t['met'] else 'NOT met'} ({shown})")
    machines: dict[str, list[str]] = {}
    for row in ROWS:
        for run in results.get(row.key, []):
            seed = (run.get("training") or {}).get("seed")
            where = (run.get("training") or {}).get("machine") or "machine not recorded"
            machines.setdefault(where, []).append(f"{row.key} s{seed}")
    lines += ["", "## Machines (train minutes compare only within one machine)", ""]
    lines += [f"- {where}: {', '.join(runs)}" for where, runs in machines.items()]
    lines += ["", "## Notes", ""] + [f"- {note}" for note in NOTES]
    data["notes"] = list(NOTES)
    return "\n".join(lines) + "\n", data


def dump_report(data: dict[str, Any]) -> str:
    """report.json text: indented, but lists of numbers (per-episode scores) on one line each."""

    def one_line(m: re.Match) -> str:
        try:
            return json.dumps(json.loads(m.group(0)))
        except ValueError:  # not a JSON list after all (brackets inside a string)
            return m.group(0)

    return re.sub(r"\[[-\s\d.,eE+nulltruefals]*\]", one_line, json.dumps(data, indent=2)) + "\n"


def _recorded_seeds(report_json: Path) -> dict[tuple[str, int], dict[str, Any]]:
    """Every (row key, seed) a report.json holds, with its run."""
    if not report_json.exists():
        return {}
    out = {}
    for key, row_data in json.loads(report_json.read_text()).get("rows", {}).items():
        for run in row_data.get("runs", []):
            seed = (run.get("training") or {}).get("seed")
            if seed is not None:
                out[(key, int(seed))] = run
    return out


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


@contextmanager
def _locked(folder: Path):
    """An exclusive advisory lock on ``folder`` (held while a report is read, merged and written)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def run_learning_bench(out_dir: Path, runs_dir: Path, rows: list[str] | None, seeds: int = 3,
                       scale: float = 1.0, say=print, rerun_scoreless: bool = False,
                       rerun_before: str | None = None) -> tuple[str, dict]:  # fmt: skip
    """Train/evaluate what is missing, then write report.md, report.json and profiles.png into
    ``out_dir``. ``rows``: row keys (``ROW_KEYS``) to train now; None = all. ``rerun_scoreless``:
    also retrain the selected rows' seeds recorded before the report kept per-episode scores;
    ``rerun_before``: also those trained by a QuickNav older than that version (a fix changed what
    trains). Each recorded seed stays in the report until its new run is evaluated."""
    out_dir.mkdir(parents=True, exist_ok=True)
    runs_dir.mkdir(parents=True, exist_ok=True)
    say("baselines (oracle, random)")
    base = baselines(runs_dir)
    # Seeds finished on another machine or in an earlier checkout survive in the committed
    # report.json even when their run folders (git-ignored) are gone: keep them.
    previous = out_dir / "report.json"
    with _locked(out_dir):
        kept = _recorded_seeds(previous)
    own: dict[tuple[str, int], dict[str, Any]] = {}  # seeds this process trained or found in runs_dir

    def write() -> tuple[str, dict]:
        # Another `bench learning` process (other rows, same results folder) may have written seeds
        # since this one started: the file on disk is the authority for every seed this process did
        # not produce itself, read again under a lock on the folder.
        with _locked(out_dir):
            by_seed = kept | _recorded_seeds(previous) | own
            results = {row.key: [by_seed[(row.key, s)] for s in range(seeds) if (row.key, s) in by_seed]
                       for row in ROWS}  # fmt: skip
            markdown, data = build_report(results, base, seeds, out_dir / "profiles.png")
            _write_atomic(out_dir / "report.md", markdown)
            _write_atomic(previous, dump_report(data))  # a cut-off write never truncates it
        return markdown, data

    for row in ROWS:
        selected = not rows or row.key in rows
        for seed in range(seeds):
            run_dir = runs_dir / f"{row.key}-s{seed}"
            path = RunFolder(run_dir).eval_result
            recorded = kept.get((row.key, seed))

            if path.exists():
                found = json.loads(path.read_text())
                if rerun_before and selected and _older_than(found, rerun_before):
                    shutil.rmtree(run_dir)  # its checkpoint may not even load any more
                else:
                    own[(row.key, seed)] = found
                    continue
            why = _why_rerun(recorded, rerun_scoreless, rerun_before) if recorded and selected else None
            if recorded is not None and why is None:
                continue
            if selected:
                say(f"{row.label}, seed {seed}" + (f" (rerun: {why})" if why else ""))
                own[(row.key, seed)] = run_one(row, seed, runs_dir, scale, say)
                write()
    return write()
