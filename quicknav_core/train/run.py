"""Run folders: training in chunks with progress callbacks, checkpoints, resume, learning curves.

A run folder (its names: ``quicknav_core.layout``) holds
  config.json          the exact TrainConfig
  metrics.jsonl        one JSON line per chunk (env steps, wall time, steps/s, losses, episode stats)
  checkpoint/          state.msgpack (flax msgpack, no pickle) and meta.json
  learning_curve.png   return and success rate against env steps (drawn by ``train.pictures``)
The same ``train_run`` serves the CLI (a progress bar) and the service worker (progress events,
chunks bounded in time, and cancellation between units: ``interrupt`` is asked after each one).

A checkpoint is written whole into ``checkpoint.new/`` and then swapped in by renames, and its
meta data records the state's size and SHA-256: a checkpoint is either the previous one or the new
one, never a mix, and a damaged one is refused instead of loaded.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from quicknav_core.config import TrainConfig
from quicknav_core.layout import CHECKPOINT, FORMAT, RUN, CheckpointMeta, RunFolder, digest
from quicknav_core.runtime import Runtime

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.train.trainers import Policy

# the layout's names, as this module's readers knew them
CONFIG_FILE, METRICS_FILE, CHECKPOINT_DIR, CURVE_FILE = RUN.config, RUN.metrics, RUN.checkpoint, RUN.curve
STATE_FILE, META_FILE, REPLAY_FILE = CHECKPOINT.state, CHECKPOINT.meta, CHECKPOINT.replay


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


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def save_checkpoint(run_dir: Path, trainer, state, chunk: int, with_replay: bool = True) -> Path:
    """Write the trainer state and its meta data; the previous checkpoint stays until the new one
    is complete on disk (a full disk fails the write and keeps the previous checkpoint).

    A replay buffer (SAC, TD3: hundreds of MB) is its own file: written with ``with_replay``, else
    the previous checkpoint's is kept (hard-linked, no bytes written) and the meta data says at
    which env step it was saved."""
    run = RunFolder(run_dir)
    ckpt, new, old = run.checkpoint_folder, run.checkpoint_new, run.checkpoint_old
    shutil.rmtree(new, ignore_errors=True)
    new.mkdir(parents=True)
    try:
        replay = trainer.has_replay(state)
        data = trainer.to_bytes(state, with_replay=not replay)
        _write_synced(new / CHECKPOINT.state, data)
        meta = CheckpointMeta(chunk=chunk, env_steps=trainer.env_steps(state),
                              trainer=trainer.config.trainer_kind, format=FORMAT,
                              state_bytes=len(data), state_sha256=digest(data))  # fmt: skip
        if replay:
            previous = _replay_meta(ckpt)
            if with_replay or previous is None:
                buffer = trainer.replay_to_bytes(state)
                _write_synced(new / CHECKPOINT.replay, buffer)
                record = {"env_steps": meta.env_steps, "bytes": len(buffer), "sha256": digest(buffer)}
            else:
                os.link(ckpt / CHECKPOINT.replay, new / CHECKPOINT.replay)
                record = previous
            meta = CheckpointMeta(**{**meta.__dict__, "replay": record})
        _write_synced(new / CHECKPOINT.meta, meta.to_json().encode())
        _fsync_dir(new)
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)  # frees what the failed write took
        raise
    shutil.rmtree(old, ignore_errors=True)
    if ckpt.exists():
        os.rename(ckpt, old)
    os.rename(new, ckpt)
    _fsync_dir(run.path)
    shutil.rmtree(old, ignore_errors=True)
    return ckpt


def _replay_meta(folder: Path) -> dict[str, Any] | None:
    """The replay entry of a complete checkpoint's meta data (None if it has none)."""
    try:
        meta = CheckpointMeta.from_json((folder / CHECKPOINT.meta).read_text())
    except (OSError, ValueError, TypeError):
        return None
    return meta.replay if (folder / CHECKPOINT.replay).exists() else None


def checkpoint_dir(run_dir: Path) -> Path | None:
    """The run's last complete checkpoint (``layout.RunFolder.checkpoint``); None if there is none."""
    return RunFolder(run_dir).checkpoint()


def read_config(run_dir: Path) -> TrainConfig:
    """The TrainConfig of a run folder; FileNotFoundError if it is not one."""
    cfg_path = RunFolder(run_dir).config
    if not cfg_path.exists():
        raise FileNotFoundError(f"{run_dir} is not a run folder: no {RUN.config}")
    return TrainConfig.model_validate_json(cfg_path.read_text())


