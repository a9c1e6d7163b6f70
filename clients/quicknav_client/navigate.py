"""Drive a mapped building with an exported policy that follows a global plan, without JAX.

The robot-side half of QuickNav's learned local planner: the global plan on the known map (a
shortest path on its occupancy grid, inflated by the robot's radius) and the policy that follows
it, fed a lidar scan and a pose in the map frame as tf2 (``map`` -> ``base_link``) gives it.

    from quicknav_client.navigate import Navigator

    nav = Navigator.load("policy")         # quicknav export RUN --map building.yaml --out policy
    nav.set_goal((12.0, 3.5))              # map frame, metres
    left, right = nav.act(scan, (x, y, yaw))   # wheel speeds, m/s; repeat at the control period

``quicknav export --map`` writes the map as the policy sees it (``map.npz``: its wall grid at the
policy's cell size) and the frame (``policy.json``'s ``map``): the map's origin, from its YAML,
and where the grid's corner lies in that frame. The planner is SciPy's Dijkstra
(``scipy.sparse.csgraph.dijkstra``) on the grid's 8-connected graph of the cells where the
robot's disc fits, a diagonal step only between two free orthogonal neighbours: the graph the
simulator plans on, so the waypoints are the ones the policy was trained with (where two paths are
equally short, the one it descends may differ).

Re-planning when blocked: the map does not show a closed door, a pallet across an aisle or a
crowd. When the plan's length left has not shrunk by a cell for ``replan_after_s`` seconds of
``act`` calls (one per control period), the Navigator marks the cells where the current scan
returns within ``mark_range_m`` as blocked and plans again on the map with them; the policy then
follows the new plan's waypoints. Marks last until the next goal; when the goal cannot be reached
with them, they are dropped and the map's own plan stays (``blocked_cells`` counts them,
``replans`` the re-plans made).

Safety layer (``shield=True``, ``quicknav_client.shield``): the policy's command is slowed where
its next pose would bring the robot within 1 cm of a scan return, down to turning in place, as
ROS 2 Navigation's collision monitor does; ``quicknav eval --shield`` measures the same rule.

Install: ``pip install 'quicknav-client[navigate]'`` (onnxruntime and SciPy).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from quicknav_client.policy import OnnxPolicy, finite_numbers, scan_arrays
from quicknav_client.shield import scan_in_robot_frame, shield_command

f32 = np.float32
MAP_FILE = "map.npz"
PATH_SCALE_M = 10.0  # the path left is observed as tanh(metres / PATH_SCALE_M), as in training
# 8 neighbours (d_row, d_col), orthogonal first: the order the simulator breaks ties in
NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))
UNREACHABLE = 1e9


def _shift(a: np.ndarray, dr: int, dc: int, fill: Any) -> np.ndarray:
    """out[r, c] = a[r + dr, c + dc] (``fill`` outside)."""
    out = np.full_like(a, fill)
    rows, cols = a.shape
    dst_r = slice(max(-dr, 0), rows - max(dr, 0))
    dst_c = slice(max(-dc, 0), cols - max(dc, 0))
    src_r = slice(max(dr, 0), rows - max(-dr, 0))
    src_c = slice(max(dc, 0), cols - max(-dc, 0))
    out[dst_r, dst_c] = a[src_r, src_c]
    return out


def disc_fits(walls: np.ndarray, cell: float, radius: float) -> np.ndarray:
    """(rows, cols) bool: free cells whose centre holds the robot's disc clear of every wall cell
    (the map inflated by the robot's radius)."""
    fits = ~walls
    if 2.0 * radius < cell:  # narrower than a cell: every free cell
        return fits
    reach = max(1, math.ceil(radius / cell))
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            gy, gx = max(abs(dy) - 0.5, 0.0), max(abs(dx) - 0.5, 0.0)
            if (gy * gy + gx * gx) * cell * cell < radius * radius:
                fits &= ~_shift(walls, dy, dx, True)
    return fits


class GridPlanner:
    """Shortest paths on a wall grid for a disc of ``robot_radius`` (SciPy's Dijkstra), and the
    plan's part of a policy's observation. Coordinates are the grid's own frame: x along columns,
    y along rows, (0, 0) the corner of cell (0, 0), metres."""

    def __init__(self, walls: np.ndarray, cell_m: float, robot_radius: float,
                 lookahead: int = 3, waypoints: int = 2):  # fmt: skip
        from scipy.sparse import csr_matrix

        self.walls = np.asarray(walls, bool)
        self.cell = float(cell_m)
        self.lookahead, self.count = int(lookahead), int(waypoints)
        self.usable = disc_fits(self.walls, self.cell, float(robot_radius))
        rows, cols = self.usable.shape
        index = np.arange(rows * cols).reshape(rows, cols)
        src, dst, cost = [], [], []
        for dr, dc in NEIGHBOURS:
            ok = self.usable & _shift(self.usable, dr, dc, False)
            if dr and dc:  # no corner cutting: both orthogonal neighbours free
                ok &= _shift(self.usable, dr, 0, False) & _shift(self.usable, 0, dc, False)
            r, c = np.nonzero(ok)
            src.append(index[r, c])
            dst.append(index[r + dr, c + dc])
            cost.append(np.full(r.size, math.sqrt(2.0) if dr and dc else 1.0))
        self.graph = csr_matrix((np.concatenate(cost), (np.concatenate(src), np.concatenate(dst))),
                                shape=(rows * cols, rows * cols))  # fmt: skip
        self.field: np.ndarray | None = None
        self.goal: np.ndarray | None = None

    def inside(self, x: float, y: float) -> bool:
        """Whether a point lies on the grid."""
        rows, cols = self.walls.shape
        return 0 <= math.floor(y / self.cell) < rows and 0 <= math.floor(x / self.cell) < cols

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of a point; ValueError outside the grid."""
        if not self.inside(x, y):
            rows, cols = self.walls.shape
            raise ValueError(f"({x:.2f}, {y:.2f}) m lies outside the map's grid"
                             f" ({cols * self.cell:g} m x {rows * self.cell:g} m)")  # fmt: skip
        return math.floor(y / self.cell), math.floor(x / self.cell)

    def fits(self, x: float, y: float) -> bool:
        """Whether the robot fits at a point of the grid (its cell is usable)."""
        return bool(self.usable[self.cell_of(x, y)])

    def plan(self, goal: Any) -> np.ndarray:
        """Plan to ``goal`` (x, y): the path length in cells from every cell to the goal's cell
        (``UNREACHABLE`` where none), kept for ``features``."""
        from scipy.sparse.csgraph import dijkstra

        gx, gy = float(goal[0]), float(goal[1])
        r, c = self.cell_of(gx, gy)
        if not self.fits(gx, gy):
            raise ValueError(f"goal ({gx:.2f}, {gy:.2f}) m: the robot does not fit there on the map"
                             " (a wall, or closer to one than the robot's radius)")  # fmt: skip
        rows, cols = self.walls.shape
        dist = dijkstra(self.graph, directed=True, indices=r * cols + c)  # edges both ways
        field = np.where(np.isfinite(dist), dist, UNREACHABLE).reshape(rows, cols)
        self.field, self.goal = field.astype(f32), np.asarray([gx, gy], f32)
        return self.field

    def path(self, rc: tuple[int, int], steps: int) -> np.ndarray:
        """(steps, 2) cells (row, col) down the field from ``rc``, never up (ties: the first
        neighbour in ``NEIGHBOURS``), staying put at the goal."""
        field, usable = self.field, self.usable
        rows, cols = field.shape
        r, c = rc
        out = np.zeros((steps, 2), np.int64)
        for i in range(steps):
            best, br, bc = field[r, c], r, c
            for dr, dc in NEIGHBOURS:
                rr, cc = min(max(r + dr, 0), rows - 1), min(max(c + dc, 0), cols - 1)
                ok = usable[rr, cc]
                if dr and dc:
                    ok = ok and usable[rr, c] and usable[r, cc]
                if ok and field[rr, cc] < best:
                    best, br, bc = field[rr, cc], rr, cc
            r, c = br, bc
            out[i] = (r, c)
        return out

    def waypoints(self, x: float, y: float) -> np.ndarray:
        """(waypoints, 2) x, y: the cell centres ``i * lookahead`` steps down the plan from the
        robot's cell, the goal itself once the path reaches the goal's cell."""
        if self.field is None:
            raise ValueError("no goal: call plan(goal) first")
        nodes = self.path(self.cell_of(x, y), self.lookahead * self.count)
        picked = nodes[self.lookahead - 1 :: self.lookahead]
        centres = (picked[:, ::-1].astype(f32) + f32(0.5)) * f32(self.cell)
        at_goal = self.field[picked[:, 0], picked[:, 1]] <= 0.0
        return np.where(at_goal[:, None], self.goal[None, :], centres).astype(f32)

    def features(self, pose: Any) -> np.ndarray:
        """The plan's part of the observation at ``pose`` (x, y, theta): per waypoint (forward,
        left) in the robot's frame over the farthest it can lie, then tanh(path left / 10 m)."""
        x, y, theta = (float(v) for v in pose)
        points = self.waypoints(x, y)
        rel = points - np.asarray([x, y], f32)[None, :]
        c, s = f32(math.cos(theta)), f32(math.sin(theta))
        fwd, left = c * rel[:, 0] + s * rel[:, 1], c * rel[:, 1] - s * rel[:, 0]
        reach = (np.arange(1, self.count + 1, dtype=f32) * f32(self.lookahead) + f32(1.0)) \
            * f32(math.sqrt(2.0)) * f32(self.cell)  # fmt: skip
        xy = np.clip(np.stack([fwd, left], axis=-1) / reach[:, None], -1.0, 1.0).reshape(-1)
        r, col = self.cell_of(x, y)
        left_m = f32(min(float(self.field[r, col]), 1e6)) * f32(self.cell)
        return np.concatenate([xy, [np.tanh(left_m / f32(PATH_SCALE_M))]]).astype(f32)

    def path_length_m(self, x: float, y: float) -> float:
        """The plan's length from the robot's cell to the goal's, metres (inf: no path)."""
        d = float(self.field[self.cell_of(x, y)])
        return math.inf if d >= UNREACHABLE else d * self.cell


