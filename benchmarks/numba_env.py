"""A compiled reference of QuickNav's batched step in numba: the anchor for the JAX env's speed.

The same env as ``quicknav_core`` (room bank, differential drive with wall sliding, lidar with goal
hits, the paper's reward with cycle counting, auto-reset with the farthest-of-K goal), written as
the loop a performance engineer would write by hand for a CPU:

- one ``prange`` over envs, so every core steps its share of the batch;
- the lidar as a grid DDA that stops at the first wall (the JAX env walks fixed work per beam);
- a spawn computed only for the envs whose episode ended (under vmap every env computes one);
- randomness from the env's own counter hash (``quicknav_core.env.rng``: MurmurHash3's finaliser
  of the key data, no Threefry), so a step costs a few integer operations of randomness.

It writes the whole observation (``obs_dim`` floats per env) every step, as the JAX env does.
``tests/benchmarks/test_numba_reference.py`` holds it to the NumPy twin: the lidar beam by beam
on random poses, and the dynamics, reward and observation step by step in the same rooms.

    uv run python benchmarks/numba_env.py [--envs 4096] [--grid 16] [--beams 16] [--seconds 3]

prints env steps/s of this reference on 1 thread and on every core, and of the JAX env
(``quicknav bench``'s rollout: vmap inside lax.scan) in the same process, and their ratio.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import numba  # noqa: E402
import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

f32 = np.float32
HIT_NONE, HIT_WALL, HIT_GOAL = 0, 1, 2
BIG = f32(1e9)
GOLDEN = np.uint32(0x9E3779B9)


# --------------------------------------------------------------------------- randomness
@njit(inline="always")
def fmix32(x):
    x = np.uint32(x)
    x ^= x >> np.uint32(16)
    x = np.uint32(x * np.uint32(0x85EBCA6B))
    x ^= x >> np.uint32(13)
    x = np.uint32(x * np.uint32(0xC2B2AE35))
    return np.uint32(x ^ (x >> np.uint32(16)))


@njit(inline="always")
def uniform(stream, i):
    """The i-th float32 uniform in [0, 1) of a stream word (``rng.counter_bits``, 23 bits)."""
    bits = fmix32(stream ^ fmix32(np.uint32(np.uint32(i) * GOLDEN + np.uint32(0x632BE5AB))))
    return f32(bits >> np.uint32(9)) * f32(1.0 / 8388608.0)


# --------------------------------------------------------------------------- geometry
@njit(inline="always")
def overlaps(walls, x, y, cell, radius):
    """Whether a disc at (x, y) overlaps a wall cell; only the 3x3 cells around it can."""
    g = walls.shape[0]
    row, col = math.floor(y / cell), math.floor(x / cell)
    r0 = min(max(row - 1, 0), g - 3)
    c0 = min(max(col - 1, 0), g - 3)
    r2 = radius * radius
    for r in range(r0, r0 + 3):
        y0 = f32(r) * cell
        gy = max(max(y0 - y, y - (y0 + cell)), f32(0.0))
        for c in range(c0, c0 + 3):
            if walls[r, c]:
                x0 = f32(c) * cell
                gx = max(max(x0 - x, x - (x0 + cell)), f32(0.0))
                if gy * gy + gx * gx < r2:
                    return True
    return False


@njit(inline="always")
def cast_beam(walls, x, y, dx, dy, cell):
    """Distance along (dx, dy) from (x, y) to the first wall cell: a grid DDA that stops there."""
    g = walls.shape[0]
    cx, cy = math.floor(x / cell), math.floor(y / cell)
    cx, cy = min(max(cx, 0), g - 1), min(max(cy, 0), g - 1)
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    if abs(dx) < 1e-12:
        t_x, d_x = BIG, BIG
    else:
        t_x = ((f32(cx + (1 if dx > 0 else 0)) * cell) - x) / dx
        d_x = cell / abs(dx)
    if abs(dy) < 1e-12:
        t_y, d_y = BIG, BIG
    else:
        t_y = ((f32(cy + (1 if dy > 0 else 0)) * cell) - y) / dy
        d_y = cell / abs(dy)
    for _ in range(2 * g + 2):
        if t_x < t_y:
            cx += step_x
            t = t_x
            t_x += d_x
        else:
            cy += step_y
            t = t_y
            t_y += d_y
        if cx < 0 or cy < 0 or cx >= g or cy >= g or walls[cy, cx]:
            return max(t, f32(0.0))
    return BIG


@njit(inline="always")
def cast_lidar(walls, x, y, theta, gx, gy, angles, cell, max_range, goal_radius, ranges, hits):
    for b in range(angles.shape[0]):
        a = theta + angles[b]
        dx, dy = f32(math.cos(a)), f32(math.sin(a))
        t_wall = cast_beam(walls, x, y, dx, dy, cell)
        fx, fy = gx - x, gy - y
        proj = fx * dx + fy * dy
        perp2 = fx * fx + fy * fy - proj * proj
        r2 = goal_radius * goal_radius
        t_goal = BIG
        if perp2 <= r2:
            half = f32(math.sqrt(max(r2 - perp2, f32(0.0))))
            if proj + half >= 0:
                t_goal = max(proj - half, f32(0.0))
        t = min(t_wall, t_goal)
        if t <= max_range:
            ranges[b] = t
            hits[b] = HIT_GOAL if t_goal < t_wall else HIT_WALL
        else:
            ranges[b] = max_range
            hits[b] = HIT_NONE


# --------------------------------------------------------------------------- episodes
@njit(inline="always")
def spawn(i, stream, rooms, free_cells, num_free, cell, radius, k, state_f, state_i, visited):
    """A fresh episode for env i: room, start pose, farthest of k goal candidates, heading."""
    g = rooms.shape[1]
    room = min(int(uniform(stream, 0) * rooms.shape[0]), rooms.shape[0] - 1)
    n_free = num_free[room]
    s = min(int(uniform(stream, 1) * n_free), n_free - 1)
    start = free_cells[room, s]
    slack = max(f32(0.5) * cell - radius, f32(0.0))
    x = (f32(start % g) + f32(0.5)) * cell + (f32(2.0) * uniform(stream, 2) - f32(1.0)) * slack
    y = (f32(start // g) + f32(0.5)) * cell + (f32(2.0) * uniform(stream, 3) - f32(1.0)) * slack
    best, bx, by = f32(-1.0), x, y
    for c in range(k):
        j = min(int(uniform(stream, 5 + c) * (n_free - 1)), n_free - 2)
        j += 1 if j >= s else 0
        cand = free_cells[room, j]
        cxy_x = (f32(cand % g) + f32(0.5)) * cell
        cxy_y = (f32(cand // g) + f32(0.5)) * cell
        d = (cxy_x - x) ** 2 + (cxy_y - y) ** 2
        if d > best:
            best, bx, by = d, cxy_x, cxy_y
    state_f[i, 0], state_f[i, 1] = x, y
    state_f[i, 2] = (f32(2.0) * uniform(stream, 4) - f32(1.0)) * f32(np.pi)
    state_f[i, 3], state_f[i, 4] = bx, by
    state_i[i, 0] = room
    state_i[i, 1] = start // g  # cell row
    state_i[i, 2] = start % g  # cell col
    state_i[i, 3] = 0  # cycle count
    state_i[i, 4] = 0  # time
    visited[i, :, :] = False
    visited[i, start // g, start % g] = True


@njit(parallel=True, fastmath=False)
def step_batch(actions, state_f, state_i, visited, rooms, free_cells, num_free, angles, params,
               ints, counter, obs, reward, done):  # fmt: skip
    """One step of every env (auto-reset), writing obs (N, obs_dim), reward (N,) and done (N,).

    state_f: (N, 5) x, y, theta, goal x, goal y; state_i: (N, 5) room, cell row, cell col, cycle
    count, time; params: float32 [room_size, radius, max_wheel_speed, wheel_base, dt, max_range,
    goal_radius, step_penalty, collision_penalty, cycle_penalty, progress_reward, goal_reward];
    ints: [max_steps, cycle_cap, goal_candidates, observe_goal]."""
    n, b = actions.shape[0], angles.shape[0]
    g = rooms.shape[1]
    room_size, radius, vmax, base, dt, max_range, goal_radius = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6])
    cell = room_size / f32(g)
    max_steps, cycle_cap, k, observe_goal = ints[0], ints[1], ints[2], ints[3]
    ranges = np.empty((n, b), np.float32)
    hits = np.empty((n, b), np.int32)
    for i in prange(n):
        walls = rooms[state_i[i, 0]]
        x0, y0, th = state_f[i, 0], state_f[i, 1], state_f[i, 2]
        gx, gy = state_f[i, 3], state_f[i, 4]
        a0, a1 = actions[i, 0], actions[i, 1]
        a0 = f32(0.0) if math.isnan(a0) else min(max(a0, f32(-1.0)), f32(1.0))
        a1 = f32(0.0) if math.isnan(a1) else min(max(a1, f32(-1.0)), f32(1.0))
        left, right = a0 * vmax, a1 * vmax
        v = f32(0.5) * (left + right)
        omega = (right - left) / base
        mid = th + f32(0.5) * omega * dt
        ddx, ddy = v * dt * f32(math.cos(mid)), v * dt * f32(math.sin(mid))
        th = f32((th + omega * dt + f32(np.pi)) % f32(2.0 * np.pi)) - f32(np.pi)
        collided = overlaps(walls, x0 + ddx, y0 + ddy, cell, radius)
        x, y = x0 + ddx, y0 + ddy
        if collided:
            ok_x = not overlaps(walls, x0 + ddx, y0, cell, radius)
            ok_y = not overlaps(walls, x0, y0 + ddy, cell, radius)
            if ok_x and ok_y:
                if abs(ddx) >= abs(ddy):
                    x, y = x0 + ddx, y0
                else:
                    x, y = x0, y0 + ddy
            elif ok_x:
                x, y = x0 + ddx, y0
            elif ok_y:
                x, y = x0, y0 + ddy
            else:
                x, y = x0, y0
        row = min(max(math.floor(y / cell), 0), g - 1)
        col = min(max(math.floor(x / cell), 0), g - 1)
        entered = row != state_i[i, 1] or col != state_i[i, 2]
        revisit = entered and visited[i, row, col]
        if revisit:
            state_i[i, 3] += 1
        visited[i, row, col] = True
        d_prev = f32(math.sqrt((gx - x0) ** 2 + (gy - y0) ** 2))
        d = f32(math.sqrt((gx - x) ** 2 + (gy - y) ** 2))
        reached = d <= goal_radius
        progress = f32(1.0) if d_prev > d else (f32(-1.0) if d_prev < d else f32(0.0))
        r = (-params[7] - (params[8] if collided else f32(0.0))
             - f32(min(state_i[i, 3], cycle_cap)) * params[9] + progress * params[10]
             + (params[11] if reached else f32(0.0)))  # fmt: skip
        t = state_i[i, 4] + 1
        ended = reached or t >= max_steps
        reward[i], done[i] = r, ended
        if ended:
            stream = fmix32(counter[0] ^ fmix32(np.uint32(counter[1]) * GOLDEN + np.uint32(i)))
            spawn(i, stream, rooms, free_cells, num_free, cell, radius, k, state_f, state_i,
                  visited)  # fmt: skip
            walls = rooms[state_i[i, 0]]
        else:
            state_f[i, 0], state_f[i, 1], state_f[i, 2] = x, y, th
            state_i[i, 1], state_i[i, 2], state_i[i, 4] = row, col, t
        x, y, th = state_f[i, 0], state_f[i, 1], state_f[i, 2]
        gx, gy = state_f[i, 3], state_f[i, 4]
        cast_lidar(walls, x, y, th, gx, gy, angles, cell, max_range, goal_radius, ranges[i],
                   hits[i])  # fmt: skip
        o = obs[i]
        o[0], o[1] = x / room_size, y / room_size
        o[2], o[3] = f32(math.sin(th)), f32(math.cos(th))
        for j in range(b):
            o[4 + j] = ranges[i, j] / max_range
            o[4 + b + j] = f32(1.0) if hits[i, j] == HIT_WALL else f32(0.0)
            o[4 + 2 * b + j] = f32(1.0) if hits[i, j] == HIT_GOAL else f32(0.0)
        if observe_goal:
            rx, ry = gx - x, gy - y
            dist = f32(math.sqrt(rx * rx + ry * ry))
            o[4 + 3 * b] = gx / room_size
            o[5 + 3 * b] = gy / room_size
            o[6 + 3 * b] = dist / room_size
            bearing = f32(math.atan2(ry, rx)) - th
            o[7 + 3 * b] = f32(math.sin(bearing)) if dist > 0 else f32(0.0)
            o[8 + 3 * b] = f32(math.cos(bearing)) if dist > 0 else f32(1.0)


@njit(parallel=True)
def lidar_only(walls, poses, goals, angles, cell, max_range, goal_radius, ranges, hits):
    """The lidar of many poses in one room (for the parity check against the twin)."""
    for i in prange(poses.shape[0]):
        cast_lidar(walls, poses[i, 0], poses[i, 1], poses[i, 2], goals[i, 0], goals[i, 1], angles,
                   cell, max_range, goal_radius, ranges[i], hits[i])  # fmt: skip


# --------------------------------------------------------------------------- driver
class NumbaBatch:
    """``num_envs`` envs of an EnvConfig stepped by ``step_batch`` (the paper's sign reward)."""

    def __init__(self, config, num_envs: int, seed: int = 0, split: str = "train"):
        from quicknav_core.env.constants import beam_angles
        from quicknav_core.env.room_sources import free_cell_table, make_room_bank

        c = config
        if c.reward.progress != "sign" or c.reward.exploration_reward:
            raise ValueError("the reference implements the paper's reward (progress='sign')")
        self.config, self.n = c, num_envs
        self.rooms = np.ascontiguousarray(make_room_bank(c, split))
        free, counts = free_cell_table(self.rooms)
        self.free_cells, self.num_free = np.asarray(free, np.int32), np.asarray(counts, np.int32)
        self.angles = np.asarray(beam_angles(c.lidar_beams, c.lidar_fov_deg), np.float32)
        r = c.reward
        self.params = np.array([c.room_size, c.robot_radius, c.max_wheel_speed, c.wheel_base, c.dt,
                                c.lidar_max_range, c.goal_radius, r.step_penalty,
                                r.collision_penalty, r.cycle_penalty, r.progress_reward,
                                r.goal_reward], np.float32)  # fmt: skip
        self.ints = np.array([c.max_steps, r.cycle_cap, c.goal_candidates, int(c.observe_goal)],
                             np.int64)  # fmt: skip
        self.state_f = np.zeros((num_envs, 5), np.float32)
        self.state_i = np.zeros((num_envs, 5), np.int32)
        g = c.grid_size
        self.visited = np.zeros((num_envs, g, g), np.bool_)
        self.obs = np.zeros((num_envs, c.obs_dim), np.float32)
        self.reward = np.zeros(num_envs, np.float32)
        self.done = np.zeros(num_envs, np.bool_)
        self.counter = np.array([fmix32_np(seed), 0], np.uint32)
        # every env starts as if its episode had just ended
        self.state_i[:, 4] = c.max_steps

    def step(self, actions: np.ndarray):
        step_batch(actions, self.state_f, self.state_i, self.visited, self.rooms, self.free_cells,
                   self.num_free, self.angles, self.params, self.ints, self.counter, self.obs,
                   self.reward, self.done)  # fmt: skip
        self.counter[1] += 1
        return self.obs, self.reward, self.done


def fmix32_np(x: int) -> np.uint32:
    return np.uint32(fmix32(np.uint32(x & 0xFFFFFFFF)))


def rate_numba(config, n: int, seconds: float, threads: int) -> float:
    numba.set_num_threads(threads)
    env = NumbaBatch(config, n)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (n, 2)).astype(np.float32) for _ in range(8)]
    for i in range(20):
        env.step(actions[i % 8])
    total, steps, t0 = 0.0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 50:
        obs, rew, done = env.step(actions[steps % 8])
        total += float(obs.sum()) + float(rew.sum())  # the whole observation is consumed
        steps += 1
    return n * steps / (time.perf_counter() - t0)


