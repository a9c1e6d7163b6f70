"""Independent references for tests: brute-force geometry written without the library's tricks."""

from __future__ import annotations

import heapq
import math

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


GOLDEN32 = 0x9E3779B9


def fmix32_np(x):
    """MurmurHash3's 32-bit finaliser in NumPy uint32 arithmetic (wraps like the JAX one)."""
    x = np.uint32(x)
    with np.errstate(over="ignore"):
        x ^= x >> np.uint32(16)
        x = np.uint32(x * np.uint32(0x85EBCA6B))
        x ^= x >> np.uint32(13)
        x = np.uint32(x * np.uint32(0xC2B2AE35))
        x ^= x >> np.uint32(16)
    return x


def block_walk_reference(key_data, grid, target, step_cap, return_prob, to_carved, block=240):
    """The block carvers (``centre``, ``carved``) one step at a time in plain Python.

    Step s draws the hash word at counter 2s (return test in its top 30 bits, direction in its low
    2) and, for ``to_carved``, the word at 2s+1 (the index of the carved cell a return lands on,
    among the cells carved before the block of s began). Returns (walls (g, g) bool, steps).
    """
    d0, d1 = (np.uint32(v) for v in key_data)
    with np.errstate(over="ignore"):
        word = fmix32_np(d0 ^ fmix32_np(np.uint32(d1 + np.uint32(GOLDEN32))))

    def bits(counter):
        with np.errstate(over="ignore"):
            mixed = np.uint32(np.uint32(counter) * np.uint32(GOLDEN32) + np.uint32(0x632BE5AB))
        return int(fmix32_np(word ^ fmix32_np(mixed)))

    threshold = int(np.round(np.float32(return_prob) * np.float32(2**30)))
    moves = ((1, 0), (-1, 0), (0, -1), (0, 1))
    walls = np.ones((grid, grid), bool)
    centre = (grid // 2, grid // 2)
    walls[centre] = False
    carved = [centre]
    pos, step, known = centre, 0, 1
    while len(carved) < target and step < step_cap:
        if step % block == 0:
            known = len(carved)  # returns land on cells carved before this block
        b = bits(2 * step)
        if (b >> 2) < threshold:
            if to_carved:
                pos = carved[(bits(2 * step + 1) * known) >> 32]
            else:
                pos = centre
        dr, dc = moves[b & 3]
        r, c = pos[0] + dr, pos[1] + dc
        if 1 <= r <= grid - 2 and 1 <= c <= grid - 2:
            pos = (r, c)
        if walls[pos]:
            walls[pos] = False
            carved.append(pos)
        step += 1
    return walls, step


def grid_dijkstra(usable, goal_seeds, step):
    """Heap Dijkstra on an 8-connected grid without corner cutting (the planner's graph):
    distance from every node to the seeded ones, ``goal_seeds`` {(row, col): start distance}."""
    n = usable.shape[0]
    dist = np.full((n, n), np.inf)
    heap = []
    for (r, c), d in goal_seeds.items():
        if usable[r, c] and d < dist[r, c]:
            dist[r, c] = d
            heapq.heappush(heap, (d, r, c))
    while heap:
        d, r, c = heapq.heappop(heap)
        if d > dist[r, c]:
            continue
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                if not (dr or dc):
                    continue
                rr, cc = r + dr, c + dc
                if not (0 <= rr < n and 0 <= cc < n) or not usable[rr, cc]:
                    continue
                if dr and dc and not (usable[r + dr, c] and usable[r, c + dc]):
                    continue
                nd = d + step * (math.sqrt(2) if dr and dc else 1.0)
                if nd < dist[rr, cc] - 1e-9:
                    dist[rr, cc] = nd
                    heapq.heappush(heap, (nd, rr, cc))
    return dist


def open_doors_cell_by_cell(walls: np.ndarray, fp, rng: np.random.Generator) -> None:
    """Floor-plan doors (``quicknav_core.env.floorplan``'s rule), found cell by cell: every wall
    cell with free cells of two different regions left and right (or above and below) starts a
    candidate when the ``width`` cells from it along the wall all do, with the same two regions;
    candidates by width, then horizontal passages before vertical ones, each in row-major order.
    Taken in a random order, a candidate opens when it joins two regions not yet connected, or,
    with probability ``loop_prob``, when no door joins its two regions yet."""
    from scipy import ndimage

    labels, _ = ndimage.label(~walls)
    g = walls.shape[0]
    candidates = []  # (cells of the door, smaller region, larger region)
    for width in range(fp.door_width, (fp.door_width_max or fp.door_width) + 1):
        for vertical in (False, True):
            lab = labels.T if vertical else labels
            for r in range(g):
                for c in range(g - 2):
                    run = []
                    for k in range(width):
                        if r + k >= g:
                            break
                        a, mid, b = lab[r + k, c], lab[r + k, c + 1], lab[r + k, c + 2]
                        if mid != 0 or a == 0 or b == 0 or a == b:
                            break
                        run.append((int(a), int(b)))
                    if len(run) < width or len(set(run)) != 1:
                        continue
                    cells = [(r + k, c + 1) for k in range(width)]
                    if vertical:
                        cells = [(cc, rr) for rr, cc in cells]
                    candidates.append((cells, *sorted(run[0])))
    parent = list(range(int(labels.max()) + 1))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    joined: set[tuple[int, int]] = set()
    for i in rng.permutation(len(candidates)):
        cells, a, b = candidates[i]
        if any(not walls[r, c] for r, c in cells):
            continue  # overlaps a door already open
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[ra] = rb
        elif (a, b) in joined or rng.random() >= fp.loop_prob:
            continue
        joined.add((a, b))
        for r, c in cells:
            walls[r, c] = False
