"""The NumPy twin of QuickNav: same semantics as the JAX env, written in NumPy alone (no JAX import).

It exists to prove the JAX env's semantics (parity tests) and as the honest baseline of the
throughput benchmark: one env, stepped from Python, vectorised NumPy inside a step (no per-cell
Python loops). It computes in float32 so it tracks the JAX env step for step.

It is a ``gymnasium.Env`` (no auto-reset): ``reset`` returns ``(obs, info)``, ``step`` returns
``(obs, reward, terminated, truncated, info)``. ``load(walls, pos, theta, goal)`` (or
``reset(options={"walls": ..., "pos": ..., "theta": ..., "goal": ...})``) puts it in a given room,
pose and goal, e.g. one taken from the JAX env.

With ``EnvConfig.randomize`` each reset draws the episode's perturbation from the twin's own RNG;
``load(..., perturbation=state.perturbation)`` takes the JAX env's draws instead, and the per-step
lidar noise, a counter hash of the episode's seed and the step re-implemented here, is then the JAX
env's to float32 rounding.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any, ClassVar

import gymnasium as gym
import numpy as np

from quicknav_core.env.carving import carve_room_np  # noqa: F401 (the twin's carver, as before)
from quicknav_core.env.clearance import disc_fits, reach_cells, spawn_region
from quicknav_core.env.constants import (
    BIG,
    HIT_GOAL,
    HIT_NONE,
    HIT_WALL,
    LATENCY_MAX_STEPS,
    OBSTACLE_ABSENT,
    OBSTACLE_WORDS,
    PATH_SCALE_M,
    beam_angles,
    check_split,
    observation_bounds,
)
from quicknav_core.env.plan_np import NEIGHBOURS, greedy_path_np, plan_polyline_np  # noqa: F401 (the twin's)

if TYPE_CHECKING:  # pragma: no cover - the twin reads its config's fields, never imports it
    from quicknav_core.config.env import EnvConfig
    from quicknav_core.env.room_sources import RoomSource
    from quicknav_core.runtime import Runtime

f32 = np.float32
_BIG = f32(BIG)
_INF = f32(1e9)  # env.plan.INF


def _shift_np(a: np.ndarray, dr: int, dc: int, fill) -> np.ndarray:
    """out[r, c] = a[r + dr, c + dc] (``fill`` outside)."""
    padded = np.pad(a, 1, constant_values=fill)
    n, m = a.shape
    return padded[1 + dr:1 + dr + n, 1 + dc:1 + dc + m]


def _moves_np(usable: np.ndarray) -> list[tuple[int, int, np.ndarray, np.float32]]:
    out = []
    for dr, dc in NEIGHBOURS:
        ok = usable & _shift_np(usable, dr, dc, False)
        if dr and dc:  # no corner cutting
            ok = ok & _shift_np(usable, dr, 0, False) & _shift_np(usable, 0, dc, False)
        out.append((dr, dc, ok, f32(np.sqrt(2.0)) if dr and dc else f32(1.0)))
    return out


def cell_field_np(usable: np.ndarray, goal_rc) -> np.ndarray:
    """``env.plan.cell_field`` in NumPy: the same relaxations in the same order, so the same
    float32 distances (cells to the goal's cell; >= 1e9 where unreachable)."""
    d = np.full(usable.shape, _INF, f32)
    d[goal_rc[0], goal_rc[1]] = f32(0.0)
    d = np.where(usable, d, _INF).astype(f32)
    moves = _moves_np(usable)
    while True:
        best = d
        for dr, dc, ok, w in moves:
            best = np.minimum(best, np.where(ok, (_shift_np(d, dr, dc, _INF) + w).astype(f32), _INF))
        if not np.any(best < d):
            return best
        d = best


def plan_waypoints_np(field, usable, rc, goal, cell, lookahead: int, count: int) -> np.ndarray:
    """``env.plan.plan_waypoints`` in NumPy."""
    nodes = greedy_path_np(field, usable, rc, lookahead * count)
    picked = nodes[lookahead - 1::lookahead]
    centres = (picked[:, ::-1].astype(f32) + f32(0.5)) * f32(cell)
    at_goal = field[picked[:, 0], picked[:, 1]] <= 0.0
    return np.where(at_goal[:, None], np.asarray(goal, f32)[None, :], centres).astype(f32)


def plan_features_np(pos, theta, waypoints, field, rc, cell, lookahead: int) -> np.ndarray:
    """``env.plan.plan_features`` in NumPy."""
    count = waypoints.shape[0]
    rel = (waypoints - np.asarray(pos, f32)[None, :]).astype(f32)
    c, s = f32(np.cos(theta)), f32(np.sin(theta))
    fwd = c * rel[:, 0] + s * rel[:, 1]
    left = c * rel[:, 1] - s * rel[:, 0]
    reach = ((np.arange(1, count + 1, dtype=f32) * f32(lookahead) + f32(1.0)) * f32(np.sqrt(2.0))
             * f32(cell)).astype(f32)  # fmt: skip
    points = np.clip(np.stack([fwd, left], axis=-1) / reach[:, None], -1.0, 1.0).reshape(-1)
    left_m = f32(min(float(field[rc[0], rc[1]]), 1e6)) * f32(cell)
    return np.concatenate([points, [np.tanh(left_m / f32(PATH_SCALE_M))]]).astype(f32)


def cast_lidar_np(
    pos: np.ndarray,
    theta: float,
    goal: np.ndarray,
    walls: np.ndarray,
    angles: np.ndarray,
    cell: float,
    max_range: float,
    goal_radius: float,
) -> tuple[np.ndarray, np.ndarray]:
    """All beams at once over every grid-line crossing, vectorised. (ranges f32 (B,), hits int32)."""
    rows, cols = walls.shape
    cell = f32(cell)
    # the heading rotated by each beam's offset, as the JAX env computes it
    ca, sa = np.cos(angles.astype(np.float64)).astype(f32), np.sin(angles.astype(np.float64)).astype(f32)
    ct, st = f32(np.cos(f32(theta))), f32(np.sin(f32(theta)))
    dx, dy = (ct * ca - st * sa).astype(f32), (st * ca + ct * sa).astype(f32)
    def nearest(o_a, o_b, d_a, d_b, vertical):
        # vertical lines x = k * cell (k < cols), crossed at a row; horizontal ones y = k * cell
        lines, across = (cols, rows) if vertical else (rows, cols)
        k = np.arange(1, lines, dtype=f32)
        d_safe = np.where(np.abs(d_a) < 1e-12, f32(1e-12), d_a).astype(f32)
        t = ((k[None, :] * cell - o_a) * (f32(1.0) / d_safe)[:, None]).astype(f32)
        forward = d_a[:, None] > 0
        line = np.where(forward, k.astype(np.int64)[None, :], k.astype(np.int64)[None, :] - 1)
        b = (o_b + t * d_b[:, None]).astype(f32)
        other = np.clip(np.floor(b / cell).astype(np.int64), 0, across - 1)
        is_wall = walls[other, line] if vertical else walls[line, other]
        hit = is_wall & (t >= 0)
        return np.where(hit, t, _BIG).min(axis=1)

    t_wall = np.minimum(
        nearest(pos[0], pos[1], dx, dy, vertical=True),
        nearest(pos[1], pos[0], dy, dx, vertical=False),
    )
    fx, fy = f32(goal[0] - pos[0]), f32(goal[1] - pos[1])
    proj = fx * dx + fy * dy
    perp2 = fx * fx + fy * fy - proj * proj
    r2 = f32(goal_radius) * f32(goal_radius)
    half = np.sqrt(np.maximum(r2 - perp2, f32(0.0)))
    meets = (perp2 <= r2) & (proj + half >= 0)
    t_goal = np.where(meets, np.maximum(proj - half, f32(0.0)), _BIG)
    t = np.minimum(t_wall, t_goal)
    in_range = t <= f32(max_range)
    hits = np.where(in_range, np.where(t_goal < t_wall, HIT_GOAL, HIT_WALL), HIT_NONE)
    ranges = np.where(in_range, t, f32(max_range)).astype(f32)
    return ranges, hits.astype(np.int32)


_MASK32 = 0xFFFFFFFF
_GOLDEN = 0x9E3779B9


def _fmix32_np(x: np.ndarray) -> np.ndarray:
    """MurmurHash3's 32-bit finaliser on uint32 words (computed in uint64, kept to 32 bits)."""
    x = np.asarray(x, np.uint64) & _MASK32
    x ^= x >> 16
    x = (x * 0x85EBCA6B) & _MASK32
    x ^= x >> 13
    x = (x * 0xC2B2AE35) & _MASK32
    return x ^ (x >> 16)


def scan_uniforms_np(seed: int, time: int, beams: int) -> np.ndarray:
    """(3, beams) float32 uniforms of the scan at step ``time`` of the episode seeded ``seed``."""
    word = _fmix32_np(np.uint64(seed) ^ _fmix32_np((np.uint64(time) * _GOLDEN + 0x2545F491) & _MASK32))
    counter = np.arange(3 * beams, dtype=np.uint64)
    bits = _fmix32_np(word ^ _fmix32_np((counter * _GOLDEN + 0x632BE5AB) & _MASK32))
    one_to_two = ((bits >> 9) | 0x3F800000).astype(np.uint32).view(np.float32)
    return (one_to_two - f32(1.0)).reshape(3, beams)


def perturb_scan_np(
    p: dict, time: int, ranges: np.ndarray, hits: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """Noise, bias and dropout on a scan (``EnvConfig.randomize``), as ``env.perturb`` does."""
    u = scan_uniforms_np(int(p["noise_seed"]), time, ranges.shape[0])
    radius = np.sqrt(f32(-2.0) * np.log(f32(1.0) - u[0]))
    angle = f32(2.0 * np.pi) * u[1]
    z_frac, z_add = radius * np.cos(angle), radius * np.sin(angle)
    noisy = (ranges * (f32(1.0) + f32(p["lidar_noise_frac"]) * z_frac)
             + f32(p["lidar_noise_m"]) * z_add + f32(p["lidar_bias_m"])).astype(f32)  # fmt: skip
    max_range = f32(max_range)
    returned = (hits != HIT_NONE) & (u[2] >= f32(p["beam_dropout"])) & (noisy <= max_range)
    return (np.where(returned, np.maximum(noisy, f32(0.0)), max_range).astype(f32),
            np.where(returned, hits, HIT_NONE).astype(np.int32))  # fmt: skip


def disc_overlaps_wall_np(pos: np.ndarray, walls: np.ndarray, cell: float, radius: float) -> bool:
    """Whether a disc at ``pos`` overlaps a wall; only the cells within ``reach_cells`` of its own
    can (the 3x3 around it for a robot narrower than a cell)."""
    rows, cols = walls.shape
    cell = f32(cell)
    k = reach_cells(float(radius), float(cell))
    n_r, n_c = min(2 * k + 1, rows), min(2 * k + 1, cols)
    row, col = (np.floor(pos[::-1] / cell)).astype(np.int64)
    r0, c0 = int(np.clip(row - k, 0, rows - n_r)), int(np.clip(col - k, 0, cols - n_c))
    block = walls[r0 : r0 + n_r, c0 : c0 + n_c]
    y0 = (np.arange(r0, r0 + n_r).astype(f32) * cell).astype(f32)
    x0 = (np.arange(c0, c0 + n_c).astype(f32) * cell).astype(f32)
    gap_y = np.maximum(np.maximum(y0 - pos[1], pos[1] - (y0 + cell)), f32(0.0))
    gap_x = np.maximum(np.maximum(x0 - pos[0], pos[0] - (x0 + cell)), f32(0.0))
    dist2 = gap_y[:, None] ** 2 + gap_x[None, :] ** 2
    return bool(np.any(block & (dist2 < f32(radius) * f32(radius))))


def place_obstacles_np(u: np.ndarray, config, free_cells: np.ndarray, walls: np.ndarray, cell,
                       start: np.ndarray, goal: np.ndarray) -> dict[str, np.ndarray]:  # fmt: skip
    """``env.obstacles.place`` in NumPy from (N, OBSTACLE_WORDS) uniforms in [0, 1)."""
    o = config.obstacles
    n, (rows, cols) = o.count, walls.shape
    f = free_cells[np.minimum(np.floor(u[:, 0] * free_cells.size).astype(np.int64), free_cells.size - 1)]
    r, c = f // cols, f % cols
    opened = np.ones(n, bool)
    for dr, dc in NEIGHBOURS:
        opened &= ~walls[np.clip(r + dr, 0, rows - 1), np.clip(c + dc, 0, cols - 1)]
    moving = np.arange(n) >= o.static
    lo = np.where(moving, o.moving_radius_m[0], o.static_radius_m[0]).astype(f32)
    hi = np.where(moving, o.moving_radius_m[1], o.static_radius_m[1]).astype(f32)
    radius = (lo + u[:, 1].astype(f32) * (hi - lo)).astype(f32)
    pos = ((np.stack([c, r], axis=-1).astype(f32) + f32(0.5)) * f32(cell)).astype(f32)
    keep = radius + f32(o.clearance_m)
    present = opened & (np.linalg.norm(pos - start[None, :], axis=-1) >= keep) & (
        np.linalg.norm(pos - goal[None, :], axis=-1) >= keep)  # fmt: skip
    angle = u[:, 2].astype(f32) * f32(2.0 * np.pi)
    speed = np.where(moving, f32(o.speed_mps[0]) + u[:, 3].astype(f32) * f32(o.speed_mps[1] - o.speed_mps[0]), 0.0)
    vel = (np.stack([np.cos(angle), np.sin(angle)], axis=-1) * speed[:, None]).astype(f32)
    return {"pos": np.where(present[:, None], pos, f32(OBSTACLE_ABSENT)).astype(f32),
            "vel": np.where(present[:, None], vel, f32(0.0)).astype(f32),
            "radius": np.where(present, radius, f32(0.0)).astype(f32)}  # fmt: skip


def obstacle_rays_np(pos, dx, dy, obstacles: dict[str, np.ndarray]) -> np.ndarray:
    """``env.obstacles.ray_distances`` in NumPy."""
    p, rad = obstacles["pos"], obstacles["radius"]
    fx = (p[:, 0][None, :] - pos[0]).astype(f32)
    fy = (p[:, 1][None, :] - pos[1]).astype(f32)
    proj = fx * dx[:, None] + fy * dy[:, None]
    perp2 = fx * fx + fy * fy - proj * proj
    r2 = (rad * rad)[None, :]
    half = np.sqrt(np.maximum(r2 - perp2, f32(0.0)))
    meets = (rad[None, :] > 0) & (perp2 <= r2) & (proj + half >= 0)
    return np.where(meets, np.maximum(proj - half, f32(0.0)), _BIG).min(axis=-1).astype(f32)


class QuickNavNumpyEnv(gym.Env):
    """One QuickNav env in NumPy. Same observation, action, reward and episode rules as the JAX env."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        config: EnvConfig,
        split: str = "train",
        render_mode: str | None = None,
        rooms: np.ndarray | RoomSource | None = None,
        runtime: Runtime | None = None,
    ):
        from quicknav_core.env.room_sources import RoomSource, room_source

        self.config = config
        self.split = check_split(split)
        self.render_mode = render_mode
        low, high = observation_bounds(self.config)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        c = self.config
        self._cell = f32(c.room_size / c.grid_size)
        self._spawn_radius = c.spawn_radius
        self._reach = c.collision_reach
        self._angles = beam_angles(c.lidar_beams, c.lidar_fov_deg)
        self._rooms: dict[int, np.ndarray] = {}
        self._bank_size = self.config.train_rooms if split == "train" else self.config.test_rooms
        self._source: RoomSource | None = None
        if isinstance(rooms, RoomSource):
            self._source = rooms
        elif rooms is not None:
            # a given bank (e.g. the JAX env's ``params.rooms``): reset picks from these rooms
            rooms = np.asarray(rooms, dtype=bool)
            rows, cols = self.config.grid_shape
            if rooms.ndim != 3 or rooms.shape[1:] != (rows, cols):
                raise ValueError(f"rooms has shape {rooms.shape}; expected (n, {rows}, {cols})")
            self._rooms = dict(enumerate(rooms))
            self._bank_size = len(rooms)
        else:  # the config's room source (carved rooms: carved here with NumPy, room by room)
            self._source = room_source(c, runtime)
        self._state: dict[str, Any] | None = None

    # ---------------------------------------------------------------- rooms
    def room(self, index: int) -> np.ndarray:
        """Room ``index`` of the bank: a given one, or its source's (built on first use)."""
        if index not in self._rooms:
            self._rooms[index] = self._source.twin_room(self.split, index)
        return self._rooms[index]

    # ---------------------------------------------------------------- gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options and "walls" in options:
            obs = self.load(options["walls"], options["pos"], options["theta"], options["goal"],
                            options.get("perturbation"), options.get("obstacles"))  # fmt: skip
            return obs, {}
        c = self.config
        rng = self.np_random
        walls = self.room(int(rng.integers(self._bank_size)))
        g = c.grid_shape[1]  # flat cell indices: row * cols + col
        # where the disc fits and can drive (every free cell for a robot narrower than a cell)
        free = np.flatnonzero(spawn_region(walls, float(self._cell), self._spawn_radius).reshape(-1))
        s = int(rng.integers(free.size))
        start = free[s]
        perturbation = self._draw_perturbation(rng)
        radius = c.robot_radius if perturbation is None else float(perturbation["robot_radius"])
        slack = max(0.5 * float(self._cell) - radius, 0.0)
        pos = (np.array([start % g, start // g], f32) + f32(0.5)) * self._cell
        pos = pos + rng.uniform(-1.0, 1.0, 2).astype(f32) * f32(slack)
        others = np.delete(free, s)
        cand = others[rng.integers(others.size, size=c.goal_candidates)]
        cand_xy = (np.stack([cand % g, cand // g], axis=-1).astype(f32) + f32(0.5)) * self._cell
        goal = cand_xy[np.argmax(((cand_xy - pos) ** 2).sum(axis=-1))]
        theta = rng.uniform(-np.pi, np.pi)
        obstacles = None
        if c.obstacle_counts:  # by env.obstacles' rules, from this twin's own random numbers
            u = rng.random((c.obstacles.count, OBSTACLE_WORDS))
            obstacles = place_obstacles_np(u, c, free, walls, self._cell, pos, goal)
        return self.load(walls, pos, theta, goal, perturbation, obstacles), {}

    def _draw_perturbation(self, rng: np.random.Generator) -> dict[str, Any] | None:
        """This episode's randomisation draws (None when the config is not randomised)."""
        r = self.config.randomize
        if r is None:
            return None
        radius = r.robot_radius_m or (self.config.robot_radius,) * 2
        lat = r.latency_steps
        return {
            "noise_seed": int(rng.integers(2**32)),
            "lidar_noise_m": f32(rng.uniform(*r.lidar_noise_m)),
            "lidar_noise_frac": f32(rng.uniform(*r.lidar_noise_frac)),
            "lidar_bias_m": f32(rng.uniform(*r.lidar_bias_m)),
            "beam_dropout": f32(rng.uniform(*r.beam_dropout)),
            "wheel_scale": np.array(
                [rng.uniform(*r.wheel_scale_left), rng.uniform(*r.wheel_scale_right)], f32
            ),
            "latency_steps": int(rng.integers(lat[0], lat[1] + 1)),
            "robot_radius": f32(rng.uniform(*radius)),
            "past_commands": np.zeros((LATENCY_MAX_STEPS, 2), f32),
        }

    def _obstacles(self, given: Any) -> dict[str, np.ndarray] | None:
        """Obstacles as the twin keeps them, from a dict or the JAX env's ``Obstacles``."""
        c = self.config
        if not c.obstacle_counts:
            if given is not None:
                raise ValueError("obstacles given, but this env has none (EnvConfig.obstacles)")
            return None
        n = c.obstacles.count
        if given is None:
            return {"pos": np.full((n, 2), OBSTACLE_ABSENT, f32), "vel": np.zeros((n, 2), f32),
                    "radius": np.zeros(n, f32)}  # fmt: skip
        get = given.get if isinstance(given, dict) else lambda k: getattr(given, k)
        return {"pos": np.array(get("pos"), f32).reshape(n, 2),
                "vel": np.array(get("vel"), f32).reshape(n, 2),
                "radius": np.array(get("radius"), f32).reshape(n)}  # fmt: skip

    def _perturbation(self, given: Any) -> dict[str, Any] | None:
        """A perturbation as the twin keeps it, from a dict or the JAX env's ``Perturbation``."""
        if self.config.randomize is None:
            if given is not None:
                raise ValueError("perturbation given, but this env is not randomised (EnvConfig.randomize)")
            return None
        if given is None:  # one that changes nothing
            given = {"noise_seed": 0, "lidar_noise_m": 0.0, "lidar_noise_frac": 0.0,
                     "lidar_bias_m": 0.0, "beam_dropout": 0.0, "wheel_scale": (1.0, 1.0),
                     "latency_steps": 0, "robot_radius": self.config.robot_radius}  # fmt: skip
        get = given.get if isinstance(given, dict) else lambda k, d=None: getattr(given, k, d)
        queue = get("past_commands")
        return {
            "noise_seed": int(np.asarray(get("noise_seed"))),
            "lidar_noise_m": f32(get("lidar_noise_m")),
            "lidar_noise_frac": f32(get("lidar_noise_frac")),
            "lidar_bias_m": f32(get("lidar_bias_m")),
            "beam_dropout": f32(get("beam_dropout")),
            "wheel_scale": np.asarray(get("wheel_scale"), f32).reshape(2),
            "latency_steps": int(np.asarray(get("latency_steps"))),
            "robot_radius": f32(get("robot_radius")),
            "past_commands": (np.zeros((LATENCY_MAX_STEPS, 2), f32) if queue is None
                              else np.array(queue, f32).reshape(LATENCY_MAX_STEPS, 2)),
        }  # fmt: skip

    def load(self, walls, pos, theta, goal, perturbation: Any = None, obstacles: Any = None
             ) -> np.ndarray:  # fmt: skip
        """Start an episode in a given room, pose and goal; returns the first observation.

        A randomised twin takes the episode's ``perturbation`` too: a dict or the JAX env's
        ``state.perturbation`` (default: one that changes nothing); a twin with obstacles takes the
        episode's ``obstacles`` (a dict of pos, vel, radius or the JAX env's ``state.obstacles``;
        default: none present)."""
        walls = np.asarray(walls, dtype=bool)
        shape = self.config.grid_shape
        if walls.shape != shape:
            raise ValueError(f"walls has shape {walls.shape}; expected {shape} for grid_size="
                             f"{self.config.grid_size}" + ("" if shape[0] == shape[1] else
                             f", grid_rows={shape[0]}, grid_cols={shape[1]}"))  # fmt: skip
        pos = np.asarray(pos, f32).reshape(2)
        cell = (np.floor(pos[::-1] / self._cell)).astype(np.int64)
        visited = np.zeros(shape, bool)
        visited[cell[0], cell[1]] = True
        self._state = {
            "walls": walls,
            "pos": pos,
            "theta": f32(theta),
            "goal": np.asarray(goal, f32).reshape(2),
            "visited": visited,
            "cell": cell,
            "cycle_count": 0,
            "collisions": 0,
            "time": 0,
            "perturbation": self._perturbation(perturbation),
            "obstacles": self._obstacles(obstacles),
        }
        if self.config.observe_plan:  # the episode's global plan on the known map
            goal_rc = self._cell_of(self._state["goal"])
            self._state["plan"] = cell_field_np(self._usable(), goal_rc)
        self._cast()
        return self._obs()

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() (or load()) before step()")
        c, s = self.config, self._state
        a = np.asarray(action, f32).reshape(2)
        a = np.clip(np.where(np.isnan(a), f32(0.0), a), f32(-1.0), f32(1.0)).astype(f32)
        p = s["perturbation"]
        if p is not None:  # the wheels act on the command of latency_steps ago, each at its scale
            queue, lat = p["past_commands"], p["latency_steps"]
            acting = queue[lat - 1] if lat > 0 else a
            p["past_commands"] = np.concatenate([a[None], queue[:-1]]).astype(f32)
            a = (acting * p["wheel_scale"]).astype(f32)
        vmax, base, dt = f32(c.max_wheel_speed), f32(c.wheel_base), f32(c.dt)
        left, right = a[0] * vmax, a[1] * vmax
        v = f32(0.5) * (left + right)
        omega = (right - left) / base
        mid = f32(s["theta"] + f32(0.5) * omega * dt)
        delta = np.array([v * dt * np.cos(mid), v * dt * np.sin(mid)], f32)
        theta = f32(np.mod(s["theta"] + omega * dt + f32(np.pi), f32(2.0 * np.pi)) - f32(np.pi))

        pos0 = s["pos"]
        full = (pos0 + delta).astype(f32)
        collided = self._overlaps(full)
        if collided:
            only_x = np.array([pos0[0] + delta[0], pos0[1]], f32)
            only_y = np.array([pos0[0], pos0[1] + delta[1]], f32)
            ok_x, ok_y = not self._overlaps(only_x), not self._overlaps(only_y)
            if ok_x and ok_y:
                pos = only_x if abs(delta[0]) >= abs(delta[1]) else only_y
            elif ok_x:
                pos = only_x
            elif ok_y:
                pos = only_y
            else:
                pos = pos0
        else:
            pos = full
        obstacles = s["obstacles"]
        if obstacles is not None:  # env.obstacles: no move into a disc, then the people walk
            radius = c.robot_radius if p is None else float(p["robot_radius"])
            gap = np.linalg.norm(obstacles["pos"] - pos[None, :], axis=-1)
            if np.any((obstacles["radius"] > 0) & (gap < f32(radius) + obstacles["radius"])):
                pos, collided = pos0, True
            self._walk(obstacles, pos, radius)

        cell = self._cell_of(pos)
        entered = bool(np.any(cell != s["cell"]))
        seen = bool(s["visited"][cell[0], cell[1]])
        revisit = entered and seen
        new_cell = entered and not seen
        s["cycle_count"] += int(revisit)
        s["visited"][cell[0], cell[1]] = True
        dist_prev = f32(np.linalg.norm(s["goal"] - pos0))
        dist = f32(np.linalg.norm(s["goal"] - pos))
        goal_reached = bool(dist <= f32(c.goal_radius))
        r = c.reward
        if r.progress == "path":  # the planned path's decrease (env.reward)
            path_prev = self._path_left(pos0)
            path = path_prev if np.all(pos == pos0) else self._path_left(pos)
            after = f32(0.0) if goal_reached else path
            progress = (path_prev - after) / (vmax * dt)
        elif r.progress == "linear":
            progress = (dist_prev - dist) / (vmax * dt)
        elif r.progress == "potential":
            after = f32(0.0) if goal_reached else dist
            progress = (dist_prev - f32(r.potential_gamma) * after) / f32(vmax * dt)
        else:
            progress = np.sign(dist_prev - dist)
        terms = {
            "step": -f32(r.step_penalty),
            "collision": -f32(collided) * f32(r.collision_penalty),
            "cycle": -f32(min(s["cycle_count"], r.cycle_cap)) * f32(r.cycle_penalty),
            "progress": f32(progress) * f32(r.progress_reward),
            "goal": f32(goal_reached) * f32(r.goal_reward),
            "exploration": f32(new_cell) * f32(r.exploration_reward),
            "proximity": -f32(np.clip(f32(1.0) - self._clearance(pos) / f32(r.proximity_m), 0.0, 1.0))
            * f32(r.proximity_penalty),
        }
        total = f32(
            terms["step"] + terms["collision"] + terms["cycle"] + terms["progress"] + terms["goal"]
        )
        reward = f32(total + terms["exploration"] + terms["proximity"])
        s.update(
            pos=pos,
            theta=theta,
            cell=cell,
            collisions=s["collisions"] + int(collided),
            time=s["time"] + 1,
        )
        self._cast()
        terminated = goal_reached or (collided and c.end_on_collision)
        truncated = (s["time"] >= c.max_steps) and not terminated
        info = {
            "goal_reached": goal_reached,
            "collision": collided,
            "revisit": revisit,
            "reward_terms": terms,
        }
        return self._obs(), float(reward), terminated, truncated, info

    def render(self):
        from quicknav_core.env.render import render_frame

        return render_frame(self.snapshot(), self.config)

    # ---------------------------------------------------------------- helpers
    def snapshot(self) -> dict[str, Any]:
        """A copy of the current state (walls, pos, theta, goal, lidar, counters)."""
        if self._state is None:
            raise RuntimeError("call reset() (or load()) before snapshot()")
        return copy.deepcopy(self._state)

    def _overlaps(self, pos: np.ndarray) -> bool:
        p = self._state["perturbation"]
        radius = self.config.robot_radius if p is None else p["robot_radius"]
        return disc_overlaps_wall_np(pos, self._state["walls"], self._cell, radius)

    def _walk(self, obstacles: dict[str, np.ndarray], robot: np.ndarray, robot_radius: float) -> None:
        """``env.obstacles.move``: each person walks on, or turns back (and stays) where it would
        overlap a wall or the robot."""
        dt = f32(self.config.dt)
        for i in range(obstacles["radius"].size):
            v = obstacles["vel"][i]
            if not np.any(v != 0):
                continue
            nxt = (obstacles["pos"][i] + v * dt).astype(f32)
            rad = float(obstacles["radius"][i])
            blocked = disc_overlaps_wall_np(nxt, self._state["walls"], self._cell, rad) or bool(
                np.linalg.norm(nxt - robot) < f32(rad) + f32(robot_radius))  # fmt: skip
            if blocked:
                obstacles["vel"][i] = -v
            else:
                obstacles["pos"][i] = nxt

    def _cast(self) -> None:
        s, c = self._state, self.config
        s["lidar_ranges"], s["lidar_hits"] = cast_lidar_np(
            s["pos"], s["theta"], s["goal"], s["walls"], self._angles, self._cell,
            c.lidar_max_range, c.goal_radius,
        )  # fmt: skip
        if s["obstacles"] is not None:  # the discs the map does not show, seen as walls
            ca = np.cos(self._angles.astype(np.float64)).astype(f32)
            sa = np.sin(self._angles.astype(np.float64)).astype(f32)
            ct, st = f32(np.cos(f32(s["theta"]))), f32(np.sin(f32(s["theta"])))
            dx, dy = (ct * ca - st * sa).astype(f32), (st * ca + ct * sa).astype(f32)
            t_obs = obstacle_rays_np(s["pos"], dx, dy, s["obstacles"])
            nearest = np.where(s["lidar_hits"] == HIT_NONE, _BIG, s["lidar_ranges"])
            closer = (t_obs < nearest) & (t_obs <= f32(c.lidar_max_range))
            s["lidar_ranges"] = np.where(closer, t_obs, s["lidar_ranges"]).astype(f32)
            s["lidar_hits"] = np.where(closer, HIT_WALL, s["lidar_hits"]).astype(np.int32)
        if s["perturbation"] is not None:
            s["lidar_ranges"], s["lidar_hits"] = perturb_scan_np(
                s["perturbation"], s["time"], s["lidar_ranges"], s["lidar_hits"], c.lidar_max_range
            )

    def _clearance(self, pos: np.ndarray) -> np.float32:
        """Metres from the robot's edge to the nearest wall (of the 3x3 cells around it) or obstacle."""
        s, (n_rows, n_cols), cell = self._state, self.config.grid_shape, self._cell
        rc = np.floor(pos[::-1] / cell).astype(np.int64)
        rows = np.clip(rc[0] + np.array([-1, 0, 1]), 0, n_rows - 1)
        cols = np.clip(rc[1] + np.array([-1, 0, 1]), 0, n_cols - 1)
        y0, x0 = (rows.astype(f32) * cell).astype(f32), (cols.astype(f32) * cell).astype(f32)
        gy = np.maximum(np.maximum(y0 - pos[1], pos[1] - (y0 + cell)), f32(0.0))
        gx = np.maximum(np.maximum(x0 - pos[0], pos[0] - (x0 + cell)), f32(0.0))
        dist = np.sqrt(gy[:, None] ** 2 + gx[None, :] ** 2).astype(f32)
        near = f32(np.min(np.where(s["walls"][np.ix_(rows, cols)], dist, cell)))
        ob = s["obstacles"]
        if ob is not None and np.any(ob["radius"] > 0):
            gaps = np.linalg.norm(ob["pos"] - pos[None, :], axis=-1).astype(f32) - ob["radius"]
            near = min(near, f32(np.min(np.where(ob["radius"] > 0, gaps, _BIG))))
        p = s["perturbation"]
        radius = self.config.robot_radius if p is None else float(p["robot_radius"])
        return f32(near - f32(radius))

    def _path_left(self, pos: np.ndarray) -> np.float32:
        """``env.plan.path_length_from`` on the plan at cell resolution: metres to the goal."""
        s, (n_rows, n_cols) = self._state, self.config.grid_shape
        metres = (s["plan"] * self._cell).astype(f32)
        rc = np.floor(pos[::-1] / self._cell).astype(np.int64)
        rows = np.repeat(np.clip(rc[0] + np.array([-1, 0, 1]), 0, n_rows - 1), 3)
        cols = np.tile(np.clip(rc[1] + np.array([-1, 0, 1]), 0, n_cols - 1), 3)
        centres = ((np.stack([cols, rows], axis=-1).astype(f32) + f32(0.5)) * self._cell).astype(f32)
        return f32(np.min(np.linalg.norm(centres - pos, axis=-1).astype(f32) + metres[rows, cols]))

    def _cell_of(self, pos: np.ndarray) -> np.ndarray:
        """(row, col) of the cell holding ``pos``, clipped to the grid."""
        rc = np.floor(pos[::-1] / self._cell).astype(np.int64)
        return np.clip(rc, 0, np.asarray(self.config.grid_shape) - 1)

    def _usable(self) -> np.ndarray:
        s = self._state
        p = s["perturbation"]
        radius = self.config.robot_radius if p is None else float(p["robot_radius"])
        return disc_fits(s["walls"], float(self._cell), radius) if self._reach else ~s["walls"]

    def _obs(self) -> np.ndarray:
        s, c = self._state, self.config
        room = f32(c.room_size)
        parts = [s["pos"] / room, [np.sin(s["theta"]), np.cos(s["theta"])]] if c.observe_pose else []
        parts += [
            s["lidar_ranges"] / f32(c.lidar_max_range),
            (s["lidar_hits"] == HIT_WALL).astype(f32),
            (s["lidar_hits"] == HIT_GOAL).astype(f32),
        ]
        if c.observe_goal:
            rel = s["goal"] - s["pos"]
            dist = f32(np.sqrt(np.sum(rel * rel)))
            bearing = f32(np.arctan2(rel[1], rel[0]) - s["theta"])
            sin_b, cos_b = (np.sin(bearing), np.cos(bearing)) if dist > 0 else (0.0, 1.0)
            parts += [s["goal"] / room, [dist / room], [sin_b], [cos_b]]
        if c.observe_plan:
            usable = self._usable()
            points = plan_waypoints_np(s["plan"], usable, s["cell"], s["goal"], self._cell,
                                       c.plan_lookahead, c.plan_waypoints)  # fmt: skip
            parts.append(plan_features_np(s["pos"], s["theta"], points, s["plan"], s["cell"],
                                          self._cell, c.plan_lookahead))  # fmt: skip
        return np.concatenate([np.asarray(p, f32) for p in parts]).astype(f32)
