"""A policy's env laid onto one map: the grid follows the map at the policy's cell size, the step
limit follows the map's longest shortest path, and the map's frame is kept for the robot.

``quicknav eval RUN --map MAP`` evaluates a policy on a map with nothing but the map;
``quicknav export RUN --map MAP`` ships the map's grid and frame with the policy for
``quicknav_client.navigate.Navigator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from quicknav_core.config import EnvConfig
from quicknav_core.config.env import GRID_SIZE_RANGE, MapsConfig
from quicknav_core.env.clearance import disc_fits
from quicknav_core.env.maps import MapError, OccupancyMap, load_map, reachable_only, to_cells

MAX_GRID = GRID_SIZE_RANGE[1]  # EnvConfig.grid_size's upper bound
# the step limit: this many times the steps the longest shortest path takes at full speed
STEP_SLACK = 2.0


@dataclass(frozen=True)
class MapFit:
    """One map at one cell size."""

    path: str
    grid_size: int  # the grid's longer side
    cell_m: float
    walls: np.ndarray  # (rows, cols) bool, the room the env drives (outer ring and islands wall)
    origin: tuple[float, float]  # the map frame's (x, y) of the map's lower-left pixel corner
    free_kept: float  # share of the map's free area the grid keeps free (0..1)
    longest_path_m: float  # the longest shortest path between two cells the robot fits in
    max_steps: int

    @property
    def room_size(self) -> float:
        return self.grid_size * self.cell_m

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(rows, cols): the map's extent in cells plus the outer ring, not a square around it."""
        return self.walls.shape

    def shape_fields(self) -> dict[str, int | None]:
        """``EnvConfig``'s grid_rows and grid_cols for this grid: the shorter side's count, None
        for the side that is grid_size (both None for a square)."""
        rows, cols = self.grid_shape
        return {"grid_rows": rows if rows != self.grid_size else None,
                "grid_cols": cols if cols != self.grid_size else None}  # fmt: skip

    @property
    def grid_corner_in_map(self) -> tuple[float, float]:
        """Where the grid's (0, 0) corner lies in the map frame: the map's lower-left corner sits
        at the corner of cell (1, 1), inside the outer ring of wall."""
        return self.origin[0] - self.cell_m, self.origin[1] - self.cell_m

    def env_overrides(self, map_name: str, reading: dict[str, Any] | None = None) -> dict[str, Any]:
        """What ``--set`` would change in a policy's env to drive this map (and this map alone:
        held-out maps the policy's env names are dropped); ``reading``: how the map is read
        (``MapsConfig.reading``)."""
        from quicknav_core.config.env import FloorplanConfig

        maps = {**(reading or {}), "train": [map_name], "test": None}
        return {"rooms": "maps", "maps": maps, "grid_size": self.grid_size, **self.shape_fields(),
                "room_size": self.room_size, "max_steps": self.max_steps,
                "floorplan": FloorplanConfig().model_dump(mode="json")}  # fmt: skip

    def warnings(self) -> list[str]:
        if self.free_kept < 0.9:
            return [f"{self.path}: at {self.cell_m:g} m cells the grid keeps {self.free_kept:.0%} of"
                    " the map's free space (narrow passages close, islands drop); a policy trained"
                    " with smaller cells keeps more"]  # fmt: skip
        return []


