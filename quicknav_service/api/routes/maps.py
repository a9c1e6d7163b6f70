"""Uploaded maps of buildings: upload, list, show (with a preview), download, delete.

A stored map is named in an env config as ``map:<id>`` (``env.maps.train``); train, eval and sweep
jobs and gRPC ``Start`` read it from the artifact store (``quicknav_service.maps``).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import (
    APIRouter,
    Depends,
    File,
    Form,
    HTTPException,
    Path,
    Request,
    Response,
    UploadFile,
)
from fastapi.responses import JSONResponse

from quicknav_service.api.deps import JobsDep, require_token
from quicknav_service.api.errors import AUTH, STORE, responses
from quicknav_service.jobs.models import JobStatus
from quicknav_service.maps import MapLibrary, MapUploadError, UploadedFile, limit_notes, maps_named
from quicknav_service.schemas import MapPublic, MapsPublic

router = APIRouter(prefix="/maps", tags=["maps"], dependencies=[Depends(require_token)],
                   responses=responses(*AUTH, *STORE))  # fmt: skip
MapId = Annotated[str, Path(min_length=8, max_length=16, pattern="^[0-9a-f]{8,16}$",
                            description="a map's id (16 hex digits, as POST /maps answers) or a"
                            " unique prefix of 8 or more")]  # fmt: skip
PAGE = 500
# the stored files a client may download, by name
FILES = {"map.yaml": "application/yaml", "map.pgm": "image/x-portable-graymap", "map.png": "image/png"}


def _library(jobs: JobsDep, request: Request) -> MapLibrary:
    return MapLibrary(jobs.artifacts, jobs.settings.max_map_pixels, request.app.state.map_decode_budget)


LibraryDep = Annotated[MapLibrary, Depends(_library)]


def _active_use(jobs: JobsDep) -> dict[str, list[str]]:
    """Map id -> the queued and running jobs whose config names it."""
    out: dict[str, list[str]] = {}
    for status in (JobStatus.queued, JobStatus.running):
        offset = 0
        while True:
            page, count = jobs.store.list(status=status, limit=PAGE, offset=offset)
            for job in page:
                for map_id in maps_named(job.config):
                    out.setdefault(map_id, []).append(job.id)
            offset += len(page)
            if not page or offset >= count:
                break
    return out


def _public(meta: dict, used: dict[str, list[str]], max_grid_size: int) -> MapPublic:
    notes = [*meta.get("notes", []), *limit_notes(meta["suggested_env"], max_grid_size)]
    return MapPublic(**{**meta, "notes": notes}, preview_url=f"/maps/{meta['id']}/preview.png",
                     used_by=sorted(set(used.get(meta["id"], []))))  # fmt: skip


@router.post("", status_code=201, response_model=MapPublic,
             responses={**responses(400, 401, 403, 413, 415, 422),
                        503: {**responses(503)[503], "description": "the job store or the artifact store"
                              " cannot be reached, or other uploads hold the memory for reading maps"
                              " (QUICKNAV_MAP_DECODE_MB); retry after Retry-After seconds"},
                        201: {"description": "stored (or already stored: the same files give the same id, renamed if a name is given)",
                              "headers": {"Location": {"description": "the map's URL", "required": True,
                                                       "schema": {"type": "string"}}}}})  # fmt: skip
def upload_map(
    library: LibraryDep,
    jobs: JobsDep,
    response: Response,
    files: Annotated[list[UploadFile], File(
        min_length=1, description="a ROS map_server .yaml with the .pgm/.png it names, or one .png/.pgm image")],
    name: Annotated[str | None, Form(max_length=200, description="a label (default: the image's name)")] = None,
    resolution: Annotated[float | None, Form(
        gt=0, le=100, description="metres per pixel: plain images only (a .yaml names its own)")] = None,
    negate: Annotated[bool | None, Form(description="plain images: white is occupied")] = None,
    occupied_thresh: Annotated[float | None, Form(gt=0, le=1, description="plain images: occupied above (0.65)")] = None,
    free_thresh: Annotated[float | None, Form(ge=0, lt=1, description="plain images: free below (0.196)")] = None,
) -> MapPublic:  # fmt: skip
    """Upload a map of a building. It is read as a job will read it: a file that cannot be used is
    refused with the reason, naming the field."""
    uploaded = [UploadedFile(f.filename or "upload", f.file.read()) for f in files]
    try:
        meta = library.add(uploaded, name=name, resolution=resolution, negate=negate,
                           occupied_thresh=occupied_thresh, free_thresh=free_thresh)  # fmt: skip
    except MapUploadError as e:
        if e.status == 422:
            raise HTTPException(422, [{"loc": ["body", e.field], "msg": e.message, "type": "map"}]) from None
        headers = {"Retry-After": str(e.retry_after_s)} if e.retry_after_s else None
        raise HTTPException(e.status, f"{e.field}: {e.message}", headers=headers) from None
    response.headers["Location"] = f"/maps/{meta['id']}"
    return _public(meta, {}, jobs.settings.max_grid_size)


@router.get("", response_model=MapsPublic)
def list_maps(library: LibraryDep, jobs: JobsDep) -> MapsPublic:
    """Every uploaded map, newest first, with the queued and running jobs that use it."""
    used = _active_use(jobs)
    data = [_public(m, used, jobs.settings.max_grid_size) for m in library.list()]
    return MapsPublic(data=data, count=len(data))


def _full_id(library: MapLibrary, map_id: str) -> str:
    """The id a prefix (8 or more hex digits, as the CLI prints them) stands for: 404 for none,
    409 naming the candidates for more than one."""
    if len(map_id) == 16:
        return map_id
    found = sorted(m["id"] for m in library.list() if m["id"].startswith(map_id))
    if not found:
        raise HTTPException(404, f"no map {map_id!r} (GET /maps lists them)")
    if len(found) > 1:
        raise HTTPException(409, f"map id prefix {map_id!r} names {len(found)} maps"
                            f" ({', '.join(found[:5])}); give more of the id")  # fmt: skip
    return found[0]


def _meta(library: MapLibrary, map_id: str) -> dict:
    meta = library.get(_full_id(library, map_id))
    if meta is None:
        raise HTTPException(404, f"no map {map_id!r} (GET /maps lists them)")
    return meta


@router.get("/{map_id}", response_model=MapPublic, responses=responses(404, 409, 422))
def get_map(map_id: MapId, library: LibraryDep, jobs: JobsDep) -> MapPublic:
    """One map: its size, resolution, free space, the env fields that hold it, and who uses it."""
    return _public(_meta(library, map_id), _active_use(jobs), jobs.settings.max_grid_size)


BINARY = {"schema": {"type": "string", "format": "binary"}}


@router.get("/{map_id}/preview.png", response_class=Response, responses={
    # octet-stream first: generated clients read it as bytes (they know no image types)
    200: {"content": {"application/octet-stream": BINARY, "image/png": BINARY},
          "description": "the map as a picture: free light, unknown grey, occupied dark"},
    **responses(404, 409, 422)})  # fmt: skip
def map_preview(map_id: MapId, library: LibraryDep) -> Response:
    """The map's picture, top row first (at most 1,024 pixels a side; preview_m_per_px says the
    scale)."""
    data = library.preview(_full_id(library, map_id))
    if data is None:
        raise HTTPException(404, f"no map {map_id!r} (GET /maps lists them)")
    return Response(data, media_type="image/png", headers={"Cache-Control": "max-age=86400, immutable"})


@router.get("/{map_id}/files/{name}", response_class=Response, responses={
    200: {"content": {"application/octet-stream": BINARY, **{t: BINARY for t in FILES.values()}},
          "description": "one stored map file"},
    **responses(404, 409, 422)})  # fmt: skip
def map_file(map_id: MapId, name: str, library: LibraryDep, jobs: JobsDep) -> Response:
    """One stored file of the map: ``map.yaml`` and the image it names (``map.pgm`` or ``map.png``),
    a map_server pair that `quicknav train` reads as it is."""
    map_id = _meta(library, map_id)["id"]
    data = jobs.artifacts.read_bytes(f"maps/{map_id}", name) if name in FILES else None
    if data is None:
        raise HTTPException(404, f"map {map_id} has no file {name!r}; it has map.yaml and the"
                            " image that map.yaml names")  # fmt: skip
    return Response(data, media_type=FILES[name])


@router.delete("/{map_id}", status_code=204, response_class=Response,
               responses=responses(403, 404, 409, 422))  # fmt: skip
def delete_map(map_id: MapId, library: LibraryDep, jobs: JobsDep) -> Response:
    """Delete a map no queued or running job uses (finished jobs keep their own results)."""
    map_id = _meta(library, map_id)["id"]
    busy = sorted(set(_active_use(jobs).get(map_id, [])))
    if busy:
        return JSONResponse({"detail": f"map {map_id} is used by queued or running job(s)"
                             f" {', '.join(busy)}; delete it once they have finished (or cancel"
                             " them)"}, status_code=409)  # fmt: skip
    library.delete(map_id)
    return Response(status_code=204)

