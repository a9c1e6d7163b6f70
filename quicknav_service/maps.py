"""Uploaded maps: building maps stored with the jobs' artifacts and named by id in env configs.

A map is uploaded as a ROS map_server pair (``.yaml`` + its ``.pgm``/``.png``) or as a plain
``.png``/``.pgm`` with its resolution. Either way it is stored as a map_server pair under the
artifact store's ``maps/<id>/`` (``map.yaml`` naming ``map.pgm`` or ``map.png``), with
``meta.json`` (what ``GET /maps/{id}`` answers) and ``preview.png``. The id is a digest of the two
map files, so the same map uploaded twice is one map, and a stored map never changes: a worker
that has fetched it once reads its own copy (``local_yaml``).

A config names a stored map as ``map:<id>`` in ``env.maps.train`` / ``env.maps.test``; every
service process's ``Runtime`` reads such names through ``local_yaml`` (``quicknav_service.runtime``),
so the env, its NumPy twin and the checks read it like a file.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import re
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from quicknav_core.env.maps import (
    IMAGE_SUFFIXES,
    MAP_ID_PREFIX,
    YAML_SUFFIXES,
    MapError,
    OccupancyMap,
    check_pixels,
    header_size,
    load_map,
    read_yaml_doc,
    shown,
)
from quicknav_service.artifacts import ArtifactStore

MAPS = "maps"  # the artifact store's folder of uploaded maps
MAP_REF = re.compile(r'"map:([0-9a-f]{16})"')  # a stored map named in a config, as JSON
ID_LENGTH = 16  # hex digits of the digest that names a map
SUGGESTED_CELL_M = 0.5  # the env's default cell (room_size 8 m / grid_size 16)


# memory one uploaded pixel takes while it is read as a job will (decoded image, thresholds,
# masks, the preview): 22 bytes measured for a 5000 x 5000 PNG (peak RSS growth, 2-core Intel VM)
DECODE_BYTES_PER_PIXEL = 24
DECODE_WAIT_S = 30.0  # an upload waits this long for memory held by others, then 503


class MapUploadError(Exception):
    """An upload that cannot be stored: ``field`` names the form field, ``status`` the HTTP code
    (``retry_after_s`` with 503: the server is busy, not the file wrong)."""

    def __init__(self, field: str, message: str, status: int = 422, retry_after_s: int | None = None):
        super().__init__(message)
        self.field = field
        self.message = message
        self.status = status
        self.retry_after_s = retry_after_s


class DecodeBudget:
    """The memory an API process gives to reading uploaded maps at once (QUICKNAV_MAP_DECODE_MB):
    an upload holds its image's share while it is decoded, and waits while others hold the rest.
    One upload larger than the whole budget may run alone."""

    def __init__(self, total_bytes: int, wait_s: float = DECODE_WAIT_S):
        self.total = total_bytes
        self.wait_s = wait_s
        self.held = 0
        self._cond = threading.Condition()

    @contextmanager
    def hold(self, nbytes: int, what: str):
        need = min(nbytes, self.total)
        with self._cond:
            if not self._cond.wait_for(lambda: self.held + need <= self.total, timeout=self.wait_s):
                raise MapUploadError(
                    "files", f"{what}: other uploads are being read and hold the memory this server"
                    f" gives to reading maps ({self.total / 2**20:,.0f} MB, QUICKNAV_MAP_DECODE_MB);"
                    " retry shortly", status=503, retry_after_s=5)  # fmt: skip
            self.held += need
        try:
            yield
        finally:
            with self._cond:
                self.held -= need
                self._cond.notify_all()


@dataclass(frozen=True)
class UploadedFile:
    filename: str
    data: bytes


def valid_id(map_id: str) -> bool:
    return len(map_id) == ID_LENGTH and all(c in "0123456789abcdef" for c in map_id)


def _suffix(name: str) -> str:
    return PurePosixPath(name).suffix.lower()


def _canonical(files: list[UploadedFile], resolution: float | None, negate: bool | None,
               occupied_thresh: float | None, free_thresh: float | None) -> tuple[bytes, str, bytes]:  # fmt: skip
    """The stored pair: (map.yaml's bytes, the image's suffix, the image's bytes)."""
    import yaml

    yamls = [f for f in files if _suffix(f.filename) in YAML_SUFFIXES]
    images = [f for f in files if _suffix(f.filename) in IMAGE_SUFFIXES]
    others = [f.filename for f in files if f not in yamls and f not in images]
    if others:
        raise MapUploadError("files", f"{others[0]!r} is neither a map_server .yaml nor a .pgm/.png"
                             " image; upload a .yaml with its image, or one image")  # fmt: skip
    if len(yamls) > 1 or len(images) != 1:
        raise MapUploadError("files", f"got {len(yamls)} .yaml and {len(images)} image file(s);"
                             " upload one map: a map_server .yaml with the one image it names, or"
                             " one .png/.pgm image with its resolution")  # fmt: skip
    image = images[0]
    if yamls:
        given = [n for n, v in (("resolution", resolution), ("negate", negate),
                                ("occupied_thresh", occupied_thresh), ("free_thresh", free_thresh))
                 if v is not None]  # fmt: skip
        if given:
            raise MapUploadError(given[0], f"{given[0]} is for a plain image; {yamls[0].filename}"
                                 " names its own (edit the .yaml instead)")  # fmt: skip
        try:
            doc = read_yaml_doc(yamls[0].data, yamls[0].filename)
        except MapError as e:
            raise MapUploadError("files", str(e)) from None
        if not isinstance(doc, dict) or "image" not in doc:
            raise MapUploadError("files", f"{yamls[0].filename}: a map_server YAML is a mapping"
                                 " with image, resolution and origin; 'image' is missing")  # fmt: skip
        if not isinstance(doc["image"], str):
            raise MapUploadError("files", f"{yamls[0].filename}: field 'image' must be the image's"
                                 f" file name; got {shown(doc['image'])}")  # fmt: skip
        named = PurePosixPath(doc["image"].replace("\\", "/")).name
        if named != PurePosixPath(image.filename).name:
            raise MapUploadError("files", f"{yamls[0].filename} names image {shown(named)}, but the"
                                 f" image uploaded is {shown(image.filename)}: upload the image it names")  # fmt: skip
        doc["image"] = "map" + _suffix(image.filename)
    else:
        if resolution is None:
            raise MapUploadError("resolution", f"{image.filename} is a plain image: give its"
                                 " resolution (metres per pixel, > 0), or upload the map_server"
                                 " .yaml that names it")  # fmt: skip
        occ = 0.65 if occupied_thresh is None else occupied_thresh
        free = 0.196 if free_thresh is None else free_thresh
        doc = {"image": "map" + _suffix(image.filename), "mode": "trinary",
               "resolution": resolution, "origin": [0.0, 0.0, 0.0], "negate": int(bool(negate)),
               "occupied_thresh": occ, "free_thresh": free}  # fmt: skip
    text = yaml.safe_dump(doc, sort_keys=False)
    return text.encode(), _suffix(image.filename), image.data


def suggest_env(yaml_path: Path, ref: str, m: OccupancyMap) -> tuple[dict[str, Any], list[str]]:
    """The env fields that drive the map ``m`` (read from ``yaml_path``) at the default 0.5 m
    cells (grid, room, and a step limit from its longest shortest path, as ``quicknav eval --map``
    sets them), and what to know about them: free space the grid loses, a map too large for any
    grid at these cells."""
    from quicknav_core.config import EnvConfig
    from quicknav_core.eval.map_fit import fit_map

    env = EnvConfig()
    assert env.cell_size == SUGGESTED_CELL_M
    try:
        fit = fit_map(env, yaml_path, loaded=m)
    except MapError as e:  # larger than any grid at 0.5 m cells, or nowhere a robot fits
        grid = max(m.cells(SUGGESTED_CELL_M)) + 2
        return ({"rooms": "maps", "maps": {"train": [ref]}, "grid_size": grid,
                 "room_size": grid * SUGGESTED_CELL_M}, [str(e)])  # fmt: skip
    shape = {k: v for k, v in fit.shape_fields().items() if v is not None}  # a non-square map's
    suggested = {"rooms": "maps", "maps": {"train": [ref]}, "grid_size": fit.grid_size, **shape,
                 "room_size": fit.room_size, "max_steps": fit.max_steps}  # fmt: skip
    return suggested, fit.warnings()


def limit_notes(suggested: dict[str, Any], max_grid_size: int) -> list[str]:
    """What this server's limits say about a suggested env (QUICKNAV_MAX_GRID_SIZE)."""
    from quicknav_core.eval.map_fit import MAX_GRID

    grid = suggested.get("grid_size", 0)
    if grid > max_grid_size:
        return [f"grid_size {grid} is above this server's limit of {max_grid_size}"
                f" (QUICKNAV_MAX_GRID_SIZE, which the operator can raise to {MAX_GRID}): a job with this"
                " env is refused here; crop the map to the part the robot drives"]  # fmt: skip
    return []


class MapLibrary:
    """The uploaded maps of one artifact store."""

    def __init__(self, artifacts: ArtifactStore, max_pixels: int, budget: DecodeBudget | None = None):
        self.artifacts = artifacts
        self.max_pixels = max_pixels
        self.budget = budget if budget is not None else DecodeBudget(max_pixels * DECODE_BYTES_PER_PIXEL)

    # ---------------------------------------------------------------- adding
    def add(self, files: list[UploadedFile], name: str | None = None, resolution: float | None = None,
            negate: bool | None = None, occupied_thresh: float | None = None,
            free_thresh: float | None = None) -> dict[str, Any]:  # fmt: skip
        """Check an upload by reading it as the env will, store it; its metadata."""
        from PIL import Image

        for field, v in (("resolution", resolution), ("occupied_thresh", occupied_thresh),
                         ("free_thresh", free_thresh)):  # fmt: skip
            if v is not None and not (math.isfinite(v) and v > 0 and (field == "resolution" or v <= 1)):
                allowed = "> 0 (metres per pixel)" if field == "resolution" else "in (0, 1]"
                raise MapUploadError(field, f"{field}={v}: allowed {allowed}")
        yaml_bytes, suffix, image_bytes = _canonical(files, resolution, negate, occupied_thresh,
                                                     free_thresh)  # fmt: skip
        image_name = next(f.filename for f in files if _suffix(f.filename) in IMAGE_SUFFIXES)
        try:
            check_pixels(image_bytes[:256], image_name, self.max_pixels)
            with Image.open(io.BytesIO(image_bytes)) as im:
                width, height = im.size
                kind = im.format
        except MapError:  # its header claims more pixels than this server takes: not decoded
            width, height = header_size(image_bytes[:256]) or (0, 0)
            kind = "header"
        except Exception:
            raise MapUploadError("files", f"{image_name}: not a PGM or PNG image (a map_server map"
                                 " is a binary P5 or text P2 PGM)") from None  # fmt: skip
        named_kind = {".png": "PNG", ".pgm": "PPM"}[suffix]
        if kind not in (named_kind, "header"):
            actual = {"PNG": ".png", "PPM": ".pgm"}.get(kind or "", f"a {kind} image")
            raise MapUploadError("files", f"{image_name}: its contents are {actual}, not {suffix}:"
                                 " name the file by what it holds")  # fmt: skip
        if width * height > self.max_pixels:
            raise MapUploadError("files", f"{image_name}: {width} x {height} pixels is more than the"
                                 f" {self.max_pixels:,} this server takes (QUICKNAV_MAX_MAP_PIXELS);"
                                 " save the map at a coarser resolution", status=413)  # fmt: skip
        with self.budget.hold(width * height * DECODE_BYTES_PER_PIXEL, image_name):
            return self._store(files, name, image_name, yaml_bytes, suffix, image_bytes, width, height)

    def _store(self, files: list[UploadedFile], name: str | None, image_name: str, yaml_bytes: bytes,
               suffix: str, image_bytes: bytes, width: int, height: int) -> dict[str, Any]:  # fmt: skip
        """Read a checked upload as a job will (within the decode budget) and store it."""
        from PIL import Image

        from quicknav_core.env.render import map_picture, map_picture_step

        map_id = hashlib.sha256(yaml_bytes + b"\0" + image_bytes).hexdigest()[:ID_LENGTH]
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            (folder / "map.yaml").write_bytes(yaml_bytes)
            (folder / f"map{suffix}").write_bytes(image_bytes)

            def ours(message: str) -> str:  # the client's file names, not the server's paths
                message = message.replace(str(folder / f"map{suffix}"), image_name)
                return message.replace(str(folder / "map.yaml"), "the map")

            try:
                m = load_map(folder / "map.yaml")
            except MapError as e:
                raise MapUploadError("files", ours(str(e))) from None
            free = int((~m.blocked).sum())
            if free == 0:
                raise MapUploadError("files", f"{image_name}: no free pixel: every pixel is occupied or"
                                     " unknown (check negate and the thresholds)")  # fmt: skip
            existing = self.get(map_id)
            if existing is not None:  # the same files: the same map, under the name given now
                if name and name[:200] != existing["name"]:
                    existing["name"] = name[:200]
                    self.artifacts.put_bytes(f"{MAPS}/{map_id}", "meta.json", json.dumps(existing).encode())
                return existing
            suggested, notes = suggest_env(folder / "map.yaml", MAP_ID_PREFIX + map_id, m)
            notes = [n.replace(str(folder / "map.yaml"), image_name) for n in notes]
        width_m, height_m = m.size_m
        step = map_picture_step(m.blocked.shape)
        preview = io.BytesIO()
        Image.fromarray(map_picture(m.blocked, m.unknown)).save(preview, format="PNG")
        meta = {
            "id": map_id,
            "ref": MAP_ID_PREFIX + map_id,
            "name": (name or PurePosixPath(image_name).stem)[:200],
            "created": time.time(),
            "files": [f.filename for f in files],
            "width_px": width,
            "height_px": height,
            "resolution": m.resolution,
            "width_m": round(width_m, 6),
            "height_m": round(height_m, 6),
            "free_fraction": round(free / m.blocked.size, 4),
            "unknown_fraction": round(float(m.unknown.mean()) if m.unknown is not None else 0.0, 4),
            "bytes": len(yaml_bytes) + len(image_bytes),
            "preview_m_per_px": m.resolution * step,
            # an env that holds the map at the default 0.5 m cells (a starting point, not a rule)
            "suggested_env": suggested,
            "notes": notes,
        }  # fmt: skip
        folder = f"{MAPS}/{map_id}"
        self.artifacts.put_bytes(folder, f"map{suffix}", image_bytes)
        self.artifacts.put_bytes(folder, "map.yaml", yaml_bytes)
        self.artifacts.put_bytes(folder, "preview.png", preview.getvalue())
        self.artifacts.put_bytes(folder, "meta.json", json.dumps(meta).encode())  # last: complete
        return meta

    # ---------------------------------------------------------------- reading
    def get(self, map_id: str) -> dict[str, Any] | None:
        if not valid_id(map_id):
            return None
        data = self.artifacts.read_bytes(f"{MAPS}/{map_id}", "meta.json")
        return json.loads(data) if data is not None else None

    def name(self, map_id: str) -> str | None:
        """The name the map was uploaded with (None: no such map)."""
        meta = self.get(map_id)
        return meta.get("name") if meta is not None else None

    def list(self) -> list[dict[str, Any]]:
        """Every stored map, newest first."""
        found = [m for i in self.artifacts.folders(MAPS) if (m := self.get(i)) is not None]
        return sorted(found, key=lambda m: -m["created"])

    def preview(self, map_id: str) -> bytes | None:
        return self.artifacts.read_bytes(f"{MAPS}/{map_id}", "preview.png") if valid_id(map_id) else None

    def local_yaml(self, map_id: str) -> Path:
        """The stored map's ``map.yaml`` on this machine (MapError naming the id if none)."""
        # the store says whether it exists (a copy cached here may outlive a delete elsewhere)
        exists = valid_id(map_id) and self.get(map_id) is not None
        folder = self.artifacts.local_folder(f"{MAPS}/{map_id}") if exists else None
        if folder is None or not (folder / "meta.json").exists():
            raise MapError(f"{MAP_ID_PREFIX}{map_id}: no such map on this server (GET /maps lists"
                           " them; upload one with POST /maps)")  # fmt: skip
        return folder / "map.yaml"

    def delete(self, map_id: str) -> None:
        self.artifacts.delete(f"{MAPS}/{map_id}")


def maps_named(config: dict[str, Any] | None) -> set[str]:
    """The stored map ids a job's config names, wherever its env sits (a train or eval job's
    ``env``, a sweep's ``base.env``, a trial batch's ``sweep.base.env``)."""
    return set(MAP_REF.findall(json.dumps(config or {})))


def library(settings) -> MapLibrary:
    """The maps of the artifact store the settings name."""
    from quicknav_service.artifacts import make_artifacts

    return MapLibrary(make_artifacts(settings), settings.max_map_pixels)