def fit_map(env: EnvConfig, path: str | Path, read: dict[str, Any] | None = None,
            loaded: OccupancyMap | None = None) -> MapFit:  # fmt: skip
    """``env``'s policy on the map at ``path`` (MapError when it cannot drive it); ``read``:
    ``load_map``'s keywords (default: as ``env.maps`` reads maps); ``loaded``: the map already
    read from ``path`` (not read again)."""
    if read is None:  # as the env reads its maps
        read = env.maps.load_options() if env.maps is not None else {}
    m = loaded if loaded is not None else load_map(path, **read)
    cell = env.cell_size
    width_m, height_m = m.size_m
    # the map's cells and the outer ring, at least the smallest grid an env may have
    rows, cols = (max(n + 2, GRID_SIZE_RANGE[0]) for n in m.cells(cell))
    side = max(rows, cols)
    if side > MAX_GRID:
        raise MapError(f"{m.path}: the map is {width_m:g} m x {height_m:g} m: at the env's"
                       f" {cell:g} m cells (cell_size; a policy's are those it trained with) that is"
                       f" a grid of {side}, above the {MAX_GRID} an env may have; crop the map to"
                       " the part the robot drives, or use cells of at least"
                       f" {max(width_m, height_m) / (MAX_GRID - 2):.2f} m")  # fmt: skip
    walls, _ = reachable_only(to_cells(m, cell, (rows, cols)), m.path)
    free_area = float((~m.blocked).sum()) * m.resolution**2
    kept = float((~walls).sum()) * cell * cell / free_area if free_area > 0 else 0.0
    longest = longest_path_cells(walls, cell, env.spawn_radius) * cell
    step_m = env.max_wheel_speed * env.dt
    steps = max(env.max_steps, math.ceil(STEP_SLACK * longest / step_m / 50.0) * 50)
    return MapFit(path=str(path), grid_size=side, cell_m=cell, walls=walls, origin=m.origin,
                  free_kept=min(kept, 1.0), longest_path_m=longest, max_steps=steps)  # fmt: skip


def longest_path_cells(walls: np.ndarray, cell: float, radius: float) -> float:
    """The longest shortest path (cells, 8-connected, no corner cutting) between two cells where
    the disc fits: two sweeps of Dijkstra (SciPy), from any cell to the farthest and from there
    (exact on trees and corridors, a lower bound elsewhere)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    usable = disc_fits(walls, cell, radius)
    rows, cols = usable.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    src, dst, cost = [], [], []
    for dr, dc in ((1, 0), (0, 1), (1, 1), (1, -1)):
        r, c = np.nonzero(usable)
        rr, cc = r + dr, c + dc
        inside = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        r, c, rr, cc = r[inside], c[inside], rr[inside], cc[inside]
        ok = usable[rr, cc]
        if dr and dc:
            ok &= usable[rr, c] & usable[r, cc]
        src.append(index[r[ok], c[ok]])
        dst.append(index[rr[ok], cc[ok]])
        cost.append(np.full(int(ok.sum()), math.sqrt(2.0) if dr and dc else 1.0))
    graph = csr_matrix((np.concatenate(cost), (np.concatenate(src), np.concatenate(dst))),
                       shape=(rows * cols, rows * cols))  # fmt: skip
    start = int(index[usable][0])
    far = 0.0
    for _ in range(2):
        d = dijkstra(graph, directed=False, indices=start)
        d[~np.isfinite(d)] = -1.0
        start, far = int(np.argmax(d)), float(d.max())
    return far


def env_on_map(env: EnvConfig, name: str, resolver: Callable[[str], Path] | None = None,
               stored_only: bool = False,
               seen: Callable[[EnvConfig, MapFit], None] | None = None,
               reading: dict[str, Any] | None = None) -> EnvConfig:  # fmt: skip
    """``env`` driving the map ``name`` (a file, or ``map:<id>`` read through ``resolver``): its
    rooms, the grid that holds it at ``env``'s cell size and the step limit of its longest path
    (``resolve_eval``'s ``map_env``). ``reading``: how the map is read (``MapsConfig.reading``: a
    plain image's scale, its thresholds; default ``env``'s own, else the defaults).
    ``stored_only``: a server's rule, only uploaded maps. ``seen(env, fit)``: told how the map
    was laid (the CLI prints it). MapError when it cannot be laid."""
    from quicknav_core.config import resolve_env
    from quicknav_core.env.maps import is_map_id, map_path

    if stored_only and not is_map_id(name):
        raise MapError("this server reads only maps uploaded to it: name one as 'map:<id>'"
                       " (GET /maps lists them; POST /maps uploads one)")  # fmt: skip
    if reading is None:
        reading = env.maps.reading() if env.maps is not None else {}
    maps = MapsConfig.model_validate({**reading, "train": [name]})
    fit = fit_map(env, map_path(name, resolver), read=maps.load_options())
    if seen is not None:
        seen(env, fit)
    return resolve_env(fit.env_overrides(name, maps.reading()), env)
