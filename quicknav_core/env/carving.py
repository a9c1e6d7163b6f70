"""How long the carving walk takes, computed before carving (NumPy and SciPy, no JAX).

Centre returns (``rooms`` carvers ``paper`` and ``centre``): the walk on the inner cells jumps back
to the centre with probability ``return_prob`` each step. Its long-run occupation ``pi`` (the
fraction of steps spent on each cell) solves ``pi = return_prob * e_centre + (1 - return_prob) *
M^T pi`` for the walk's move matrix M (moves into the outer wall are refused): one sparse linear
solve. A cell visited with rate ``pi_c`` is carved within t steps with probability ``1 - exp(-t
pi_c)``, so the expected number of carved cells after t steps is ``sum_c 1 - exp(-t pi_c)``; the step
count at which it reaches the carve target is the estimate. Measured against the real carver (grid
16 to 64, return_prob 0.01 to 0.1, 32 rooms each) the slowest room needed 2.2 to 4.6 times the
estimate.

Returns to carved cells (carver ``carved``): the walk has no fixed occupation (it restarts
anywhere in a growing blob), so the estimate is a fitted one. With p = return_prob: the steps a
walker visiting uniformly random inner cells would need (the coupon collector, ``N ln(N / (N -
target))``), times the walk's slowdown ``3 + log2(max(grid, 16) / 16) / 2 + 0.12 grid sqrt(p) +
p / (1 - p)``: its steps are local (3 to 4.5 times the coupon count without returns), and a return
restarts it inside the blob, about grid/2 cells from the edge, of which an excursion of 1/p steps
covers sqrt(1/p). Measured (grid 8 to 128, carve_fraction 0.3 to 1, p 0 to 0.9, 64 rooms each):
the mean room took 0.23 to 1.2 times the estimate, the slowest up to 2.9 times.

A config is refused when ``SLOWEST_ROOM_FACTOR`` times its carver's estimate exceeds the step cap: it
would spend minutes of CPU and then fail (before this check: grid 48 and 64 with the defaults).
``choose_carver`` decides what ``carver="auto"`` means from the same estimates.
"""

from __future__ import annotations

import math

import numpy as np

from quicknav_core.env.constants import CARVE_MOVES

SLOWEST_ROOM_FACTOR = 4.0

# How ``rooms`` carves (``EnvConfig.carver``): the first two return to the centre, the last to a
# random carved cell.
CARVERS = ("paper", "centre", "carved")
# ``carver="auto"``: the paper's exact stream (eight threefry calls a step, ~80 ns a room-step on
# one CPU core) while the estimate stays under AUTO_PAPER_MAX_STEPS (a default grid-16 bank: under
# a second); the same walk with block draws (~20 ns a room-step) under AUTO_CENTRE_MAX_STEPS (grid
# 32 at return_prob 0.05); beyond that, returns to carved cells.
AUTO_PAPER_MAX_STEPS = 2_000
AUTO_CENTRE_MAX_STEPS = 50_000


def occupation(grid_size: int, return_prob: float) -> np.ndarray:
    """Long-run fraction of steps the walk spends on each inner cell, ((g-2)**2,) summing to 1."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = grid_size - 2
    idx = np.arange(n * n).reshape(n, n)
    rows, cols, vals = [], [], []
    row, col = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        r, c = row + dr, col + dc
        inside = (r >= 0) & (r < n) & (c >= 0) & (c < n)  # a move into the wall ring is refused
        dst = np.where(inside, idx[np.clip(r, 0, n - 1), np.clip(c, 0, n - 1)], idx)
        rows.append(dst.ravel())
        cols.append(idx.ravel())
        vals.append(np.full(n * n, 0.25))
    move = sp.csc_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * n, n * n)
    )
    centre = idx[grid_size // 2 - 1, grid_size // 2 - 1]
    even = np.full(n * n, 1.0 / (n * n))  # a walk without resets spreads evenly
    if return_prob <= 0.0 or 1.0 - return_prob == 1.0:
        return even  # (a chance below float64's resolution of 1 is no reset at all: I - move is singular)
    a = sp.identity(n * n, format="csc") - (1.0 - return_prob) * move
    b = np.zeros(n * n)
    b[centre] = return_prob
    with np.errstate(all="ignore"):
        pi = np.clip(spla.spsolve(a, b), 0.0, None)
    total = pi.sum()
    if not (np.isfinite(total) and total > 0.0):  # a system too near singular to solve: the limit
        return even
    return pi / total


def expected_steps(grid_size: int, return_prob: float, target: int, pi: np.ndarray | None = None) -> float:
    """Estimated carving steps until ``target`` cells are free (inf if the walk cannot); ``pi``:
    the walk's ``occupation`` when the caller has it (one sparse solve, ~35 ms at grid 128)."""
    n_inner = (grid_size - 2) ** 2
    if target > n_inner:
        return math.inf
    if return_prob <= 0.0:
        # a reflecting random walk: about n log^2 n steps to cover the grid (coupon collector
        # on a 2-D lattice), fewer for a partial target
        cover = n_inner * max(math.log(n_inner), 1.0) ** 2 / 4
        return max(float(target), cover * target / n_inner)
    if pi is None:
        pi = occupation(grid_size, float(return_prob))
    carved = lambda t: float(np.sum(-np.expm1(-t * pi)))  # noqa: E731
    if carved(1e18) < target - 0.5:
        return math.inf
    lo, hi = float(target - 1), float(max(target, 2))
    while carved(hi) < target:
        hi *= 2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if carved(mid) < target else (lo, mid)
    return hi