def scan_points(scan: Any, beam_angles: np.ndarray, pose: Any, beyond: float = 0.0) -> np.ndarray:
    """(n, 2) x, y of a scan's valid returns for a robot at ``pose`` (x, y, yaw), each pushed
    ``beyond`` metres further along its beam (into what it hit). A plain array of ranges is read
    at the policy's beams (``beam_angles``); a LaserScan at its own angles."""
    ranges, angles, ok = scan_arrays(scan, np.asarray(beam_angles))
    x, y, yaw = (float(v) for v in pose)
    r, a = ranges[ok] + beyond, angles[ok] + yaw
    return np.stack([x + r * np.cos(a), y + r * np.sin(a)], axis=-1)


class Navigator:
    """An exported plan-following policy on its map: ``set_goal`` once per goal, then ``act``
    with every scan, once per control period. Poses and goals are in the map frame (the YAML's
    ``origin`` frame, as tf2 and RViz give them); a pose off the map is an error, never an action.

    ``replan_after_s`` (None: never) and ``mark_range_m``: re-planning when blocked; ``shield``:
    the safety layer (the module's doc)."""

    def __init__(self, policy: OnnxPolicy, walls: np.ndarray, frame: dict[str, Any],
                 replan_after_s: float | None = 5.0, mark_range_m: float = 3.0,
                 shield: bool = False):  # fmt: skip
        m = policy.manifest
        env = m["env"]
        if not env.get("observe_plan"):
            raise ValueError("this policy does not follow a plan (env.observe_plan false): drive it"
                             " with OnnxPolicy.act(scan, pose, goal) in its room's frame")  # fmt: skip
        if replan_after_s is not None and not replan_after_s > 0:
            raise ValueError(f"replan_after_s={replan_after_s}: allowed: > 0 seconds, or None (never)")
        if not mark_range_m > 0:
            raise ValueError(f"mark_range_m={mark_range_m}: allowed: > 0 metres")
        self.policy = policy
        self.frame = frame
        self.corner = np.asarray(frame["grid_corner_in_map"], np.float64)  # grid (0, 0) in the map frame
        self.walls = np.asarray(walls, bool)
        self._planner_args = (float(frame["cell_m"]), float(env["robot_radius"]),
                              int(env["plan_lookahead"]), int(env["plan_waypoints"]))  # fmt: skip
        self.planner = GridPlanner(self.walls, *self._planner_args)
        self.goal_grid: np.ndarray | None = None
        self.period_s = float(env["dt"])
        self.replan_after_s, self.mark_range_m = replan_after_s, float(mark_range_m)
        self.blocked = np.zeros_like(self.walls)
        self.replans = 0
        self._best_left, self._stalled = math.inf, 0
        self.shield = bool(shield)
        self.shielded = 0  # act calls whose command the safety layer changed

    @property
    def blocked_cells(self) -> int:
        """Cells the Navigator marked blocked for this goal (none: the map's own plan)."""
        return int(self.blocked.sum())

    @classmethod
    def load(cls, folder: str | Path, replan_after_s: float | None = 5.0,
             mark_range_m: float = 3.0, shield: bool = False) -> Navigator:  # fmt: skip
        """The policy and the map ``quicknav export RUN --map MAP --out FOLDER`` wrote."""
        folder = Path(folder)
        policy = OnnxPolicy.load(folder)
        frame = policy.manifest.get("map")
        if not frame or not (folder / frame.get("file", MAP_FILE)).is_file():
            raise ValueError(f"{folder}: no map exported with this policy; run `quicknav export RUN"
                             " --map YOUR_MAP.yaml --out FOLDER` to add one")  # fmt: skip
        with np.load(folder / frame.get("file", MAP_FILE)) as data:
            walls = np.asarray(data["walls"], bool)
        return cls(policy, walls, frame, replan_after_s, mark_range_m, shield)

    def to_grid(self, x: float, y: float) -> tuple[float, float]:
        """A map-frame point in the planner's grid frame."""
        return x - float(self.corner[0]), y - float(self.corner[1])

    def _on_map(self, what: str, x: float, y: float) -> tuple[float, float]:
        """A map-frame point in the grid frame; ValueError naming it in the map frame, and the
        map's extent there, when it lies outside the map's grid."""
        gx, gy = self.to_grid(x, y)
        if not self.planner.inside(gx, gy):
            rows, cols = self.walls.shape
            cell = self.planner.cell
            x0, y0 = (float(v) for v in self.corner)
            hint = ("check the localisation (map -> base_link)" if what == "pose" else
                    "a goal is given in the map frame, as RViz's 2D Goal Pose gives it")  # fmt: skip
            raise ValueError(f"{what} ({x:.2f}, {y:.2f}) m lies outside the map: its grid spans x"
                             f" {x0:g} to {x0 + cols * cell:g} m and y {y0:g} to {y0 + rows * cell:g} m"
                             f" in the map frame (the YAML's origin frame); {hint}")  # fmt: skip
        return gx, gy

    def set_goal(self, goal: Any) -> None:
        """A new goal (x, y) in the map frame: plan to it on the map (marks of the last goal
        dropped) and start a new episode."""
        x, y = finite_numbers(goal, "goal", 2, "(x, y) in the map frame, metres")
        gx, gy = self._on_map("goal", x, y)
        planner = self.planner if not self.blocked.any() else GridPlanner(self.walls, *self._planner_args)
        if not planner.fits(gx, gy):
            raise ValueError(f"goal ({x:.2f}, {y:.2f}) m in the map frame: the robot does not fit"
                             " there on the map (a wall, or closer to one than the robot's radius)")  # fmt: skip
        planner.plan((gx, gy))
        self.planner, self.blocked = planner, np.zeros_like(self.walls)
        self.goal_grid = np.asarray([gx, gy], f32)
        self.replans, self._best_left, self._stalled = 0, math.inf, 0
        self.policy.reset()

    def observation(self, scan: Any, pose: Any) -> np.ndarray:
        """The policy's observation for a scan and a map-frame pose (x, y, yaw)."""
        if self.goal_grid is None:
            raise ValueError("no goal: call set_goal((x, y)) first")
        x, y, yaw = finite_numbers(pose, "pose", 3, "(x, y, yaw) in the map frame: metres and radians")
        gx, gy = self._on_map("pose", x, y)
        r, c = self.planner.cell_of(gx, gy)
        if self.walls[r, c]:
            raise ValueError(f"pose ({x:.2f}, {y:.2f}) m lies in a wall cell of the map: check the"
                             " localisation (map -> base_link)")  # fmt: skip
        grid_pose = (gx, gy, yaw)
        return self.policy.observation(scan, grid_pose, self.goal_grid, self.planner.features(grid_pose))

    def act(self, scan: Any, pose: Any) -> tuple[float, float]:
        """(left, right) wheel speeds in m/s for this step (re-planning first if blocked)."""
        obs = self.observation(scan, pose)
        if self.replan_after_s is not None:
            gx, gy = self.to_grid(float(pose[0]), float(pose[1]))
            left = self.planner.path_length_m(gx, gy)
            if left <= self._best_left - self.planner.cell:  # a cell nearer: progress
                self._best_left, self._stalled = left, 0
            else:
                self._stalled += 1
            if self._stalled * self.period_s >= self.replan_after_s:
                self._stalled = 0
                if self.replan(scan, pose):
                    self._best_left = self.planner.path_length_m(gx, gy)
                    obs = self.observation(scan, pose)
        left, right = self.policy.act_on(obs)
        if not self.shield:
            return left, right
        return self.shielded_command(scan, left, right)

    def shielded_command(self, scan: Any, left: float, right: float) -> tuple[float, float]:
        """Wheel speeds (m/s) through the safety layer (``quicknav_client.shield``) for this scan."""
        env = self.policy.manifest["env"]
        top = float(env["max_wheel_speed"])
        angles = np.asarray(self.policy.manifest["lidar"]["beam_angles_rad"], np.float64)
        points = scan_in_robot_frame(*scan_arrays(scan, angles))
        let = shield_command((left / top, right / top), points, radius=float(env["robot_radius"]),
                             max_wheel_speed=top, wheel_base=float(env["wheel_base"]),
                             dt=self.period_s)  # fmt: skip
        self.shielded += let != (left / top, right / top)
        return let[0] * top, let[1] * top

    def replan(self, scan: Any, pose: Any) -> bool:
        """Mark the scan's returns within ``mark_range_m`` as blocked (never the robot's or the
        goal's cell) and plan again on the map with every mark so far; True if the plan changed
        the marks (a plan that cannot reach the goal with them drops them all: False)."""
        if self.goal_grid is None:
            raise ValueError("no goal: call set_goal((x, y)) first")
        gx, gy = self.to_grid(float(pose[0]), float(pose[1]))
        cell = self.planner.cell
        angles = np.asarray(self.policy.manifest["lidar"]["beam_angles_rad"], np.float64)
        # a tenth of a cell past the return: a hit on a cell's edge marks the cell it hit
        points = scan_points(scan, angles, (gx, gy, float(pose[2])), beyond=0.1 * cell)
        near = np.hypot(points[:, 0] - gx, points[:, 1] - gy) <= self.mark_range_m
        rows, cols = self.walls.shape
        rc = np.floor(points[near][:, ::-1] / cell).astype(np.int64)
        rc = rc[(rc[:, 0] >= 0) & (rc[:, 0] < rows) & (rc[:, 1] >= 0) & (rc[:, 1] < cols)]
        marks = self.blocked.copy()
        marks[rc[:, 0], rc[:, 1]] = True
        marks &= ~self.walls
        for x, y in ((gx, gy), (float(self.goal_grid[0]), float(self.goal_grid[1]))):
            marks[self.planner.cell_of(x, y)] = False
        if (marks == self.blocked).all():
            return False
        # a robot wider than a cell: marks at its side close its own cell on the inflated grid,
        # so if every mark walls it in, try again without those within its radius and a cell
        centres_r, centres_c = np.nonzero(marks)
        gap = np.hypot((centres_c + 0.5) * cell - gx, (centres_r + 0.5) * cell - gy)
        side = np.zeros_like(marks)
        side[centres_r, centres_c] = gap <= self._planner_args[1] + cell
        planner = None
        for tried in (marks, marks & ~side) if side.any() else (marks,):
            candidate = GridPlanner(self.walls | tried, *self._planner_args)
            try:
                candidate.plan(self.goal_grid)
                if not math.isinf(candidate.path_length_m(gx, gy)):
                    planner, marks = candidate, tried
                    break
            except ValueError:  # the goal closed by the marks (a robot wider than a cell)
                pass
        if planner is None:  # the marks leave no way to the goal: the map's plan, marks dropped
            if self.blocked.any():
                self.planner = GridPlanner(self.walls, *self._planner_args)
                self.planner.plan(self.goal_grid)
            self.blocked = np.zeros_like(self.walls)
            return False
        self.planner, self.blocked = planner, marks
        self.replans += 1
        return True

    def reached(self, pose: Any) -> bool:
        """Whether ``pose`` is within the trained goal radius of the goal."""
        x, y = self.to_grid(float(pose[0]), float(pose[1]))
        radius = float(self.policy.manifest["env"]["goal_radius"])
        return math.hypot(x - float(self.goal_grid[0]), y - float(self.goal_grid[1])) <= radius

