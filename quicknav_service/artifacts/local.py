"""Artifacts in a local folder: ``<root>/<job id>/`` is the job's run folder, written in place."""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path

from quicknav_core.layout import RunFolder
from quicknav_service.artifacts.base import PARTIAL_DIRS, ArtifactInfo, ArtifactStore


class LocalArtifacts(ArtifactStore):
    remote = False

    def __init__(self, root: Path):
        self.root = Path(root)
        self.url = str(self.root)

    def work_dir(self, job_id: str) -> Path:
        return self.root / job_id

    def restore(self, job_id: str) -> Path:
        return self.work_dir(job_id)

    def save(self, job_id: str, checkpoint_only: bool = False) -> None:
        """Nothing to do: the job wrote its files in place (checkpoints swapped in atomically)."""

    def save_file(self, job_id: str, path: Path, name: str) -> None:
        if path.resolve() != (self.work_dir(job_id) / name).resolve():
            shutil.copyfile(path, self.work_dir(job_id) / name)

    def release(self, job_id: str) -> None:
        """Nothing to drop: the folder is the store."""

    def run_copy(self, job_id: str) -> Path | None:
        return self.work_dir(job_id) if self.has_checkpoint(job_id) else None

    def has_checkpoint(self, job_id: str) -> bool:
        return RunFolder(self.work_dir(job_id)).checkpoint() is not None

    def list(self, job_id: str) -> list[ArtifactInfo]:
        root = self.work_dir(job_id)
        if not root.exists():
            return []
        out = []
        for p in sorted(root.rglob("*")):
            rel = p.relative_to(root)
            partial = p.name.endswith(".tmp") or any(part in PARTIAL_DIRS for part in rel.parts)
            if p.is_file() and not partial:
                out.append(ArtifactInfo(rel.as_posix(), p.stat().st_size))
        return out

    def _file(self, job_id: str, name: str) -> Path | None:
        root = self.work_dir(job_id).resolve()
        target = (root / name).resolve()
        return target if target.is_relative_to(root) and target.is_file() else None

    def read_bytes(self, job_id: str, name: str) -> bytes | None:
        path = self._file(job_id, name)
        return path.read_bytes() if path is not None else None

    def download(self, job_id: str, name: str) -> Path | None:
        return self._file(job_id, name)

    def delete(self, job_id: str) -> None:
        shutil.rmtree(self.work_dir(job_id), ignore_errors=True)

    def check(self) -> None:
        """The data folder's own check (free space, writes) is /readyz's disk check."""

    def put_bytes(self, folder: str, name: str, data: bytes) -> None:
        path = self.work_dir(folder) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex[:8]}.tmp")
        tmp.write_bytes(data)
        tmp.replace(path)

    def folders(self, parent: str) -> list[str]:
        root = self.work_dir(parent)
        return sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []

    def local_folder(self, folder: str) -> Path | None:
        path = self.work_dir(folder)
        return path if path.is_dir() and any(path.iterdir()) else None
