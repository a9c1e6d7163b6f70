"""Generated floor plans: rectangular rooms split by one-cell walls, joined by doors, off a corridor.

A plan is built on the same ``(grid, grid)`` wall grid as a carved room (outer ring wall):

1. The inner area is split recursively (binary space partitioning): a rectangle wider or taller
   than ``2 * min_room + 1`` cells may be cut by a wall line across it, at a random place that
   leaves both sides at least ``min_room`` cells; it stops being cut with probability growing as
   it shrinks, so plans mix large and small rooms. The first cut across the longer side is a
   corridor instead of a wall when ``corridor_width > 0``: two wall lines with that many free
   cells between them (the hallway of an office floor).
2. Doors join the regions: every run of ``door_width`` wall cells (of each width from
   ``door_width`` to ``door_width_max``, when set) with a free cell of one region on
   one side and of another region on the other side is a candidate; candidates are taken in a
   random order and one is opened whenever it joins two regions not yet connected (a random
   spanning tree of the rooms, so every free cell is reachable), and each further candidate
   between regions already joined opens with probability ``loop_prob`` only if no door joins
   those two regions yet (a second way round, as real floors have).

Plans are drawn from numpy's generator seeded by (room_seed, split stream, room index), so
a bank is the same on every machine, and the test bank skips any plan that is also a train plan.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from quicknav_core.env.constants import SPLIT_STREAM

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig, Split
    from quicknav_core.config.env import FloorplanConfig

PLAN_STREAM = 0x0F100  # keeps plan seeds apart from the carver's streams


def floorplan(grid: int, fp: FloorplanConfig, rng: np.random.Generator) -> np.ndarray:
    """One plan: (grid, grid) bool, True = wall."""
    walls = np.ones((grid, grid), dtype=bool)
    walls[1:-1, 1:-1] = False
    cuts = [(1, 1, grid - 2, grid - 2, 0)]  # (row0, col0, rows, cols, depth) of free rectangles
    while cuts:
        r0, c0, h, w, depth = cuts.pop()
        corridor = fp.corridor_width if depth == 0 else 0
        across_rows = h > w or (h == w and rng.random() < 0.5)  # cut the longer side
        span = h if across_rows else w
        thick = 1 if corridor == 0 else corridor + 2
        room_max = max(fp.min_room, fp.max_room)
        if span < 2 * fp.min_room + thick:
            continue
        # big rectangles are always cut; smaller ones stop with a growing chance
        if span <= room_max and depth > 0 and rng.random() < 0.35 + 0.65 * (1 - span / room_max):
            continue
        at = int(rng.integers(fp.min_room, span - fp.min_room - thick + 1))  # cells before the cut
        if across_rows:
            walls[r0 + at:r0 + at + thick, c0:c0 + w] = True
            if corridor:
                walls[r0 + at + 1:r0 + at + 1 + corridor, c0:c0 + w] = False
            cuts += [(r0, c0, at, w, depth + 1), (r0 + at + thick, c0, h - at - thick, w, depth + 1)]
        else:
            walls[r0:r0 + h, c0 + at:c0 + at + thick] = True
            if corridor:
                walls[r0:r0 + h, c0 + at + 1:c0 + at + 1 + corridor] = False
            cuts += [(r0, c0, h, at, depth + 1), (r0, c0 + at + thick, h, w - at - thick, depth + 1)]
    _open_doors(walls, fp, rng)
    return walls


def _labels(walls: np.ndarray) -> np.ndarray:
    """Connected regions of free cells (4-neighbour), numbered from 1; walls are 0."""
    from scipy import ndimage

    labels, _ = ndimage.label(~walls)
    return labels


def _door_candidates(labels: np.ndarray, widths: range) -> list[tuple[tuple[int, ...], int, int]]:
    """Every door candidate as (its cells as flat indices of the grid, region a, region b), a < b.
    In the order the plans have always used: by width, then doors between left and right regions
    before doors between upper and lower ones, each in row-major order of its first cell (the
    order decides which door a plan's random permutation picks, so banks stay what they were)."""
    g = labels.shape[0]
    out = []
    for width in widths:
        n = g - width + 1  # first cells whose ``width`` cells fit in the grid
        for vertical in (False, True):
            lab = labels.T if vertical else labels
            # a wall cell between two free cells of different regions, left and right of it
            a, b = lab[:, :-2], lab[:, 2:]
            ok = (lab[:, 1:-1] == 0) & (a > 0) & (b > 0) & (a != b)
            run = ok[:n].copy()
            for k in range(1, width):  # every cell of the door, between the same two regions
                run &= ok[k:k + n] & (a[k:k + n] == a[:n]) & (b[k:k + n] == b[:n])
            rows, cols = np.nonzero(run)
            lo = np.minimum(a[rows, cols], b[rows, cols]).tolist()
            hi = np.maximum(a[rows, cols], b[rows, cols]).tolist()
            # in ``lab``'s frame the door runs down rows r.. at column c + 1
            if vertical:  # lab is the transpose: the door is row c + 1, columns r..
                first, step = (cols + 1) * g + rows, 1
            else:
                first, step = rows * g + cols + 1, g
            for f, x, y in zip(first.tolist(), lo, hi, strict=True):
                out.append((tuple(range(f, f + width * step, step)), x, y))
    return out


def _open_doors(walls: np.ndarray, fp: FloorplanConfig, rng: np.random.Generator) -> None:
    labels = _labels(walls)
    widths = range(fp.door_width, (fp.door_width_max or fp.door_width) + 1)
    candidates = _door_candidates(labels, widths)
    parent = list(range(int(labels.max()) + 1))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    joined: set[tuple[int, int]] = set()
    opened: set[int] = set()  # cells of the doors opened so far (every candidate cell is a wall)
    for i in rng.permutation(len(candidates)).tolist():
        cells, a, b = candidates[i]
        if not opened.isdisjoint(cells):
            continue  # overlaps a door already open
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[ra] = rb
        elif (a, b) in joined or rng.random() >= fp.loop_prob:
            continue  # a second door between two regions already joined: at most one, by chance
        joined.add((a, b))
        opened.update(cells)
    walls.flat[sorted(opened)] = False


def plan_rng(config: EnvConfig, split: Split, index: int) -> np.random.Generator:
    return np.random.default_rng([config.room_seed & 0xFFFFFFFF, PLAN_STREAM + SPLIT_STREAM[split], index])


def floorplan_bank(config: EnvConfig, split: Split, count: int, skip: set[bytes] | None = None,
                   tries: int | None = None) -> np.ndarray:  # fmt: skip
    """``count`` plans of ``split`` (the test split skips plans in ``skip``): (count, g, g)."""
    out: list[np.ndarray] = []
    seen = set(skip or ())
    limit = tries if tries is not None else 20 * count + 1000
    index = 0
    while len(out) < count:
        if index >= limit:
            raise ValueError(
                f"env.floorplan at grid_size={config.grid_size}: only {len(out)} distinct"
                f" {split} plans found in {limit} draws (test plans must differ from train plans);"
                " use a larger grid_size, a smaller floorplan.min_room, or fewer test_rooms"
            )
        plan = floorplan(config.grid_size, config.floorplan, plan_rng(config, split, index))
        index += 1
        key = plan.tobytes()
        if split == "test" and key in seen:
            continue
        if split == "test":
            seen.add(key)
        out.append(plan)
    return np.stack(out)
