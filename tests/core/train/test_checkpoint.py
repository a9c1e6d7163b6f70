"""Checkpoints are written then swapped in: a failed write, a torn swap or a damaged state file
never gets loaded. No JAX here: save_checkpoint only needs the trainer's bytes and step count."""

import errno
import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from quicknav_core.train import run as run_mod
from quicknav_core.train.run import (
    CHECKPOINT_DIR,
    META_FILE,
    STATE_FILE,
    checkpoint_dir,
    read_meta,
    save_checkpoint,
)


class FakeTrainer:
    config = SimpleNamespace(trainer_kind="fake")

    def to_bytes(self, state, with_replay: bool = True) -> bytes:
        return state

    def has_replay(self, state) -> bool:
        return False

    def env_steps(self, state) -> int:
        return len(state)


def test_a_complete_save_replaces_the_previous_checkpoint(tmp_path: Path):
    save_checkpoint(tmp_path, FakeTrainer(), b"a" * 100, chunk=1)
    save_checkpoint(tmp_path, FakeTrainer(), b"b" * 200, chunk=2)
    assert checkpoint_dir(tmp_path) == tmp_path / CHECKPOINT_DIR
    assert read_meta(tmp_path)["chunk"] == 2
    assert (tmp_path / CHECKPOINT_DIR / STATE_FILE).read_bytes() == b"b" * 200
    assert sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT_DIR]


def test_disk_full_in_the_middle_of_a_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    save_checkpoint(tmp_path, FakeTrainer(), b"a" * 100, chunk=1)
    real_write = run_mod._write_synced

    def write_then_fail(path, data):  # the state gets half written, then the disk is full
        real_write(path, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_mod, "_write_synced", write_then_fail)
    with pytest.raises(OSError) as err:
        save_checkpoint(tmp_path, FakeTrainer(), b"b" * 200, chunk=2)
    assert err.value.errno == errno.ENOSPC
    # the half-written one is gone (it frees its space), the previous one is intact and chosen
    assert not (tmp_path / f"{CHECKPOINT_DIR}.new").exists()
    assert checkpoint_dir(tmp_path) == tmp_path / CHECKPOINT_DIR
    assert read_meta(tmp_path)["chunk"] == 1
    assert (tmp_path / CHECKPOINT_DIR / STATE_FILE).read_bytes() == b"a" * 100


def test_a_crash_between_the_two_renames_loads_the_previous_checkpoint(tmp_path: Path):
    save_checkpoint(tmp_path, FakeTrainer(), b"a" * 100, chunk=1)
    # the state the swap leaves after its first rename: checkpoint.old and checkpoint.new
    (tmp_path / CHECKPOINT_DIR).rename(tmp_path / f"{CHECKPOINT_DIR}.old")
    assert checkpoint_dir(tmp_path) == tmp_path / f"{CHECKPOINT_DIR}.old"
    assert read_meta(tmp_path)["chunk"] == 1
    # and the next save cleans it up
    save_checkpoint(tmp_path, FakeTrainer(), b"c" * 10, chunk=3)
    assert sorted(p.name for p in tmp_path.iterdir()) == [CHECKPOINT_DIR]


@pytest.mark.parametrize("damage", ["truncated", "flipped", "meta-missing"])
def test_a_damaged_checkpoint_is_never_loaded(tmp_path: Path, damage: str):
    save_checkpoint(tmp_path, FakeTrainer(), b"a" * 100, chunk=1)
    save_checkpoint(tmp_path, FakeTrainer(), b"b" * 200, chunk=2)
    (tmp_path / CHECKPOINT_DIR).rename(tmp_path / "keep")
    save_checkpoint(tmp_path, FakeTrainer(), b"a" * 100, chunk=1)
    (tmp_path / CHECKPOINT_DIR).rename(tmp_path / f"{CHECKPOINT_DIR}.old")
    (tmp_path / "keep").rename(tmp_path / CHECKPOINT_DIR)
    state = tmp_path / CHECKPOINT_DIR / STATE_FILE
    if damage == "truncated":
        state.write_bytes(state.read_bytes()[:150])
    elif damage == "flipped":
        state.write_bytes(b"x" + state.read_bytes()[1:])
    else:
        (tmp_path / CHECKPOINT_DIR / META_FILE).unlink()
    # the damaged newer one is passed over for the intact older one ...
    assert checkpoint_dir(tmp_path) == tmp_path / f"{CHECKPOINT_DIR}.old"
    assert read_meta(tmp_path)["chunk"] == 1
    # ... and with no intact one at all, there is no checkpoint rather than a wrong one
    (tmp_path / f"{CHECKPOINT_DIR}.old" / STATE_FILE).write_bytes(b"")
    assert checkpoint_dir(tmp_path) is None
    with pytest.raises(FileNotFoundError, match="no complete checkpoint"):
        read_meta(tmp_path)


def test_meta_records_size_and_checksum(tmp_path: Path):
    save_checkpoint(tmp_path, FakeTrainer(), b"xyz", chunk=4)
    meta = json.loads((tmp_path / CHECKPOINT_DIR / META_FILE).read_text())
    assert meta["state_bytes"] == 3 and len(meta["state_sha256"]) == 64
    assert meta["trainer"] == "fake" and meta["env_steps"] == 3


def test_replay_buffer__written_at_most_every_replay_every_s_and_restored(tmp_path, monkeypatch):
    """SAC with a replay buffer: with replay_every_s large, checkpoints after the first carry the
    buffer written then (hard-linked, not written again) and say at which env step; the last
    checkpoint of the run writes it fresh; a resumed state holds the buffer the checkpoint has."""
    import json

    import numpy as np

    from quicknav_core.config import resolve_train
    from quicknav_core.train import run as run_mod
    from quicknav_core.train.run import REPLAY_FILE, load_run, train_run

    cfg = resolve_train({"preset": "paper-sac", "overrides": {
        "env.grid_size": 8, "env.train_rooms": 8, "env.test_rooms": 8, "num_envs": 4,
        "algorithm.buffer_size": 40_000, "algorithm.batch_size": 16, "algorithm.fill_buffer": 16,
        "total_steps": 64, "chunk_steps": 16}})  # fmt: skip
    written = []
    real = run_mod._write_synced
    monkeypatch.setattr(run_mod, "_write_synced",
                        lambda path, data: (written.append(path.name), real(path, data))[1])  # fmt: skip
    metas = []
    real_save = run_mod.save_checkpoint

    def save(*args, **kwargs):
        out = real_save(*args, **kwargs)
        metas.append(json.loads((out / "meta.json").read_text()))
        return out

    monkeypatch.setattr(run_mod, "save_checkpoint", save)
    train_run(cfg, tmp_path / "run", replay_every_s=3600)
    assert [m["env_steps"] for m in metas] == [16, 32, 48, 64]
    assert written.count(REPLAY_FILE) == 2  # the first checkpoint and the last
    assert [m["replay"]["env_steps"] for m in metas] == [16, 16, 16, 64]
    assert all(m["state_bytes"] < m["replay"]["bytes"] / 3 for m in metas)  # networks apart
    _, trainer, state, meta = load_run(tmp_path / "run")
    assert meta["replay"]["env_steps"] == 64
    buf = state.replay_buffer
    assert int(buf.index) == 64 and np.abs(np.asarray(buf.data.obs[:64])).sum() > 0