def expected_steps_carved(grid_size: int, return_prob: float, target: int) -> float:
    """Estimated carving steps until ``target`` cells are free when returns land on carved cells."""
    n_inner = (grid_size - 2) ** 2
    if target > n_inner:
        return math.inf
    coupon = n_inner * math.log(n_inner / (n_inner - target + 0.5))
    slowdown = (
        3.0 + 0.5 * math.log2(max(grid_size, 16) / 16) + 0.12 * grid_size * math.sqrt(return_prob)
        + return_prob / (1.0 - return_prob)
    )  # fmt: skip
    return max(float(target), coupon * slowdown)


def carver_steps(
    carver: str, grid_size: int, return_prob: float, target: int, pi: np.ndarray | None = None
) -> float:
    """Estimated carving steps per room for one of ``CARVERS`` (``pi``: as ``expected_steps``)."""
    if carver == "carved":
        return expected_steps_carved(grid_size, return_prob, target)
    return expected_steps(grid_size, return_prob, target, pi)


def choose_carver(grid_size: int, return_prob: float, target: int) -> str:
    """What ``carver="auto"`` means for this room: the first of ``CARVERS`` that is quick."""
    steps = expected_steps(grid_size, return_prob, target)
    if steps <= AUTO_PAPER_MAX_STEPS:
        return "paper"
    return "centre" if steps <= AUTO_CENTRE_MAX_STEPS else "carved"


def feasible(
    grid_size: int, return_prob: float, target: int, step_cap: int, carver: str = "paper",
    pi: np.ndarray | None = None,
) -> bool:
    """Whether even the slowest rooms of ``carver`` are expected to meet ``target`` within the cap
    (``pi``: as ``expected_steps``)."""
    return SLOWEST_ROOM_FACTOR * carver_steps(carver, grid_size, return_prob, target, pi) <= step_cap


def largest_return_prob(grid_size: int, target: int, step_cap: int) -> float:
    """The largest return_prob (to 3 significant digits) with which a walk that returns to the
    centre still carves ``target`` cells."""
    if not feasible(grid_size, 0.0, target, step_cap):
        return 0.0
    lo, hi = 0.0, 0.99
    if feasible(grid_size, hi, target, step_cap):
        return hi
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if feasible(grid_size, mid, target, step_cap) else (lo, mid)
    return float(f"{lo:.3g}")


# --------------------------------------------------------------------------- the NumPy carver
def carve_room_np(
    rng: np.random.Generator, grid_size: int, target: int, step_cap: int, return_prob: float,
    to_carved: bool = False,
) -> np.ndarray:  # fmt: skip
    """Random-walk carving in NumPy (same algorithm as ``rooms.carve_bank``; the twin's rooms). (g, g) bool, True = wall.

    A return goes to the centre, or with ``to_carved`` (carver ``carved``) to a uniformly random
    cell carved so far.
    """
    walls = np.ones((grid_size, grid_size), dtype=bool)
    centre = np.array([grid_size // 2, grid_size // 2])
    walls[centre[0], centre[1]] = False
    carved = [centre.copy()]
    pos, free, step = centre.copy(), 1, 0
    while free < target and step < step_cap:
        if rng.random() < return_prob:
            pos = carved[rng.integers(len(carved))].copy() if to_carved else centre.copy()
        nxt = pos + CARVE_MOVES[rng.integers(4)]
        if np.all((nxt >= 1) & (nxt <= grid_size - 2)):
            pos = nxt
        if walls[pos[0], pos[1]]:
            walls[pos[0], pos[1]] = False
            carved.append(pos.copy())
            free += 1
        step += 1
    return walls
