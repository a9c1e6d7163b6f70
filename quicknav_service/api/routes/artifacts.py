"""A job's files (run folder, eval pictures, sweep outputs) and its per-chunk metrics history."""

from __future__ import annotations

import json
from pathlib import PurePosixPath
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Path
from fastapi.responses import FileResponse, Response, StreamingResponse

from quicknav_core.layout import RUN
from quicknav_service.api.deps import JobId, JobsDep, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
from quicknav_service.artifacts import RemoteFile, bad_name
from quicknav_service.schemas import ArtifactPublic, ArtifactsPublic, JobMetricsPublic

router = APIRouter(prefix="/jobs", tags=["artifacts"], dependencies=[Depends(require_token)],
                   responses=responses(*AUTH, *STORE, 404, 409, 422))  # fmt: skip

# The media type of a download, by suffix; anything else (checkpoints, ONNX, studies) is bytes.
MEDIA_TYPES = {".png": "image/png", ".gif": "image/gif", ".json": "application/json",
               ".jsonl": "application/x-ndjson", ".csv": "text/csv", ".txt": "text/plain"}  # fmt: skip
BINARY = "application/octet-stream"
# a running job's files change under the same name (a sweep's trials.json, metrics.jsonl): a
# browser must ask again each time, not reuse its copy. Without this, FileResponse's Last-Modified
# let Chromium keep a sweep's trials.json of two running trials as fresh for seconds after both
# had finished (heuristic freshness), and the page drew the history of a sweep that had ended
# without its points
FRESH = {"Cache-Control": "no-cache"}
DOWNLOAD_DOC = {
    "description": "the file's bytes, typed by its suffix (application/octet-stream otherwise)",
    "content": {t: {"schema": {"type": "string", "format": "binary"}}
                for t in (BINARY, *MEDIA_TYPES.values())},
    "headers": {"Cache-Control": {"description": "no-cache: a running job's files change",
                                  "schema": {"type": "string"}}},
}  # fmt: skip


@router.get("/{job_id}/metrics", response_model=JobMetricsPublic)
def job_metrics(job_id: JobId, jobs: JobsDep) -> JobMetricsPublic:
    """One row per training chunk (the job's metrics.jsonl; on an object store, as of its last
    published checkpoint)."""
    job = jobs.get(job_id)
    data = jobs.artifacts.read_bytes(job.id, RUN.metrics) or b""
    rows = [json.loads(x) for x in data.decode().splitlines() if x.strip()]
    return JobMetricsPublic(job_id=job.id, metrics=rows)


@router.get("/{job_id}/artifacts", response_model=ArtifactsPublic)
def list_artifacts(job_id: JobId, jobs: JobsDep) -> ArtifactsPublic:
    """The job's files with their sizes."""
    job = jobs.get(job_id)
    return ArtifactsPublic(job_id=job.id, artifacts=[
        ArtifactPublic(name=a.name, bytes=a.bytes) for a in jobs.artifacts.list(job.id)])  # fmt: skip


# what the artifacts are called: file paths inside the job's folder, each part starting with a
# letter, digit or underscore (the document's pattern; the route refuses, with 400, only names
# that leave the folder, so a name outside the pattern is answered 404 or 400, never served)
ARTIFACT_NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(/[A-Za-z0-9_][A-Za-z0-9_.-]*)*$"
ArtifactName = Annotated[str, Path(description="a file path inside the job's folder, as GET"
                                               " /jobs/{job_id}/artifacts lists it",
                                   json_schema_extra={"pattern": ARTIFACT_NAME})]  # fmt: skip


@router.get("/{job_id}/artifacts/{name:path}", response_class=FileResponse,
            responses={200: DOWNLOAD_DOC, **responses(400)})  # fmt: skip
def get_artifact(job_id: JobId, name: ArtifactName, jobs: JobsDep) -> Response:
    """One file of the job (names never leave the job's folder); streamed from an object store."""
    if why := bad_name(name):
        raise HTTPException(400, why)
    job = jobs.get(job_id)
    found = jobs.artifacts.download(job.id, name)
    if found is None:
        raise HTTPException(404, f"job {job_id} has no artifact {name!r}")
    media_type = MEDIA_TYPES.get(PurePosixPath(name).suffix.lower(), BINARY)
    if isinstance(found, RemoteFile):
        return StreamingResponse(found.chunks, media_type=media_type,
                                 headers={"Content-Length": str(found.size), **FRESH})  # fmt: skip
    return FileResponse(found, media_type=media_type, headers=FRESH)
