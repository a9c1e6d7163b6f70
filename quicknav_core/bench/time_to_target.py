"""`quicknav bench time-to-target`: wall-clock time until a policy works, compile included.

What a user buys is minutes to a policy that reaches its goals, not env steps per second. For each
row (PPO, SAC, TD3 with MLPs; PPO with the memory MLP, the LSTM, the GTrXL) and each seed, one
training run in its own process:

- the clock starts when the trainer is built (JAX and the room banks are loaded before: they are
  the same for every row) and runs through compilation and every chunk of training;
- after a chunk, when the training time has grown by 10 % (+1 s) since the last evaluation, the
  policy plays 100 held-out episodes (the test bank, deterministic, the same episodes every time);
  the evaluation's own time is measured apart and not counted;
- the run stops at the first evaluation with success >= 90 % (its training time is the row's time
  to target) or at the row's time cap (it then did not reach the target).

Each row runs first with an empty JAX compilation cache (cold: what a first run costs) and then
every seed with the cache the cold run filled (warm: a user's second run, or a worker that has
seen the shape). The peers a user would pick instead run the same protocol in
``benchmarks/time_to_target_peers.py`` (Stable-Baselines3 on the NumPy twin) and join the table.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quicknav_core.compile_cache import MIN_COMPILE_TIME_S

TARGET = 0.9
EVAL_EPISODES = 100
EVAL_GROWTH = 1.10  # evaluate when the training time has grown by 10 % (+ EVAL_SLACK_S)
EVAL_SLACK_S = 1.0


@dataclass(frozen=True)
class Row:
    key: str
    label: str
    preset: str
    cap_minutes: float = 10.0
    overrides: tuple[tuple[str, Any], ...] = ()
    note: str = ""

    def request(self, seed: int) -> dict[str, Any]:
        return {"preset": self.preset, "overrides": {"seed": seed, **dict(self.overrides)}}


ROWS = (
    Row("ppo", "PPO (MLP 2x128)", "paper-ppo"),
    Row("ppo-fast", "PPO (MLP 2x128), wall-clock preset", "fast-ppo",
        note="the paper-ppo env and network with rollouts sized for wall-clock time"),
    Row("sac", "SAC (MLP 2x128)", "paper-sac"),
    Row("td3", "TD3 (MLP 2x128), tuned, shaped reward", "tuned-td3"),
    Row("mlp-memory", "PPO + MLP with memory", "paper-mlp"),
    Row("lstm", "PPO + LSTM, tuned 1x32, curriculum", "tuned-lstm",
        overrides=(("curriculum.enabled", True),)),
    Row("gtrxl", "PPO + GTrXL, tuned embed 16", "tuned-gtrxl"),
)
ROW_KEYS = tuple(r.key for r in ROWS)


@dataclass
class Evaluation:
    train_s: float  # training wall time before this evaluation (compile included)
    env_steps: int
    success: float
    eval_s: float  # this evaluation's own time (not counted)


@dataclass
class RunResult:
    row: str
    seed: int
    cache: str  # "cold" | "warm"
    cap_s: float
    reached: bool
    time_to_target_s: float | None
    steps_to_target: int | None
    train_s: float
    eval_s: float
    first_chunk_s: float  # compile and the first chunk
    evaluations: list[Evaluation] = field(default_factory=list)
    machine: str = ""


def evaluation_due(train_s: float, last_eval_s: float) -> bool:
    """The schedule: the training time grew by EVAL_GROWTH (+ EVAL_SLACK_S) since the last one."""
    return train_s >= last_eval_s * EVAL_GROWTH + EVAL_SLACK_S


def run_one(row: Row, seed: int, cap_s: float, cache: str,
            clock: Callable[[], float] = time.perf_counter) -> RunResult:  # fmt: skip
    """Train one seed of ``row`` until the held-out success reaches TARGET or ``cap_s`` (this
    process; ``run_in_process`` gives it a process and a compilation cache of its own)."""
    from quicknav_core.bench.machine import machine_line
    from quicknav_core.config import EvalConfig, resolve_train
    from quicknav_core.eval.agents import PolicyAgent
    from quicknav_core.eval.episodes import run_episodes
    from quicknav_core.runtime import Runtime
    from quicknav_core.train.trainers import make_trainer

    cfg = resolve_train(row.request(seed))
    # chunks of about a second of training: a chunk is the finest grain evaluations can see
    cfg = cfg.model_copy(update={"chunk_steps": max(cfg.steps_per_update, 16_384)})
    runtime = Runtime()  # the run's banks and compiled programs
    test_env, test_params = cfg.env.build("test", runtime)
    cfg.env.build("train", runtime)  # room banks are built before the clock starts, as for every row
    eval_cfg = EvalConfig(episodes=EVAL_EPISODES, seed=0, deterministic=True, gif_episodes=0)
    result = RunResult(row.key, seed, cache, cap_s, False, None, None, 0.0, 0.0, 0.0,
                       machine=machine_line())  # fmt: skip
    t0 = clock()
    trainer = make_trainer(cfg, runtime)
    state = trainer.init_state()
    last_eval = 0.0
    done_updates = 0
    while result.train_s < cap_s and done_updates < trainer.num_updates:
        state, _ = trainer.run_chunk(state)
        done_updates = trainer.updates_done(state)
        now = clock()
        if not result.first_chunk_s:
            result.first_chunk_s = now - t0
        result.train_s = now - t0 - result.eval_s
        if not evaluation_due(result.train_s, last_eval) and done_updates < trainer.num_updates:
            continue
        e0 = clock()
        ep = run_episodes(test_env, test_params, PolicyAgent(trainer.policy(state)), eval_cfg,
                          runtime=runtime)  # fmt: skip
        success = float(ep.success.mean())
        spent = clock() - e0
        result.eval_s += spent
        last_eval = result.train_s
        steps = trainer.env_steps(state)
        result.evaluations.append(Evaluation(round(result.train_s, 3), steps, success, round(spent, 3)))
        if success >= TARGET:
            result.reached = True
            result.time_to_target_s = result.train_s
            result.steps_to_target = steps
            break
    return result


def run_in_process(row: Row, seed: int, cap_s: float, cache_dir: Path, cache: str,
                   timeout_s: float) -> RunResult:  # fmt: skip
    """``run_one`` in a fresh Python process with its own JAX compilation cache folder."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        # the CLI's own cache setting (quicknav_core.compile_cache); the recorded rows up to the
        # 2026-11-27 stop were measured when it cached programs of 0.5 s and more
        env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache_dir),
               "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(MIN_COMPILE_TIME_S)}  # fmt: skip
        code = ("import sys, json, dataclasses; from pathlib import Path;"
                "from quicknav_core.bench import time_to_target as t;"
                f"r = t.run_one(t.ROWS[{ROW_KEYS.index(row.key)}], {seed}, {cap_s}, {cache!r});"
                f"Path({str(out)!r}).write_text(json.dumps(dataclasses.asdict(r)))")  # fmt: skip
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                              timeout=timeout_s)  # fmt: skip
        if done.returncode != 0 or not out.exists():
            raise RuntimeError(f"{row.key} seed {seed} ({cache}) failed:\n{done.stderr[-3000:]}")
        data = json.loads(out.read_text())
    data["evaluations"] = [Evaluation(**e) for e in data["evaluations"]]
    return RunResult(**data)


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median and spread of the times to target of a row's runs (None where no run reached it)."""
    times = [r["time_to_target_s"] for r in runs if r["reached"]]
    return {
        "runs": len(runs), "reached": len(times),
        "median_s": statistics.median(times) if len(times) == len(runs) and times else None,
        "min_s": min(times) if times else None, "max_s": max(times) if times else None,
        "times_s": [r["time_to_target_s"] for r in runs],
    }  # fmt: skip


