"""`quicknav bench train`: end-to-end training throughput (env steps per second, compile excluded).

Each row builds the trainer of a paper preset (network sizes and hyperparameters as in the paper),
runs one chunk to compile and warm up, then times ``chunks`` more chunks. The figure is env steps
per wall-clock second of those chunks, gradient updates included.
"""

from __future__ import annotations

import json
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from quicknav_core.config import resolve_train
from quicknav_core.config.overrides import as_dict

# (row name, preset, chunk size in env steps)
ROWS = (
    ("ppo-mlp", "paper-ppo", 262_144),
    ("sac-mlp", "paper-sac", 8_192),
    ("td3-mlp", "paper-td3", 8_192),
    ("rppo-mlp-memory", "paper-mlp", 262_144),
    ("rppo-lstm", "paper-lstm", 262_144),
    ("rppo-gtrxl", "paper-gtrxl", 262_144),
)
TARGETS = {"ppo-mlp": 100_000, "rppo-lstm": 30_000, "rppo-gtrxl": 40_000}


@dataclass
class TrainBenchRow:
    name: str
    preset: str
    trainer: str
    network: str
    num_envs: int
    chunk_steps: int
    compile_and_first_chunk_s: float
    chunk_seconds: list[float]
    env_steps_per_s: float
    target: float | None


def bench_row(
    name: str, preset: str, chunk_steps: int, chunks: int, overrides: dict | list[str] | None = None
) -> TrainBenchRow:
    from quicknav_core.train.trainers import make_trainer

    cfg = resolve_train({"preset": preset, "overrides": {
        "chunk_steps": chunk_steps, **as_dict(overrides)}})  # fmt: skip
    # room for the warm-up chunk and every timed one, whatever the chunk rounds up to
    per_chunk = max(chunk_steps, cfg.steps_per_update)
    cfg = cfg.model_copy(update={"total_steps": per_chunk * (chunks + 1)})
    trainer = make_trainer(cfg)
    state = trainer.init_state()
    t0 = time.perf_counter()
    state, _ = trainer.run_chunk(state)
    first = time.perf_counter() - t0
    secs, done = [], []
    for _ in range(chunks):
        before = trainer.env_steps(state)
        t0 = time.perf_counter()
        state, _ = trainer.run_chunk(state)
        secs.append(time.perf_counter() - t0)
        done.append(trainer.env_steps(state) - before)
    if min(done) <= 0:
        raise RuntimeError(f"{name}: a timed chunk made no env steps (total_steps too small)")
    rate = statistics.median(n / s for n, s in zip(done, secs, strict=True))
    return TrainBenchRow(
        name, preset, cfg.trainer_kind, cfg.network.kind, cfg.num_envs, trainer.steps_per_chunk,
        round(first, 3), [round(s, 4) for s in secs], rate, TARGETS.get(name),
    )  # fmt: skip


def run_train_bench(
    names: list[str] | None = None,
    chunks: int = 3,
    overrides: dict | list[str] | None = None,
    progress=None,
) -> dict[str, Any]:
    from quicknav_core.bench.machine import machine_info

    say = progress or (lambda _m: None)
    rows = []
    for name, preset, chunk in ROWS:
        if names and name not in names:
            continue
        say(f"{name} ({preset})")
        rows.append(bench_row(name, preset, chunk, chunks, overrides))
    return {"machine": machine_info(), "chunks": chunks, "rows": [asdict(r) for r in rows]}


def write_report(report: dict[str, Any], out_dir: Path) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "bench_train.json"
    path.write_text(json.dumps(report, indent=2))
    return path
