"""Independent references for tests: brute-force geometry written without the library's tricks."""

from __future__ import annotations

import numpy as np


def brute_force_lidar(pos, theta, goal, walls, angles, cell, max_range, goal_radius):
    """Slab-test every beam against every wall cell's square (float64), and the goal disc."""
    pos = np.asarray(pos, np.float64)
    rows, cols = np.nonzero(walls)
    x0, x1 = cols * cell, (cols + 1) * cell
    y0, y1 = rows * cell, (rows + 1) * cell
    ranges, hits = [], []
    for a in np.asarray(angles, np.float64) + float(theta):
        d = np.array([np.cos(a), np.sin(a)])
        with np.errstate(divide="ignore", invalid="ignore"):
            tx0, tx1 = (x0 - pos[0]) / d[0], (x1 - pos[0]) / d[0]
            ty0, ty1 = (y0 - pos[1]) / d[1], (y1 - pos[1]) / d[1]
        t_enter = np.maximum(np.minimum(tx0, tx1), np.minimum(ty0, ty1))
        t_exit = np.minimum(np.maximum(tx0, tx1), np.maximum(ty0, ty1))
        ok = (t_enter <= t_exit) & (t_exit >= 0)
        t_wall = np.min(np.where(ok, np.maximum(t_enter, 0.0), np.inf))
        # goal disc: solve |pos + t d - goal| = R
        f = pos - np.asarray(goal, np.float64)
        b = f @ d
        c = f @ f - goal_radius**2
        disc = b * b - c
        t_goal = np.inf
        if disc >= 0:
            t1, t2 = -b - np.sqrt(disc), -b + np.sqrt(disc)
            if t2 >= 0:
                t_goal = max(t1, 0.0)
        t = min(t_wall, t_goal)
        if t > max_range:
            ranges.append(max_range)
            hits.append(0)
        else:
            ranges.append(t)
            hits.append(2 if t_goal < t_wall else 1)
    return np.array(ranges), np.array(hits)


def disc_wall_clearance(pos, walls, cell):
    """Distance from a point to the nearest wall cell (0 inside a wall), checking every wall cell."""
    rows, cols = np.nonzero(walls)
    gx = np.maximum(np.maximum(cols * cell - pos[0], pos[0] - (cols + 1) * cell), 0.0)
    gy = np.maximum(np.maximum(rows * cell - pos[1], pos[1] - (rows + 1) * cell), 0.0)
    return float(np.min(np.hypot(gx, gy)))


def flood_fill_component(free: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Cells reachable from ``start`` through 4-connected free cells (iterative stack)."""
    seen = np.zeros_like(free, dtype=bool)
    stack = [start]
    while stack:
        r, c = stack.pop()
        if not (0 <= r < free.shape[0] and 0 <= c < free.shape[1]) or seen[r, c] or not free[r, c]:
            continue
        seen[r, c] = True
        stack.extend([(r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)])
    return seen
