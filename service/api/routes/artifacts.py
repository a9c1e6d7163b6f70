"""A job's files (run folder, eval pictures, sweep outputs) and its per-chunk metrics history."""

from __future__ import annotations

import json
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse

from service.api.deps import SettingsDep, StoreDep, get_job, require_token

router = APIRouter(prefix="/jobs", tags=["artifacts"], dependencies=[Depends(require_token)])


@router.get("/{job_id}/metrics")
def job_metrics(job_id: str, store: StoreDep, settings: SettingsDep) -> dict:
    """One row per training chunk (the job's metrics.jsonl)."""
    job = get_job(store, job_id)
    path = settings.artifacts_dir / job.id / "metrics.jsonl"
    rows = (
        [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    )
    return {"job_id": job.id, "metrics": rows}


def _artifact_files(root: Path) -> list[dict]:
    if not root.exists():
        return []
    out = []
    for p in sorted(root.rglob("*")):
        partial = p.name.endswith(".tmp") or any(
            part in ("checkpoint.new", "checkpoint.old") for part in p.relative_to(root).parts
        )  # a checkpoint being written or swapped
        if p.is_file() and not partial:
            out.append({"name": p.relative_to(root).as_posix(), "bytes": p.stat().st_size})
    return out


@router.get("/{job_id}/artifacts")
def list_artifacts(job_id: str, store: StoreDep, settings: SettingsDep) -> dict:
    """The job's files with their sizes."""
    job = get_job(store, job_id)
    return {"job_id": job.id, "artifacts": _artifact_files(settings.artifacts_dir / job.id)}


@router.get("/{job_id}/artifacts/{name:path}")
def get_artifact(job_id: str, name: str, store: StoreDep, settings: SettingsDep):
    """One file of the job (names never leave the job's folder)."""
    if "\x00" in name:
        raise HTTPException(400, "artifact name holds a NUL byte; names are file paths inside the job's folder")
    job = get_job(store, job_id)
    root = (settings.artifacts_dir / job.id).resolve()
    target = (root / name).resolve()
    if not target.is_relative_to(root):
        raise HTTPException(400, f"artifact name {name!r} leaves the job's folder")
    if not target.is_file():
        raise HTTPException(404, f"job {job_id} has no artifact {name!r}")
    return FileResponse(target)
