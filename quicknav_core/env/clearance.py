"""Where the robot's disc fits: the cells a start or a goal may be drawn in (NumPy only).

A robot narrower than a cell fits at the centre of every free cell, and every room source makes
its free cells one connected region, so starts and goals are drawn among all free cells (as the
paper does). A robot as wide as a cell or wider (a building mapped at fine cells) fits only where
its disc at the cell's centre overlaps no wall cell, and can drive only between such cells: the
cells where starts and goals are drawn are the largest region of them that is connected by moves
between side neighbours (the disc moving between two neighbouring centres clears every wall that
it clears at both ends, so the region is one the robot can drive through).
"""

from __future__ import annotations

import math

import numpy as np


class RobotFitError(ValueError):
    """A robot that fits in fewer than two cells of some room of a bank; the message starts with
    the field that set its radius (``robot_radius`` or ``randomize.robot_radius_m``)."""


def narrow(radius: float, cell: float) -> bool:
    """Whether the disc fits at the centre of any free cell (it is narrower than a cell)."""
    return 2.0 * radius < cell


def reach_cells(radius: float, cell: float) -> int:
    """How many cells from its own a disc of ``radius`` can overlap, whatever its position."""
    return max(1, math.ceil(radius / cell))


def disc_fits(walls: np.ndarray, cell: float, radius: float) -> np.ndarray:
    """(..., rows, cols) bool: free cells whose centre holds the disc clear of every wall cell."""
    fits = ~np.asarray(walls, dtype=bool)
    if narrow(radius, cell):
        return fits
    rows, cols = fits.shape[-2:]
    k = reach_cells(radius, cell)
    padded = np.pad(np.asarray(walls, bool), [(0, 0)] * (fits.ndim - 2) + [(k, k), (k, k)],
                    constant_values=True)  # fmt: skip
    for dy in range(-k, k + 1):
        for dx in range(-k, k + 1):
            # gap from a cell's centre to the cell (dy, dx) away, in metres
            gy, gx = max(abs(dy) - 0.5, 0.0) * cell, max(abs(dx) - 0.5, 0.0) * cell
            if gy * gy + gx * gx < radius * radius:
                fits &= ~padded[..., k + dy:k + dy + rows, k + dx:k + dx + cols]
    return fits


def spawn_region(walls: np.ndarray, cell: float, radius: float) -> np.ndarray:
    """(rows, cols) bool: the cells starts and goals are drawn in (see the module doc)."""
    fits = disc_fits(walls, cell, radius)
    if narrow(radius, cell):
        return fits
    from scipy import ndimage

    labels, n = ndimage.label(fits)
    if n == 0:
        return fits
    sizes = np.bincount(labels.ravel())[1:]
    return labels == int(np.argmax(sizes)) + 1


def spawn_regions(rooms: np.ndarray, cell: float, radius: float) -> np.ndarray:
    """``spawn_region`` of every room of a bank: (n, rows, cols) bool."""
    if narrow(radius, cell):
        return ~np.asarray(rooms, dtype=bool)
    return np.stack([spawn_region(r, cell, radius) for r in rooms])


def spawn_cells(rooms: np.ndarray, config, split: str, of: int | None = None) -> np.ndarray:
    """(n, rows, cols) bool: where the episodes of each room of a bank start and end. A
    ``RobotFitError`` names the robot's radius when some room has no two cells it fits in (``of``:
    the bank's size when ``rooms`` are its first rooms only)."""
    radius, cell = config.spawn_radius, config.cell_size
    regions = spawn_regions(rooms, cell, radius)
    counts = regions.reshape(len(regions), -1).sum(axis=1)
    short = np.flatnonzero(counts < 2)
    if short.size:
        field = "randomize.robot_radius_m" if radius > config.robot_radius else "robot_radius"
        raise RobotFitError(
            f"{field}: a robot of radius {radius:g} m fits in fewer than two cells of {short.size}"
            f" of the {_rooms_checked(len(rooms), of)} {split} rooms (room {int(short[0])} first):"
            " the disc (diameter"
            f" {2 * radius:g} m) is wider than their passages of {cell:g} m cells. Use a smaller"
            " robot, larger cells (room_size / grid_size), or wider passages (floorplan.door_width,"
            " floorplan.corridor_width)"
        )
    return regions


def _rooms_checked(n: int, of: int | None) -> str:
    return f"first {n} of the {of:,}" if of is not None and of > n else str(n)


def check_fit(config, rooms, at_most: int | None = None) -> None:
    """For a robot wider than a cell, build the banks of ``rooms`` (a room source) and check that
    it fits in every room (``spawn_cells``'s RobotFitError), before anything compiles or trains;
    nothing to do otherwise. ``at_most``: check the first that many rooms of each bank only (a
    door that does not build the env: a service's API, which must not carve a million rooms to
    answer one request; the worker's env build checks every room and fails the job naming the
    same field)."""
    if not config.collision_reach:
        return
    checked = rooms if at_most is None else rooms.first(at_most)
    for split in ("train", "test"):
        spawn_cells(checked.bank(split), config, split, of=rooms.count(split))