def run_bench(rows: list[str] | None, seeds: int, out_dir: Path, scale: float = 1.0,
              say=print) -> dict[str, Any]:  # fmt: skip
    """Every chosen row: one cold run (seed 0, empty cache), then ``seeds`` warm runs; results are
    merged into ``out_dir/time_to_target.json`` (rows not run keep their recorded results)."""
    from quicknav_core.bench.machine import machine_info

    path = out_dir / "time_to_target.json"
    data = json.loads(path.read_text()) if path.exists() else {"rows": {}}
    data["machine"] = machine_info()
    data["protocol"] = {"target": TARGET, "eval_episodes": EVAL_EPISODES,
                        "eval_growth": EVAL_GROWTH, "eval_slack_s": EVAL_SLACK_S}  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    for row in ROWS:
        if rows and row.key not in rows:
            continue
        cap_s = row.cap_minutes * 60 * scale
        with tempfile.TemporaryDirectory() as cache_dir:
            say(f"{row.label}: cold (empty compilation cache), seed 0")
            cold = run_in_process(row, 0, cap_s, Path(cache_dir), "cold", cap_s * 3 + 600)
            say(f"  {_run_line(cold)}")
            warm = []
            for seed in range(seeds):
                say(f"{row.label}: warm, seed {seed}")
                warm.append(run_in_process(row, seed, cap_s, Path(cache_dir), "warm",
                                           cap_s * 3 + 600))  # fmt: skip
                say(f"  {_run_line(warm[-1])}")
        from dataclasses import asdict

        entry = {"label": row.label, "preset": row.preset, "overrides": dict(row.overrides),
                 "cap_s": cap_s, "note": row.note, "cold": asdict(cold),
                 "warm": [asdict(w) for w in warm]}  # fmt: skip
        entry["warm_summary"] = summarize(entry["warm"])
        data["rows"][row.key] = entry
        path.write_text(json.dumps(data, indent=2))
        say(_line(entry))
    return data


def _run_line(r: RunResult) -> str:
    last = r.evaluations[-1] if r.evaluations else None
    got = (f"reached 90 % after {r.time_to_target_s:.1f} s ({r.steps_to_target:,} env steps)"
           if r.reached else f"not reached in {r.train_s:.0f} s"
           + (f" (last: {last.success:.0%} at {last.env_steps:,} steps)" if last else ""))  # fmt: skip
    return f"{got}; {len(r.evaluations)} evaluations took {r.eval_s:.1f} s (not counted)"


