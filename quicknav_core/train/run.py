"""Run folders: training in chunks with progress callbacks, checkpoints, resume, learning curves.

A run folder holds
  config.json          the exact TrainConfig
  metrics.jsonl        one JSON line per chunk (env steps, wall time, steps/s, losses, episode stats)
  checkpoint/          state.msgpack (flax msgpack, no pickle) and meta.json, written atomically
  learning_curve.png   return and success rate against env steps
The same ``train_run`` serves the CLI (a progress bar) and the service worker (progress events and
cancellation between chunks: the callback returns True to stop).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quicknav_core.config import TrainConfig

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
CHECKPOINT_DIR = "checkpoint"
STATE_FILE = "state.msgpack"
META_FILE = "meta.json"
CURVE_FILE = "learning_curve.png"


@dataclass
class ChunkResult:
    chunk: int  # 1-based index of the chunk just finished
    chunks: int  # chunks in the whole run
    env_steps: int
    total_steps: int  # env steps the whole run will have made
    wall_s: float  # seconds this chunk took (compile included on the first)
    steps_per_s: float
    metrics: dict[str, float]

    def record(self) -> dict[str, Any]:
        return {
            "chunk": self.chunk, "env_steps": self.env_steps, "wall_s": round(self.wall_s, 4),
            "steps_per_s": round(self.steps_per_s, 1), **self.metrics,
        }  # fmt: skip


ProgressCallback = Callable[[ChunkResult], bool | None]


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save_checkpoint(run_dir: Path, trainer, state, chunk: int) -> Path:
    """Write the full trainer state and its meta data; the previous checkpoint stays until replaced."""
    ckpt = Path(run_dir) / CHECKPOINT_DIR
    ckpt.mkdir(parents=True, exist_ok=True)
    _write_atomic(ckpt / STATE_FILE, trainer.to_bytes(state))
    meta = {
        "chunk": chunk, "env_steps": trainer.env_steps(state),
        "trainer": trainer.config.trainer_kind, "format": "flax-msgpack-v1",
    }  # fmt: skip
    _write_atomic(ckpt / META_FILE, json.dumps(meta).encode())
    return ckpt


def load_run(run_dir: Path, trainer=None):
    """(config, trainer, state, meta) of a run folder's last checkpoint (``trainer``: a warm one)."""
    from quicknav_core.train.trainers import make_trainer

    run_dir = Path(run_dir)
    cfg_path = run_dir / CONFIG_FILE
    if not cfg_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run folder: no {CONFIG_FILE}")
    config = TrainConfig.model_validate_json(cfg_path.read_text())
    ckpt = run_dir / CHECKPOINT_DIR
    if not (ckpt / STATE_FILE).exists():
        raise FileNotFoundError(f"{run_dir} has no checkpoint yet ({CHECKPOINT_DIR}/{STATE_FILE})")
    meta = json.loads((ckpt / META_FILE).read_text())
    trainer = trainer if trainer is not None and trainer.config == config else make_trainer(config)
    state = trainer.from_bytes((ckpt / STATE_FILE).read_bytes())
    return config, trainer, state, meta


def read_metrics(run_dir: Path) -> list[dict[str, Any]]:
    path = Path(run_dir) / METRICS_FILE
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def train_run(
    config: TrainConfig,
    run_dir: Path,
    callback: ProgressCallback | None = None,
    resume: bool = False,
    checkpoint_every: int = 1,
    trainer=None,
) -> dict[str, Any]:
    """Train ``config`` into ``run_dir`` (or continue it with ``resume``). Returns a summary.

    After every chunk: metrics are appended, a checkpoint is written every ``checkpoint_every``
    chunks (and always at the end or on a stop), and ``callback`` may return True to stop.
    """
    from quicknav_core.train.trainers import make_trainer

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        config, trainer, state, meta = load_run(run_dir, trainer)
        done_chunks = int(meta["chunk"])
        # drop metric lines written after the checkpoint (a crash between the two)
        kept = [m for m in read_metrics(run_dir) if m["chunk"] <= done_chunks]
        (run_dir / METRICS_FILE).write_text("".join(json.dumps(m) + "\n" for m in kept))
    else:
        (run_dir / CONFIG_FILE).write_text(config.model_dump_json(indent=2))
        (run_dir / METRICS_FILE).write_text("")
        trainer = trainer or make_trainer(config)
        state = trainer.init_state()
        done_chunks = 0
    chunks = math.ceil(trainer.num_updates / trainer.updates_per_chunk)
    total = chunks * trainer.steps_per_chunk
    stopped = False
    chunk = done_chunks
    while chunk < chunks:
        t0 = time.perf_counter()
        state, metrics = trainer.run_chunk(state)
        wall = time.perf_counter() - t0
        chunk += 1
        result = ChunkResult(
            chunk, chunks, trainer.env_steps(state), total, wall, trainer.steps_per_chunk / wall,
            metrics,
        )  # fmt: skip
        with open(run_dir / METRICS_FILE, "a") as f:
            f.write(json.dumps(result.record()) + "\n")
        stop = bool(callback(result)) if callback else False
        if stop or chunk == chunks or chunk % checkpoint_every == 0:
            save_checkpoint(run_dir, trainer, state, chunk)
        if stop:
            stopped = True
            break
    plot_learning_curve(run_dir)
    return {
        "run_dir": str(run_dir), "chunks_done": chunk, "chunks": chunks,
        "env_steps": trainer.env_steps(state), "stopped": stopped,
        "final": read_metrics(run_dir)[-1] if chunk else {},
    }  # fmt: skip


def plot_learning_curve(run_dir: Path) -> Path | None:
    """learning_curve.png: mean episode return and success rate against env steps."""
    rows = read_metrics(run_dir)
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["env_steps"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    a1.plot(steps, [r.get("mean_return", math.nan) for r in rows], marker=".")
    a1.set_xlabel("env steps")
    a1.set_ylabel("mean episode return")
    a1.grid(alpha=0.3)
    a2.plot(steps, [r.get("success_rate", math.nan) for r in rows], marker=".", color="tab:green")
    a2.set_xlabel("env steps")
    a2.set_ylabel("success rate (training episodes)")
    a2.set_ylim(-0.02, 1.02)
    a2.grid(alpha=0.3)
    cfg_path = Path(run_dir) / CONFIG_FILE
    if cfg_path.exists():
        cfg = TrainConfig.model_validate_json(cfg_path.read_text())
        fig.suptitle(
            f"{cfg.trainer_kind}, {cfg.network.kind}, grid {cfg.env.grid_size}", fontsize=10
        )
    fig.tight_layout()
    path = Path(run_dir) / CURVE_FILE
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
