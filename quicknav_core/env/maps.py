"""Maps of real buildings as rooms: ROS map_server occupancy grids (YAML + PGM) and plain images.

A map is read into an occupancy picture (True = the robot may not be there: occupied, and unknown
unless told otherwise), then laid on the env's cell grid conservatively: a cell is wall if any
such pixel overlaps it, so every free cell of the grid is free space in the map, and a passage the
grid opens is one the disc can drive (a robot wider than a cell starts and drives only where its
disc fits: ``env.clearance``). The map's lower-left
corner sits at the corner of cell (1, 1), inside the outer ring of wall; cells the map does not
reach are wall. Free cells that the robot cannot reach from the largest free region (islands
behind unknown space, closed rooms) become wall, so starts and goals are only drawn where the robot
can drive between them.

ROS map_server's YAML (as gmapping, cartographer and slam_toolbox save it): ``image`` (relative
to the YAML), ``resolution`` (m/pixel), ``origin`` ([x, y, yaw] of the lower-left pixel: yaw must
be 0), ``occupied_thresh``, ``free_thresh``, ``negate`` and ``mode`` (``trinary``, the default, or
``scale``). A pixel's occupancy is ``(255 - v) / 255`` (``negate: 1``: ``v / 255``): above
``occupied_thresh`` it is occupied, below ``free_thresh`` free, between the two unknown (``scale``
grades those; QuickNav, which has no graded cells, keeps them unknown). ``v`` is the pixel's grey
level; of a colour image, or one with an alpha channel, it is Nav2's map_server rule (``map_io``):
the mean of red, green and blue, and in ``trinary`` mode the alpha (255 = opaque) averaged in as a
fourth channel; in ``scale`` mode alpha is not averaged and a pixel that is not opaque is unknown.
(ROS 1's map_server averages a grey-and-alpha image's two channels as two; Nav2, read here, as
three grey and one alpha.) A plain PNG/PGM is read the same way, as ``trinary``, with the
thresholds and the resolution given in the config (dark = occupied).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

YAML_SUFFIXES = (".yaml", ".yml")
IMAGE_SUFFIXES = (".pgm", ".png")
MAX_MAP_PIXELS = 64_000_000  # 8000 x 8000: far above what an env grid can use
MAX_RESOLUTION_M = 100.0  # metres per pixel: a map coarser than this is not a building's
# a map_server YAML is a handful of short fields: anything far larger is refused unread
MAX_YAML_BYTES = 64 * 1024
MAX_YAML_DEPTH = 8
MAX_YAML_SCALAR = 1024  # characters of one value (a file name, a number)


def shown(value: Any, most: int = 80) -> str:
    """``repr(value)`` cut to ``most`` characters: error messages never echo unbounded input."""
    text = repr(value)
    return text if len(text) <= most else text[: most - 3] + "..."


def read_yaml_doc(text: str | bytes, where: str) -> Any:
    """A map_server YAML parsed without what a map never has and an attacker would send: aliases
    (their expansion can be exponential), nesting deeper than MAX_YAML_DEPTH, values longer than
    MAX_YAML_SCALAR characters, more than MAX_YAML_BYTES. MapError names the file and the rule."""
    import yaml

    if isinstance(text, bytes):
        if len(text) > MAX_YAML_BYTES:
            raise MapError(f"{where}: {len(text):,} bytes; a map_server YAML is a few fields"
                           f" (at most {MAX_YAML_BYTES:,} bytes here)")  # fmt: skip
        try:
            text = text.decode()
        except UnicodeDecodeError:
            raise MapError(f"{where}: not valid YAML (not UTF-8 text)") from None
    if len(text) > MAX_YAML_BYTES:
        raise MapError(f"{where}: {len(text):,} characters; a map_server YAML is a few fields"
                       f" (at most {MAX_YAML_BYTES:,} here)")  # fmt: skip
    try:
        depth = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent):
                raise MapError(f"{where}: YAML aliases (*name) are not read here; a map_server"
                               " YAML has none (write the values out)")  # fmt: skip
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_YAML_DEPTH:
                    raise MapError(f"{where}: nested more than {MAX_YAML_DEPTH} levels deep; a"
                                   " map_server YAML is flat (origin: [x, y, yaw])")  # fmt: skip
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
            elif isinstance(event, yaml.ScalarEvent) and len(event.value) > MAX_YAML_SCALAR:
                raise MapError(f"{where}: a value of {len(event.value):,} characters; allowed: up"
                               f" to {MAX_YAML_SCALAR:,}")  # fmt: skip
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise MapError(f"{where}: not valid YAML ({shown(str(e).splitlines()[0], 200)})") from None
    except ValueError as e:  # e.g. Python's limit on an integer's digits
        if isinstance(e, MapError):
            raise
        raise MapError(f"{where}: not valid YAML ({shown(str(e), 200)})") from None
MAP_ID_PREFIX = "map:"  # `map:<id>` names a map uploaded to a QuickNav service (POST /maps)

def is_map_id(name: str) -> bool:
    return name.startswith(MAP_ID_PREFIX)


def map_path(name: str, resolver: Callable[[str], Path] | None = None) -> Path:
    """The local file a map name stands for: a path as given, or a stored map's .yaml, which
    ``resolver(id)`` (a service's, ``Runtime.map_resolver``) fetches."""
    if not is_map_id(name):
        return Path(name)
    map_id = name[len(MAP_ID_PREFIX):]
    if resolver is None:
        raise MapError(f"{name}: names a map uploaded to a QuickNav service, which only that"
                       " service's jobs can read; give a file path here (download the map with"
                       " `quicknav maps show ID --download DIR`)")  # fmt: skip
    return resolver(map_id)


def map_parts(path: Path) -> list[Path]:
    """The files a map is read from (a YAML and its image)."""
    if path.suffix.lower() in YAML_SUFFIXES and path.is_file():
        try:
            doc = read_yaml_doc(path.read_bytes(), str(path))
            return [path, path.parent / str(doc["image"])]
        except Exception:  # a broken YAML: loading it says what is wrong
            return [path]
    return [path]


class MapError(ValueError):
    """A map that cannot be used: names the file, the field and the fix."""


@dataclass
class OccupancyMap:
    """A map as read: ``blocked[y, x]`` with y up (row 0 = the bottom row of the picture)."""

    path: str
    blocked: np.ndarray  # (H, W) bool: occupied, or unknown (as wall)
    resolution: float  # metres per pixel
    origin: tuple[float, float] = (0.0, 0.0)  # world (x, y) of the lower-left pixel's corner
    meta: dict[str, Any] = field(default_factory=dict)
    unknown: np.ndarray | None = None  # (H, W) bool, y up: neither occupied nor free (pictures)

    @property
    def size_m(self) -> tuple[float, float]:
        h, w = self.blocked.shape
        return w * self.resolution, h * self.resolution

    def cells(self, cell: float) -> tuple[int, int]:
        """(rows, cols) of ``cell``-metre cells the map covers, without the outer ring of wall."""
        width_m, height_m = self.size_m
        return math.ceil(height_m / cell - 1e-9), math.ceil(width_m / cell - 1e-9)


def _read_image(path: Path, mode: str = "trinary") -> tuple[np.ndarray, np.ndarray | None]:
    """The pixels' levels 0..255, (H, W), top row first (as the picture is drawn), by map_server's
    rule for ``mode`` (the module doc): uint8 of a grey image, float32 means of a colour one or one
    with alpha; and, in ``scale`` mode, the pixels that are not opaque (None when all are)."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise MapError(f"{path}: no such file")
    try:
        with path.open("rb") as f:
            check_pixels(f.read(256), path, MAX_MAP_PIXELS)
        with Image.open(path) as im:
            if im.width * im.height > MAX_MAP_PIXELS:
                raise MapError(f"{path}: {im.width} x {im.height} pixels is more than the"
                               f" {MAX_MAP_PIXELS:,} a map may have; save it at a coarser resolution")  # fmt: skip
            if im.mode in ("I", "I;16", "I;16B", "F"):  # 16-bit PGM: scale to 8 bits
                arr = np.asarray(im, dtype=np.float64)
                top = max(float(arr.max()), 1.0)
                return np.clip(np.round(arr / (65535.0 if top > 255 else 255.0) * 255), 0, 255).astype(np.uint8), None
            return _levels(im, mode)
    except MapError:
        raise
    except UnidentifiedImageError:
        raise MapError(f"{path}: not a PGM or PNG image Pillow can read (a map_server map is a"
                       " binary P5 or text P2 PGM)") from None  # fmt: skip
    except (OSError, ValueError, SyntaxError) as e:  # truncated data, a broken header
        raise MapError(f"{path}: the image cannot be read ({shown(str(e), 120)}); it may be"
                       " truncated") from None  # fmt: skip


def _levels(im, mode: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A decoded 8-bit picture's levels and its pixels that are not opaque (``_read_image``)."""
    if im.mode == "P":  # a palette: its colours, with alpha where the palette has transparency
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    if im.mode in ("1", "L"):
        return np.asarray(im.convert("L"), dtype=np.uint8), None
    alpha = im.mode in ("LA", "RGBA", "PA", "La", "RGBa")
    if im.mode not in ("RGB", "RGBA"):
        im = im.convert("RGBA" if alpha else "RGB")
    px = np.asarray(im)  # (H, W, 3 or 4) uint8; summed a channel at a time, 2 bytes a pixel
    rgb = px[..., 0].astype(np.uint16)
    rgb += px[..., 1]
    rgb += px[..., 2]
    if not alpha:
        return (rgb / np.float32(3.0)).astype(np.float32), None
    a = px[..., 3]
    if mode == "scale":  # alpha is not averaged; a pixel that is not opaque is unknown
        transparent = a < 255
        return (rgb / np.float32(3.0)).astype(np.float32), (transparent if transparent.any() else None)
    rgb += a
    return (rgb / np.float32(4.0)).astype(np.float32), None


def header_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) as a PNG's or a PNM's (PGM's) header states it, read before any decoding;
    None for anything else (Pillow then says what it is)."""
    import struct

    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        return struct.unpack(">II", head[16:24])
    if len(head) >= 2 and head[:1] == b"P" and head[1:2] in b"123456":
        text = re.sub(rb"#[^\n]*", b" ", head[2:256])  # comments may sit between the numbers
        numbers = re.match(rb"\s+(\d{1,12})\s+(\d{1,12})\s", text)
        if numbers:
            return int(numbers[1]), int(numbers[2])
    return None


def check_pixels(head: bytes, where: Path | str, limit: int) -> None:
    """MapError, before decoding, for an image whose header claims more than ``limit`` pixels
    (a decompression bomb, or a map saved far finer than a grid can use)."""
    size = header_size(head)
    if size is not None and size[0] * size[1] > limit:
        raise MapError(f"{where}: {size[0]:,} x {size[1]:,} pixels is more than the {limit:,} a"
                       " map may have; save it at a coarser resolution")  # fmt: skip


def _occupancy_of(levels: np.ndarray, negate: bool) -> np.ndarray:
    """Each pixel's occupancy, ``(255 - v) / 255`` (``negate``: ``v / 255``), in one float64 array
    (a large map's read holds 8 bytes a pixel here, not twice that)."""
    p = levels.astype(np.float64)
    p /= 255.0
    if not negate:
        np.subtract(1.0, p, out=p)
    return p


def occupancy(grey: np.ndarray, occupied_thresh: float, free_thresh: float, negate: bool,
              unknown_free: bool, transparent: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Blocked pixels of a picture's levels by map_server's rule (``transparent``: pixels a
    ``scale`` map leaves unknown whatever their level)."""
    p = _occupancy_of(grey, negate)
    occupied = p > occupied_thresh
    free = p < free_thresh
    if transparent is not None:
        occupied &= ~transparent
        free &= ~transparent
    return occupied | (~free & (not unknown_free))


def unknown_pixels(grey: np.ndarray, occupied_thresh: float, free_thresh: float,
                   negate: bool, transparent: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Pixels that are neither occupied nor free, y up (for pictures of the map)."""
    p = _occupancy_of(grey, negate)
    unknown = (p <= occupied_thresh) & (p >= free_thresh)
    if transparent is not None:
        unknown |= transparent
    return np.ascontiguousarray(unknown[::-1])


def load_map(path: str | Path, resolution: float | None = None, occupied_thresh: float = 0.65,
             free_thresh: float = 0.196, negate: bool = False,
             unknown_free: bool = False) -> OccupancyMap:  # fmt: skip
    """A map_server YAML (its own fields win) or a PNG/PGM with ``resolution`` m/pixel."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in YAML_SUFFIXES:
        return _load_yaml(path, unknown_free)
    if suffix not in IMAGE_SUFFIXES:
        raise MapError(f"{path}: a map is a map_server .yaml (with its .pgm) or a .png/.pgm image;"
                       f" {suffix or 'no suffix'} is neither")  # fmt: skip
    if resolution is None:
        raise MapError(f"{path}: a plain image needs its scale: set maps.resolution (metres per"
                       " pixel), or give the map_server .yaml that names it")  # fmt: skip
    grey, _ = _read_image(path)  # a plain image is read as a trinary map
    blocked = occupancy(grey, occupied_thresh, free_thresh, negate, unknown_free)[::-1]
    return OccupancyMap(str(path), np.ascontiguousarray(blocked), float(resolution),
                        unknown=unknown_pixels(grey, occupied_thresh, free_thresh, negate))  # fmt: skip


def _load_yaml(path: Path, unknown_free: bool) -> OccupancyMap:
    if not path.is_file():
        raise MapError(f"{path}: no such file")
    doc = read_yaml_doc(path.read_bytes(), str(path))
    if not isinstance(doc, dict):
        raise MapError(f"{path}: a map_server YAML is a mapping with image, resolution and origin")

    def need(key: str):
        if key not in doc:
            raise MapError(f"{path}: field {key!r} is missing (map_server needs image, resolution"
                           " and origin)")  # fmt: skip
        return doc[key]

    named = need("image")
    if not isinstance(named, str):
        raise MapError(f"{path}: field 'image' must be the image's file name; got {shown(named)}")
    image = path.parent / named
    raw_resolution, raw_origin = need("resolution"), need("origin")
    try:
        resolution = float(raw_resolution)
        origin = [float(v) for v in raw_origin]
        occ = float(doc.get("occupied_thresh", 0.65))
        free = float(doc.get("free_thresh", 0.196))
        negate = bool(int(doc.get("negate", 0)))
    except (TypeError, ValueError, OverflowError):
        raise MapError(f"{path}: resolution, origin, occupied_thresh, free_thresh and negate must"
                       " be numbers (origin: [x, y, yaw])") from None  # fmt: skip
    if not (0 < resolution <= MAX_RESOLUTION_M):
        raise MapError(f"{path}: field 'resolution' is {resolution:g}; allowed: 0 < resolution <="
                       f" {MAX_RESOLUTION_M:g} (metres per pixel)")  # fmt: skip
    if len(origin) != 3 or not all(math.isfinite(v) and abs(v) <= 1e6 for v in origin):
        raise MapError(f"{path}: field 'origin' must be [x, y, yaw], finite and within 1e6 m; got"
                       f" {shown(origin)}")  # fmt: skip
    if abs(origin[2]) > 1e-9:
        raise MapError(f"{path}: field 'origin' has yaw {origin[2]}; only maps with yaw 0 can be"
                       " laid on the grid (rotate the image and set yaw to 0)")  # fmt: skip
    if not 0.0 <= free < occ <= 1.0:
        raise MapError(f"{path}: free_thresh={free} and occupied_thresh={occ} must satisfy 0 <="
                       " free_thresh < occupied_thresh <= 1")  # fmt: skip
    mode = str(doc.get("mode", "trinary"))
    if mode not in ("trinary", "scale"):
        raise MapError(f"{path}: field 'mode' is {shown(mode)}; QuickNav reads 'trinary' and 'scale' maps")
    if not image.is_file():
        raise MapError(f"{path}: its image {named!r} is not there ({image}: no such file); a"
                       " map_server YAML names its image relative to the YAML's folder")  # fmt: skip
    grey, transparent = _read_image(image, mode)
    blocked = occupancy(grey, occ, free, negate, unknown_free, transparent)[::-1]
    return OccupancyMap(str(path), np.ascontiguousarray(blocked), resolution, (origin[0], origin[1]),
                        unknown=unknown_pixels(grey, occ, free, negate, transparent),
                        meta={"image": str(image), "negate": negate, "mode": mode})  # fmt: skip


def to_cells(m: OccupancyMap, cell: float, grid: int | tuple[int, int]) -> np.ndarray:
    """The map on a (rows, cols) wall grid (``grid``: a square's side or (rows, cols)) with cells
    of ``cell`` metres (see the module doc)."""
    rows, cols = (grid, grid) if isinstance(grid, int) else grid
    width_m, height_m = m.size_m
    need_y, need_x = m.cells(cell)
    if need_x > cols - 2 or need_y > rows - 2:
        side = max(need_x, need_y) + 2
        if rows == cols:
            held = f"grid_size={rows} holds {rows - 2} x {rows - 2}"
            fix = (f"Set grid_size >= {side} with room_size = grid_size x {cell:g} m (="
                   f" {side * cell:g} m)")  # fmt: skip
        else:
            held = f"grid_rows x grid_cols = {rows} x {cols} holds {cols - 2} x {rows - 2}"
            fix = (f"Set grid_rows >= {need_y + 2} and grid_cols >= {need_x + 2} with grid_size the"
                   f" larger and room_size = grid_size x {cell:g} m (or leave them unset for a"
                   f" square grid_size >= {side})")  # fmt: skip
        raise MapError(
            f"{m.path}: the map is {width_m:g} m x {height_m:g} m, {need_x} x {need_y} cells of"
            f" {cell:g} m (room_size / grid_size) plus the outer wall; {held}. {fix}, or a larger"
            " cell size (room_size / grid_size)"
        )
    walls = np.ones((rows, cols), dtype=bool)
    walls[1:1 + need_y, 1:1 + need_x] = False
    h, w = m.blocked.shape
    ys, xs = np.nonzero(m.blocked)
    if ys.size:
        # the cells a pixel overlaps: from its lower-left to its upper-right corner (exclusive)
        eps = 1e-9 * cell
        x0 = np.floor(xs * m.resolution / cell).astype(np.int64)
        x1 = np.floor(((xs + 1) * m.resolution - eps) / cell).astype(np.int64)
        y0 = np.floor(ys * m.resolution / cell).astype(np.int64)
        y1 = np.floor(((ys + 1) * m.resolution - eps) / cell).astype(np.int64)
        span = int(max((x1 - x0).max(), (y1 - y0).max())) + 1
        for dy in range(span):
            for dx in range(span):
                ok = (y0 + dy <= y1) & (x0 + dx <= x1)
                walls[1 + y0[ok] + dy, 1 + x0[ok] + dx] = True
    return walls


def reachable_only(walls: np.ndarray, path: str) -> tuple[np.ndarray, float]:
    """Walls with every free cell outside the largest free region made wall; and the share of
    free cells dropped. MapError when no region of two cells is left."""
    from scipy import ndimage

    labels, n = ndimage.label(~walls)
    if n == 0:
        raise MapError(f"{path}: no free cell is left on the grid (every cell overlaps an occupied"
                       " or unknown pixel); use smaller cells (room_size / grid_size), or"
                       " maps.unknown='free' if the free space is marked unknown")  # fmt: skip
    sizes = np.bincount(labels.ravel())[1:]
    keep = int(np.argmax(sizes)) + 1
    if sizes[keep - 1] < 2:
        raise MapError(f"{path}: no free space the robot fits in: the largest free region is one"
                       " cell; use smaller cells (room_size / grid_size)")  # fmt: skip
    out = walls | (labels != keep)
    return out, 1.0 - sizes[keep - 1] / sizes.sum()


def map_room(path: str | Path, cell: float, grid: int | tuple[int, int], **read: Any) -> np.ndarray:
    """A map file as one room of the bank: (rows, cols) bool (``to_cells``), True = wall."""
    m = load_map(path, **read)
    walls, _ = reachable_only(to_cells(m, cell, grid), m.path)
    return walls