def rate_jax(grid: int, n: int, beams: int, seconds: float) -> float:
    from quicknav_core.bench.env import BenchConfig, bench_jax_scan

    steps = max(int(seconds * 1_000_000), n * 32)
    m = bench_jax_scan(grid, n, BenchConfig(grids=(grid,), batches=(n,), beams=beams, steps=steps))
    return m.steps_per_s


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--envs", type=int, default=4096)
    ap.add_argument("--grid", type=int, default=16)
    ap.add_argument("--beams", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/numba_env.json")
    args = ap.parse_args()
    from quicknav_core.bench.machine import machine_info
    from quicknav_core.config import EnvConfig

    config = EnvConfig(grid_size=args.grid, lidar_beams=args.beams)
    cores = numba.config.NUMBA_NUM_THREADS
    rates = {"numba_1_thread": rate_numba(config, args.envs, args.seconds, 1),
             f"numba_{cores}_threads": rate_numba(config, args.envs, args.seconds, cores),
             "jax": rate_jax(args.grid, args.envs, args.beams, args.seconds)}  # fmt: skip
    info = machine_info()
    print(f"grid {args.grid}, {args.envs} envs, {args.beams} beams, {info['cpu']}, {info['cores']} cores")
    for name, r in rates.items():
        print(f"  {name:<18} {r:>12,.0f} env steps/s")
    best = max(v for k, v in rates.items() if k.startswith("numba"))
    print(f"  JAX / compiled reference: {rates['jax'] / best:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": info, "envs": args.envs, "grid": args.grid,
                                    "beams": args.beams, "env_steps_per_s": rates,
                                    "jax_over_reference": rates["jax"] / best}, indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
