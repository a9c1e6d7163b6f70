"""A job's files (run folder, eval pictures, sweep outputs) and its per-chunk metrics history."""

from __future__ import annotations

import json
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse

from quicknav_service.api.deps import JobId, JobsDep, SettingsDep, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
from quicknav_service.schemas import ArtifactPublic, ArtifactsPublic, JobMetricsPublic

router = APIRouter(prefix="/jobs", tags=["artifacts"], dependencies=[Depends(require_token)],
                   responses=responses(*AUTH, *STORE, 404, 409, 422))  # fmt: skip

# The media type of a download, by suffix; anything else (checkpoints, ONNX, studies) is bytes.
MEDIA_TYPES = {".png": "image/png", ".gif": "image/gif", ".json": "application/json",
               ".jsonl": "application/x-ndjson", ".csv": "text/csv", ".txt": "text/plain"}  # fmt: skip
BINARY = "application/octet-stream"
DOWNLOAD_DOC = {
    "description": "the file's bytes, typed by its suffix (application/octet-stream otherwise)",
    "content": {t: {"schema": {"type": "string", "format": "binary"}}
                for t in (BINARY, *MEDIA_TYPES.values())},
}  # fmt: skip


@router.get("/{job_id}/metrics", response_model=JobMetricsPublic)
def job_metrics(job_id: JobId, jobs: JobsDep, settings: SettingsDep) -> JobMetricsPublic:
    """One row per training chunk (the job's metrics.jsonl)."""
    job = jobs.get(job_id)
    path = settings.artifacts_dir / job.id / "metrics.jsonl"
    rows = (
        [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    )
    return JobMetricsPublic(job_id=job.id, metrics=rows)


def _artifact_files(root: Path) -> list[ArtifactPublic]:
    if not root.exists():
        return []
    out = []
    for p in sorted(root.rglob("*")):
        partial = p.name.endswith(".tmp") or any(
            part in ("checkpoint.new", "checkpoint.old") for part in p.relative_to(root).parts
        )  # a checkpoint being written or swapped
        if p.is_file() and not partial:
            out.append(ArtifactPublic(name=p.relative_to(root).as_posix(), bytes=p.stat().st_size))
    return out


@router.get("/{job_id}/artifacts", response_model=ArtifactsPublic)
def list_artifacts(job_id: JobId, jobs: JobsDep, settings: SettingsDep) -> ArtifactsPublic:
    """The job's files with their sizes."""
    job = jobs.get(job_id)
    return ArtifactsPublic(job_id=job.id, artifacts=_artifact_files(settings.artifacts_dir / job.id))


@router.get("/{job_id}/artifacts/{name:path}", response_class=FileResponse,
            responses={200: DOWNLOAD_DOC, **responses(400)})  # fmt: skip
def get_artifact(job_id: JobId, name: str, jobs: JobsDep, settings: SettingsDep) -> FileResponse:
    """One file of the job (names never leave the job's folder)."""
    if "\x00" in name:
        raise HTTPException(400, "artifact name holds a NUL byte; names are file paths inside the job's folder")
    job = jobs.get(job_id)
    root = (settings.artifacts_dir / job.id).resolve()
    target = (root / name).resolve()
    if not target.is_relative_to(root):
        raise HTTPException(400, f"artifact name {name!r} leaves the job's folder")
    if not target.is_file():
        raise HTTPException(404, f"job {job_id} has no artifact {name!r}")
    return FileResponse(target, media_type=MEDIA_TYPES.get(target.suffix.lower(), BINARY))
