"""A scripted grid-path follower: BFS over free cells to the goal, steering to the next cell centre.

Used by ``quicknav env demo`` to show a purposeful episode without a trained agent. NumPy only.
"""

from __future__ import annotations

from collections import deque

import numpy as np

_NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def bfs_cell_distances(walls: np.ndarray, target: tuple[int, int]) -> np.ndarray:
    """4-connected BFS distance (in cells) from every free cell to ``target``; -1 where unreachable."""
    g = walls.shape[0]
    dist = np.full((g, g), -1, dtype=np.int64)
    if walls[target]:
        return dist
    dist[target] = 0
    queue = deque([target])
    while queue:
        r, c = queue.popleft()
        for dr, dc in _NEIGHBOURS:
            nr, nc = r + dr, c + dc
            if 0 <= nr < g and 0 <= nc < g and not walls[nr, nc] and dist[nr, nc] < 0:
                dist[nr, nc] = dist[r, c] + 1
                queue.append((nr, nc))
    return dist


class GridPathFollower:
    """Drives towards the centre of the neighbouring cell that is one BFS step closer to the goal."""

    def __init__(self, walls: np.ndarray, goal: np.ndarray, cell_size: float):
        self.walls = np.asarray(walls, bool)
        self.goal = np.asarray(goal, np.float64)
        self.cell = float(cell_size)
        goal_rc = tuple(int(v) for v in np.floor(self.goal[::-1] / self.cell))
        self.goal_rc = goal_rc
        self.dist = bfs_cell_distances(self.walls, goal_rc)

    def target(self, pos: np.ndarray) -> np.ndarray:
        """Point the robot should head for from ``pos``."""
        r, c = (int(v) for v in np.floor(np.asarray(pos)[::-1] / self.cell))
        if (r, c) == self.goal_rc or self.dist[r, c] < 0:
            return self.goal
        best = None
        for dr, dc in _NEIGHBOURS:
            d = self.dist[r + dr, c + dc]
            if d >= 0 and (best is None or d < best[0]):
                best = (d, r + dr, c + dc)
        if best is None or best[0] == 0:
            return self.goal
        return (np.array([best[2], best[1]], np.float64) + 0.5) * self.cell

    def __call__(self, pos: np.ndarray, theta: float) -> np.ndarray:
        """(left, right) wheel command in [-1, 1]."""
        aim = self.target(pos) - np.asarray(pos, np.float64)
        err = np.arctan2(aim[1], aim[0]) - float(theta)
        err = (err + np.pi) % (2 * np.pi) - np.pi
        forward = 0.9 * max(np.cos(err), 0.0) ** 3
        turn = float(np.clip(1.5 * err, -1.0, 1.0))
        return np.clip(np.array([forward - 0.5 * turn, forward + 0.5 * turn]), -1.0, 1.0).astype(
            np.float32
        )