def read_meta(run_dir: Path) -> dict[str, Any]:
    """The meta data of a run folder's last complete checkpoint (chunk, env steps, trainer)."""
    meta = RunFolder(run_dir).meta()
    if meta is None:
        raise FileNotFoundError(f"{run_dir} has no complete checkpoint")
    return json.loads(meta.to_json())


def _last_checkpoint(run_dir: Path) -> tuple[TrainConfig, Path, dict[str, Any]]:
    """(config, checkpoint folder, meta) of a run folder's last complete checkpoint."""
    config = read_config(run_dir)
    ckpt = checkpoint_dir(run_dir)
    if ckpt is None:
        raise FileNotFoundError(f"{run_dir} has no checkpoint yet, or none that is complete"
                                f" ({RUN.checkpoint}/{CHECKPOINT.state})")  # fmt: skip
    return config, ckpt, read_meta(run_dir)


def load_run(run_dir: Path, trainer=None, runtime: Runtime | None = None):
    """(config, trainer, state, meta) of a run folder's last checkpoint (``trainer``: a warm one;
    else one made in ``runtime``)."""
    from quicknav_core.train.trainers import make_trainer

    config, ckpt, meta = _last_checkpoint(Path(run_dir))
    trainer = (trainer if trainer is not None and trainer.config == config
               else make_trainer(config, runtime))  # fmt: skip
    state = trainer.from_bytes((ckpt / STATE_FILE).read_bytes())
    if "replay" in meta:
        state = trainer.with_replay_bytes(state, (ckpt / REPLAY_FILE).read_bytes())
    return config, trainer, state, meta


def load_policy(run_dir: Path) -> tuple[TrainConfig, Policy, dict[str, Any]]:
    """(config, policy, meta) of a run folder's last checkpoint, without building its trainer:
    the network and its parameters only (``trainers.policy_from_bytes``), what evaluation, export
    and the Policy stream need. ``load_run`` is for what continues training."""
    from quicknav_core.train.trainers import policy_from_bytes

    config, ckpt, meta = _last_checkpoint(Path(run_dir))
    return config, policy_from_bytes(config, (ckpt / STATE_FILE).read_bytes()), meta


def read_metrics(run_dir: Path) -> list[dict[str, Any]]:
    """metrics.jsonl's rows (``layout.RunFolder.read_metrics``)."""
    return RunFolder(run_dir).read_metrics()


