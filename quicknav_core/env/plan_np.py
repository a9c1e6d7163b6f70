"""The global plan in NumPy, for the NumPy twin and for pictures: the walk down a plan's field
(``env.plan.greedy_path``'s rule and order) and the whole plan as points. NumPy only, so that
``render`` draws a plan without importing the twin."""

from __future__ import annotations

import numpy as np

f32 = np.float32
_INF = f32(1e9)  # env.plan.INF
# 8 neighbours (d_row, d_col), orthogonal first: env.plan's order, so ties break the same way
NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))


def greedy_path_np(field: np.ndarray, usable: np.ndarray, start, steps: int) -> np.ndarray:
    """``env.plan.greedy_path``: (steps, 2) cells down the field, never up (ties: the first)."""
    n_rows, n_cols = field.shape
    r, c = int(start[0]), int(start[1])
    out = np.zeros((steps, 2), np.int64)
    for i in range(steps):
        best, br, bc = field[r, c], r, c
        for dr, dc in NEIGHBOURS:
            rr, cc = min(max(r + dr, 0), n_rows - 1), min(max(c + dc, 0), n_cols - 1)
            ok = usable[rr, cc]
            if dr and dc:
                ok = ok and usable[rr, c] and usable[r, cc]
            d = field[rr, cc] if ok else _INF
            if d < best:
                best, br, bc = d, rr, cc
        r, c = br, bc
        out[i] = (r, c)
    return out


def plan_polyline_np(field: np.ndarray, rc, start, goal, cell: float) -> np.ndarray:
    """(K, 2) x, y of the whole plan, for pictures: ``start``, the centres of the cells down the
    field from the cell ``rc`` (row, col; ``greedy_path_np``) until the goal's cell, then the
    goal. Just ``start`` when the goal cannot be reached from ``rc``."""
    field = np.asarray(field, f32)
    r, c = int(rc[0]), int(rc[1])
    points = [np.asarray(start, np.float64)]
    if field[r, c] < _INF:
        # each step goes one cell down the field, a path of at most field[r, c] + 1 cells
        for rr, cc in greedy_path_np(field, field < _INF, (r, c), int(field[r, c]) + 2):
            if field[rr, cc] <= 0.0:
                break
            points.append((np.array([cc, rr], np.float64) + 0.5) * cell)
        points.append(np.asarray(goal, np.float64))
    return np.asarray(points, np.float32)