def _line(entry: dict[str, Any]) -> str:
    s = entry["warm_summary"]
    cold = entry["cold"]
    warm = (f"median {s['median_s']:.1f} s (min {s['min_s']:.1f}, max {s['max_s']:.1f})"
            if s["median_s"] is not None else f"{s['reached']}/{s['runs']} reached 90 %")  # fmt: skip
    cold_s = f"{cold['time_to_target_s']:.1f} s" if cold["reached"] else "not reached"
    return f"{entry['label']}: warm {warm}; cold {cold_s} (cap {entry['cap_s'] / 60:.0f} min)"


MARKERS = ("<!-- time-to-target:start -->", "<!-- time-to-target:end -->")


def between_markers(markdown: str) -> str | None:
    """The text a page holds between the time-to-target markers, or None without them."""
    start, end = markdown.find(MARKERS[0]), markdown.find(MARKERS[1])
    if start < 0 or end < start:
        return None
    return markdown[start + len(MARKERS[0]):end].strip()


def write_between_markers(page: Path, table: str) -> None:
    """Put ``table`` between the markers of ``page`` (README.md, docs/performance.md)."""
    text = page.read_text()
    if between_markers(text) is None:
        raise ValueError(f"{page}: no {MARKERS[0]} ... {MARKERS[1]} block to write the table into")
    start, end = text.find(MARKERS[0]) + len(MARKERS[0]), text.find(MARKERS[1])
    page.write_text(f"{text[:start]}\n{table.strip()}\n{text[end:]}")


def _machine_words(info: dict[str, Any]) -> str:
    """A results file's machine in the words of ``machine_line`` (peers record no JAX backend)."""
    words = f"{info.get('cpu', '?')}, {info.get('cores', '?')} cores"
    return f"{words}, {info['jax_backend']}" if "jax_backend" in info else f"{words}, cpu"


def report(results: Path, peers: Path | None = None) -> str:
    """The table: each row's warm median (min-max) and cold time to target, with its peer beside
    it and the ratio (peer / QuickNav), as Markdown."""
    data = json.loads(results.read_text()) if results.exists() else {"rows": {}}
    peer_rows: dict[str, Any] = {}
    peer_data: dict[str, Any] = {}
    if peers is not None and peers.exists():
        peer_data = json.loads(peers.read_text())
        peer_rows = {v["beside"]: v for v in peer_data["rows"].values()}

    def fmt(s: float | None) -> str:
        return "—" if s is None else (f"{s:.1f} s" if s < 120 else f"{s / 60:.1f} min")

    def spread(summary: dict[str, Any]) -> str:
        if summary["median_s"] is None:
            return f"{summary['reached']}/{summary['runs']} seeds reached 90 %" + (
                f" (fastest {fmt(summary['min_s'])})" if summary["min_s"] is not None else "")
        return f"{fmt(summary['median_s'])} ({fmt(summary['min_s'])}–{fmt(summary['max_s'])})"

    # every figure names the machine it was measured on: rows recorded in other sittings keep theirs
    machines: list[str] = []

    def mark(machine: str) -> str:
        if machine not in machines:
            machines.append(machine)
        return f"[{chr(ord('A') + machines.index(machine))}]"

    lines = ["| row | warm: median (min–max) | cold | peer: median (min–max) | peer / QuickNav |",
             "|---|---|---|---|---|"]  # fmt: skip
    for row in ROWS:
        entry = data["rows"].get(row.key)
        if entry is None:
            continue
        s, cold = entry["warm_summary"], entry["cold"]
        ours = mark(cold.get("machine") or _machine_words(data.get("machine", {})))
        peer = peer_rows.get(row.key)
        peer_cell, ratio = "", ""
        if peer is not None:
            ps = peer["summary"]
            theirs = mark(_machine_words(peer_data.get("machine", {})))
            cap = peer["runs"][0]["cap_s"] if peer["runs"] else None
            capped = f", cap {fmt(cap)} per run" if cap and ps["reached"] < ps["runs"] else ""
            peer_cell = f"{peer['label']}: {spread(ps)}{capped} {theirs}"
            if ps["median_s"] is not None and s["median_s"]:
                ratio = f"{ps['median_s'] / s['median_s']:.1f}x"
            elif s["median_s"] and ps["reached"] < ps["runs"]:
                ratio = f"> {ps['runs'] and peer['runs'][0]['cap_s'] / s['median_s']:.0f}x (peer capped)"
        lines.append(f"| {entry['label']} {ours} | {spread(s)} | "
                     f"{fmt(cold['time_to_target_s']) if cold['reached'] else 'not reached'} | "
                     f"{peer_cell} | {ratio} |")  # fmt: skip
    lines.append("")
    lines.append("Machines: " + "; ".join(f"[{chr(ord('A') + i)}] {m}"
                                          for i, m in enumerate(machines)) + ".")  # fmt: skip
    lines.append(f"Held-out success >= {TARGET:.0%} on {EVAL_EPISODES} test-bank episodes;"
                 " caps: 10 min per QuickNav run, as stated per peer run.")  # fmt: skip
    return "\n".join(lines)