def train_run(
    config: TrainConfig,
    run_dir: Path,
    callback: ProgressCallback | None = None,
    resume: bool = False,
    checkpoint_every: int = 1,
    trainer=None,
    max_chunk_s: float | None = None,
    interrupt: Callable[[], bool] | None = None,
    replay_every_s: float = 0.0,
    on_checkpoint: Callable[[int], None] | None = None,
    runtime: Runtime | None = None,
) -> dict[str, Any]:
    """Train ``config`` into ``run_dir`` (or continue it with ``resume``). Returns a summary.

    A chunk is ``updates_per_chunk`` updates, or fewer if ``max_chunk_s`` seconds have passed or
    ``interrupt()`` (asked after every unit) says stop. After every chunk: metrics are appended, a
    checkpoint is written every ``checkpoint_every`` chunks (and always at the end or on a stop),
    and ``callback`` may return True to stop. Grouping units into chunks never changes the result.

    ``replay_every_s``: a replay buffer (SAC, TD3) is written with a checkpoint only when this many
    seconds have passed since it last was (0: every time, and a resumed run is exactly the
    uninterrupted one); between, checkpoints carry the last one written, so a run resumed from one
    refills from a buffer up to ``replay_every_s`` old. The last checkpoint of a run has it fresh.

    ``on_checkpoint(chunk)`` is called after each checkpoint is complete on disk (the service
    publishes it to its artifact store there); what it raises ends the run.
    """
    from quicknav_core.train.trainers import make_trainer

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if resume:
        config, trainer, state, meta = load_run(run_dir, trainer, runtime)
        chunk = int(meta["chunk"])
        # drop metric lines written after the checkpoint (a crash between the two)
        kept = [m for m in read_metrics(run_dir) if m["chunk"] <= chunk]
        (run_dir / METRICS_FILE).write_text("".join(json.dumps(m) + "\n" for m in kept))
    else:
        (run_dir / CONFIG_FILE).write_text(config.model_dump_json(indent=2))
        (run_dir / METRICS_FILE).write_text("")
        # an attempt that stopped before its first checkpoint starts again from nothing: its
        # TensorBoard curve goes with its metrics
        for stale in run_dir.glob(f"{RUN.tensorboard_prefix}*"):
            stale.unlink(missing_ok=True)
        trainer = trainer or make_trainer(config, runtime)
        state = trainer.init_state()
        chunk = 0
    chunks = math.ceil(trainer.num_updates / trainer.updates_per_chunk)  # without time bounds
    total = trainer.total_env_steps
    done = trainer.updates_done(state)
    replay_saved = time.monotonic()  # a resumed run has its buffer as the checkpoint has it
    with TensorBoardLog(run_dir) as board:
        stopped = False
        while done < trainer.num_updates:
            t0 = time.perf_counter()
            steps0 = trainer.env_steps(state)
            target = min(trainer.num_updates, done + trainer.updates_per_chunk)
            units, interrupted = [], False
            while done < target:
                state, metrics = trainer.run_unit(state)
                units.append(metrics)
                done += trainer.updates_per_unit
                if interrupt is not None and interrupt():
                    interrupted = True
                    break
                if max_chunk_s is not None and time.perf_counter() - t0 >= max_chunk_s:
                    break
            state, metrics = trainer.finish_chunk(state, units)
            wall = time.perf_counter() - t0
            chunk += 1
            steps = trainer.env_steps(state)
            result = ChunkResult(chunk, max(chunks, chunk), steps, total, wall,
                                 (steps - steps0) / max(wall, 1e-9), metrics)  # fmt: skip
            with open(run_dir / METRICS_FILE, "a") as f:
                f.write(json.dumps(result.record()) + "\n")
            board.add(result.record())
            asked = bool(callback(result)) if callback else False
            stop = interrupted or asked
            last = stop or done >= trainer.num_updates
            if last or chunk % checkpoint_every == 0:
                due = last or time.monotonic() - replay_saved >= replay_every_s
                save_checkpoint(run_dir, trainer, state, chunk, with_replay=due)
                if due:
                    replay_saved = time.monotonic()
                if on_checkpoint is not None:
                    on_checkpoint(chunk)
            if stop:
                stopped = True
                break
    from quicknav_core.train.pictures import draw_learning_curve_safely

    if resume and not stopped:  # an earlier attempt's curve, whatever it left, made whole
        TensorBoardLog.rebuild(run_dir)
    warnings = draw_learning_curve_safely(run_dir)  # a picture never costs a run its numbers
    return {
        "run_dir": str(run_dir), "chunks_done": chunk, "chunks": max(chunks, chunk),
        "env_steps": trainer.env_steps(state), "total_steps": total, "stopped": stopped,
        "final": read_metrics(run_dir)[-1] if chunk else {}, "warnings": warnings,
    }  # fmt: skip


class TensorBoardLog:
    """TensorBoard event files in the run folder (tensorboardX), one scalar per chunk metric
    against env steps, flushed every chunk: `tensorboard --logdir <runs or data/artifacts>` shows
    every run, live.

    A run resumed after its worker died writes a new events file beside whatever the earlier
    attempt left (perhaps nothing: a worker elsewhere); when the run ends, ``rebuild`` replaces
    them with one file written from metrics.jsonl, so the curve a user opens has every chunk
    exactly once, whatever attempts made them."""

    def __init__(self, run_dir: Path):
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(logdir=str(run_dir), flush_secs=3600)

    @staticmethod
    def rebuild(run_dir: Path) -> None:
        """One events file with every chunk of metrics.jsonl, in place of the attempts' files."""
        run = RunFolder(run_dir)
        old = sorted(run.path.glob(f"{RUN.tensorboard_prefix}*"))  # before the new file exists
        with TensorBoardLog(run.path) as board:
            for record in run.read_metrics():
                board.add(record, flush=False)
        for path in old:
            path.unlink(missing_ok=True)

    def add(self, record: dict[str, Any], flush: bool = True) -> None:
        step = int(record["env_steps"])
        for name, value in record.items():
            if name in ("chunk", "env_steps", "chunks", "total_steps"):
                continue
            if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
                self.writer.add_scalar(f"train/{name}", float(value), step)
        if flush:
            self.writer.flush()

    def __enter__(self) -> TensorBoardLog:
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()
