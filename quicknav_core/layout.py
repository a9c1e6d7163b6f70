"""The run folder's layout: every file name of a run, an evaluation and a sweep, and what a
checkpoint's ``meta.json`` holds, in one place that every reader and writer uses (the trainer, the
evaluation, the export, the CLI, the service's artifact stores and routes).

    run folder (a train job's artifacts)          RUN
      config.json  metrics.jsonl  learning_curve.png  policy.onnx  policy.json  error.txt
      checkpoint/  state.msgpack  meta.json  [replay.msgpack]      CHECKPOINT (meta: CheckpointMeta)
      eval/        what ``quicknav eval RUN`` writes                EVAL
    evaluation folder (an eval job's artifacts)   EVAL
      eval.json  replay.json  trajectories.png  difficulty.png  robustness.png  episodes.gif
    sweep folder (a sweep job's artifacts)        SWEEP
      sweep_config.json  trials.json  trials.csv  best_params.json  best_config.json  summary.json

``RunFolder(path)`` gives a run folder's paths and finds its last complete checkpoint (``checkpoint/``,
or ``checkpoint.old/`` left by a crash in the middle of a swap; one whose files match the sizes and
SHA-256 its meta data records). Pure Python: no JAX, so the service and the SDK side read it freely.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class RunLayout:
    """File names of a run folder."""

    config: str = "config.json"  # the exact TrainConfig
    metrics: str = "metrics.jsonl"  # one JSON line per chunk
    curve: str = "learning_curve.png"
    checkpoint: str = "checkpoint"  # folder: CHECKPOINT's files
    policy: str = "policy.onnx"  # the exported policy (quicknav_core.export)
    manifest: str = "policy.json"  # what the exported policy's inputs and outputs mean
    eval_dir: str = "eval"  # ``quicknav eval RUN`` writes RUN/eval/
    error: str = "error.txt"  # a failed job's traceback
    tensorboard_prefix: str = "events.out.tfevents"  # TensorBoard's event files


@dataclass(frozen=True)
class CheckpointLayout:
    """File names inside a checkpoint folder; a new checkpoint is written into ``<name>.new/``
    and swapped in by renames (the previous one stays in ``<name>.old/`` until it is)."""

    state: str = "state.msgpack"  # flax msgpack, no pickle
    meta: str = "meta.json"  # CheckpointMeta
    replay: str = "replay.msgpack"  # SAC/TD3: the replay buffer, written at most every replay_every_s
    new_suffix: str = ".new"
    old_suffix: str = ".old"


@dataclass(frozen=True)
class EvalLayout:
    """File names of an evaluation's folder."""

    result: str = "eval.json"
    replay: str = "replay.json"  # the browser replay's episodes
    trajectories: str = "trajectories.png"
    difficulty: str = "difficulty.png"
    robustness: str = "robustness.png"
    gif: str = "episodes.gif"


@dataclass(frozen=True)
class SweepLayout:
    """File names of a sweep's folder."""

    config: str = "sweep_config.json"
    trials: str = "trials.json"
    trials_csv: str = "trials.csv"
    best_params: str = "best_params.json"
    best_config: str = "best_config.json"
    summary: str = "summary.json"
    study: str = "study.db"  # SQLite storage of a study kept in the folder


RUN = RunLayout()
CHECKPOINT = CheckpointLayout()
EVAL = EvalLayout()
SWEEP = SweepLayout()
FORMAT = "flax-msgpack-v1"


@dataclass(frozen=True)
class CheckpointMeta:
    """A checkpoint's ``meta.json``: where the run was and the checksums of its files."""

    chunk: int = 0  # chunks done (0: a meta data file written by hand, before chunks were counted)
    env_steps: int = 0
    trainer: str = ""
    format: str = FORMAT
    state_bytes: int | None = None
    state_sha256: str | None = None  # None: written before checksums were
    replay: dict[str, Any] | None = None  # {"env_steps", "bytes", "sha256"} of replay.msgpack

    @classmethod
    def from_json(cls, text: str | bytes) -> CheckpointMeta:
        data = json.loads(text)
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})

    def to_json(self) -> str:
        return json.dumps({k: v for k, v in asdict(self).items() if v is not None})


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class RunFolder:
    """A run folder on disk: the paths of its files and its last complete checkpoint."""

    def __init__(self, path: Path | str):
        self.path = Path(path)

    def __truediv__(self, name: str) -> Path:
        return self.path / name

    @property
    def config(self) -> Path:
        return self.path / RUN.config

    @property
    def metrics(self) -> Path:
        return self.path / RUN.metrics

    @property
    def curve(self) -> Path:
        return self.path / RUN.curve

    @property
    def manifest(self) -> Path:
        return self.path / RUN.manifest

    @property
    def policy(self) -> Path:
        return self.path / RUN.policy

    @property
    def eval_result(self) -> Path:
        """``quicknav eval RUN``'s eval.json."""
        return self.path / RUN.eval_dir / EVAL.result

    @property
    def checkpoint_folder(self) -> Path:
        return self.path / RUN.checkpoint

    @property
    def checkpoint_new(self) -> Path:
        return self.path / (RUN.checkpoint + CHECKPOINT.new_suffix)

    @property
    def checkpoint_old(self) -> Path:
        return self.path / (RUN.checkpoint + CHECKPOINT.old_suffix)

    def checkpoint(self) -> Path | None:
        """The last complete checkpoint folder, or None if there is none."""
        for folder in (self.checkpoint_folder, self.checkpoint_old):
            if complete(folder):
                return folder
        return None

    def read_metrics(self) -> list[dict[str, Any]]:
        """metrics.jsonl's rows, one per chunk ([] when there is none)."""
        if not self.metrics.exists():
            return []
        return [json.loads(line) for line in self.metrics.read_text().splitlines() if line.strip()]

    def meta(self) -> CheckpointMeta | None:
        """The meta data of the last complete checkpoint (None without one)."""
        folder = self.checkpoint()
        return read_meta(folder) if folder is not None else None

    @staticmethod
    def of(path: Path | str) -> RunFolder:
        """The run folder of ``path``: the folder itself, or the run a checkpoint folder is in."""
        path = Path(path)
        return RunFolder(path.parent if path.name == RUN.checkpoint else path)


def read_meta(checkpoint: Path) -> CheckpointMeta:
    return CheckpointMeta.from_json((checkpoint / CHECKPOINT.meta).read_text())


def _matches(data: bytes, size: int | None, sha256: str | None) -> bool:
    return len(data) == size and digest(data) == sha256


def complete(folder: Path) -> bool:
    """Whether a checkpoint folder holds a state (and replay buffer) that match its meta data."""
    try:
        meta = read_meta(folder)
        data = (folder / CHECKPOINT.state).read_bytes()
        if meta.replay is not None and not _matches((folder / CHECKPOINT.replay).read_bytes(),
                                                    meta.replay["bytes"], meta.replay["sha256"]):  # fmt: skip
            return False
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if meta.state_sha256 is None:  # written before checksums were: as good as its files
        return True
    return _matches(data, meta.state_bytes, meta.state_sha256)
