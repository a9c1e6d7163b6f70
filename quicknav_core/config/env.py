"""The environment's configuration: ``EnvConfig`` (room, robot, lidar, task) and its ``RewardConfig``.

Every field is validated on construction; a bad value raises ``pydantic.ValidationError`` whose
message names the field and the allowed range. Fields that change array shapes (``grid_size``,
``lidar_beams``, ``observe_goal``, bank sizes) are fixed when the environment is built; every other
number ends up in the traced ``EnvParams`` pytree and can be vmapped without recompiling.

Rooms are carved by a random walk (``quicknav_core.env.rooms``); ``carver`` says how: the paper's
walk from the centre (``paper``, bit for bit as before; ``centre``, the same walk drawn in blocks),
or returns to carved cells (``carved``) that reach across large grids. ``auto`` picks by the
walk's estimated length (``env.carving``), and a config whose walk would not meet its carve target
within ``carve_max_steps`` is refused with the ways out.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

from pydantic import Field, model_validator

from quicknav_core.config.base import (
    STATIC,
    TRACED,
    Flag,
    Split,
    StrictModel,
    static_fields,
    traced,
)
from quicknav_core.env.constants import LATENCY_MAX_STEPS

if TYPE_CHECKING:  # pragma: no cover - import only for type checkers, keeps this module JAX-free
    from quicknav_core.env.quicknav import QuickNavEnv
    from quicknav_core.env.types import EnvParams
    from quicknav_core.runtime import Runtime


class RewardConfig(StrictModel):
    """Reward weights of the paper's formula.

    r_t = -step_penalty - 1[collision]*collision_penalty - min(C_t, cycle_cap)*cycle_penalty
          + progress_term + 1[goal reached]*goal_reward + 1[new cell]*exploration_reward
          - max(0, 1 - clearance/proximity_m)*proximity_penalty
    with progress_term = sign(d_{t-1} - d_t) * progress_reward (``progress="sign"``) or
    progress_reward * (d_{t-1} - d_t) / (max_wheel_speed * dt) (``progress="linear"``) or
    progress_reward * (d_{t-1} - potential_gamma * d'_t) / (max_wheel_speed * dt) with d'_t = 0 at
    the goal (``progress="potential"``: potential-based shaping with Φ = -distance, which leaves the
    optimal policy that of the sparse goal reward: circling near the goal earns nothing).

    The same optimal policy is not the same learning problem. The shaping term's discounted sum
    telescopes to γ^T Φ(s_T) - Φ(s_0), so what pulls an agent to the goal is γ^T·goal_reward against
    the penalties, a thin margin at short discounts, while the paper's sign term pays every step of
    progress (by hand, γ 0.96, the paper-lstm weights, a straight 8 m drive at full speed: reaching
    the goal beats standing still by 2.3 under shaping and by 13.0 under the sign term). PPO with an
    LSTM or GTrXL settled on standing still under shaping, even with the goal observed; PPO with an
    MLP or the memory MLP learned at the same γ (``benchmarks/results/shaped_memory.json``,
    ``benchmarks/results/learning/report.md``).
    """

    step_penalty: float = Field(
        0.1, ge=0.0, le=1000.0, description="λs, paid every step", json_schema_extra=TRACED
    )
    collision_penalty: float = Field(
        10.0, ge=0.0, le=1000.0, description="λw, per wall collision", json_schema_extra=TRACED
    )
    cycle_penalty: float = Field(
        0.0, ge=0.0, le=1000.0, description="λc, times min(C_t, cycle_cap)", json_schema_extra=TRACED
    )
    progress_reward: float = Field(
        1.0, ge=0.0, le=1000.0, description="λp, progress towards goal", json_schema_extra=TRACED
    )
    goal_reward: float = Field(
        50.0, ge=0.0, le=10000.0, description="λg, on reaching the goal", json_schema_extra=TRACED
    )
    cycle_cap: int = Field(
        10, ge=0, le=1_000_000, description="cap on the revisit count C_t", json_schema_extra=TRACED
    )
    exploration_reward: float = Field(
        0.0,
        ge=0.0,
        le=1000.0,
        description="λe, paid on entering a cell not yet visited this episode (0 = the paper's formula)",
        json_schema_extra=TRACED,
    )
    proximity_penalty: float = Field(
        0.0, ge=0.0, le=1000.0, description="λn, times how far the nearest wall or obstacle is"
        " inside proximity_m of the robot's edge (0 to 1 as it closes in; 0 = the paper's formula)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    proximity_m: float = Field(
        0.2, gt=0.0, le=100.0, description="the distance from the robot's edge within which"
        " proximity_penalty grows, metres", json_schema_extra=TRACED,
    )  # fmt: skip
    progress: Literal["sign", "linear", "potential", "path"] = Field(
        "sign", description="shape of the progress term: the paper's sign, a scaled distance"
        " difference, potential-based shaping (its optimal policy is the unshaped one's), or the"
        " scaled decrease of the planned path's length to the goal ('path': needs observe_plan)",
        json_schema_extra=traced("progress_mode"),
    )
    potential_gamma: float = Field(
        0.99, ge=0.0, le=1.0, description="γ of the potential shaping (use the trainer's discount)",
        json_schema_extra=TRACED,
    )


def _pair(kind: type, lo: float, hi: float) -> type:
    """A ``[low, high]`` range whose ends lie in ``[lo, hi]`` (the order is checked by the model)."""
    end = Annotated[kind, Field(ge=lo, le=hi)]
    return tuple[end, end]  # type: ignore[valid-type]


# EnvConfig.grid_size: cells per side (map_fit.MAX_GRID and `quicknav bench --grid` read it)
GRID_SIZE_RANGE = (4, 256)
NoiseMetres = _pair(float, 0.0, 1.0)
NoiseFraction = _pair(float, 0.0, 0.5)
BiasMetres = _pair(float, -1.0, 1.0)
Probability = _pair(float, 0.0, 0.99)
WheelScale = _pair(float, 0.5, 1.5)
LatencySteps = _pair(int, 0, LATENCY_MAX_STEPS)
RadiusMetres = _pair(float, 0.001, 100.0)


class RandomizeConfig(StrictModel):
    """Sensor and actuator randomisation: each field is a ``[low, high]`` range, and every env draws
    one value uniformly from each range at the start of every episode (the two wheels separately).

    The ranges are traced numbers (``EnvParams.randomize``): changing them never recompiles, and
    ``[x, x]`` fixes a perturbation at ``x`` (what ``quicknav eval --robustness`` does level by
    level). The defaults perturb nothing; a config without ``randomize`` (the default) runs the
    plain env, and every figure measured on it stays as it was.

    What each does to a step (``env.perturb``; the NumPy twin does the same with the same draws):
    a beam that returned reports ``range * (1 + lidar_noise_frac * z1) + lidar_noise_m * z2 +
    lidar_bias_m``, clipped to ``[0, lidar_max_range]`` (at the cap: no return), with z1, z2
    standard normal per beam per step; with probability ``beam_dropout`` a beam reports no return
    (range = max, hit type none), as a real lidar reports inf. The wheels turn at the commanded
    speed times their scale (a robot that pulls to one side), ``latency_steps`` steps after the
    command (the queue starts at rest), and the disc has a radius drawn from ``robot_radius_m``
    (``None``: the env's ``robot_radius``).
    """

    lidar_noise_m: NoiseMetres = Field(
        (0.0, 0.0), description="std of additive Gaussian range noise, metres (0..1)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    lidar_noise_frac: NoiseFraction = Field(
        (0.0, 0.0), description="std of range noise proportional to the range (0..0.5; 0.05 = 5 %)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    lidar_bias_m: BiasMetres = Field(
        (0.0, 0.0), description="constant range offset for the episode, metres (-1..1)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    beam_dropout: Probability = Field(
        (0.0, 0.0), description="chance per beam per step of no return (0..0.99)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    wheel_scale_left: WheelScale = Field(
        (1.0, 1.0), description="left wheel speed / commanded speed (0.5..1.5)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    wheel_scale_right: WheelScale = Field(
        (1.0, 1.0), description="right wheel speed / commanded speed (0.5..1.5)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    latency_steps: LatencySteps = Field(
        (0, 0), description=f"steps between a command and the wheels turning (0..{LATENCY_MAX_STEPS})",
        json_schema_extra=TRACED,
    )  # fmt: skip
    robot_radius_m: RadiusMetres | None = Field(
        None, description="robot disc radius range, metres (None: the env's robot_radius); the"
        " largest must stay under half a cell", json_schema_extra=TRACED,
    )  # fmt: skip

    @model_validator(mode="after")
    def _ordered(self) -> RandomizeConfig:
        for name in type(self).model_fields:
            pair = getattr(self, name)
            if pair is not None and pair[0] > pair[1]:
                raise ValueError(
                    f"{name}=[{pair[0]:g}, {pair[1]:g}]: a range is [low, high]; allowed: low <= high"
                )
        return self

    @property
    def wheel_scale_max(self) -> float:
        """The fastest a wheel turns, as a multiple of its command."""
        return max(self.wheel_scale_left[1], self.wheel_scale_right[1])


Count = Annotated[int, Field(ge=0, le=64)]
ObstacleRadius = _pair(float, 0.01, 10.0)
Speed = _pair(float, 0.0, 10.0)


class ObstaclesConfig(StrictModel):
    """Obstacles the map does not show (``env.obstacles``): static boxes and moving people placed
    in open free space at every episode start, seen only by the lidar. Counts fix shapes; the
    ranges are traced numbers (``EnvParams.obstacles``). Off (None) for the paper's presets."""

    static: Count = Field(0, description="static obstacles (boxes, furniture) per episode, at most"
                          " (0..64; one whose drawn cell is not open is left out)",
                          json_schema_extra=STATIC)  # fmt: skip
    moving: Count = Field(0, description="moving obstacles (people) per episode, at most (0..64)",
                          json_schema_extra=STATIC)  # fmt: skip
    static_radius_m: ObstacleRadius = Field(
        (0.12, 0.22), description="radius range of static ones, metres (below half a cell)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    moving_radius_m: ObstacleRadius = Field(
        (0.18, 0.22), description="radius range of people, metres (below half a cell)",
        json_schema_extra=TRACED,
    )  # fmt: skip
    speed_mps: Speed = Field((0.2, 0.6), description="walking speed range of people, m/s",
                             json_schema_extra=TRACED)  # fmt: skip
    clearance_m: float = Field(0.6, ge=0.0, le=100.0, description="no obstacle within this of"
                               " the start or the goal (beyond its radius), metres",
                               json_schema_extra=TRACED)  # fmt: skip

    @model_validator(mode="after")
    def _ordered(self) -> ObstaclesConfig:
        for name in ("static_radius_m", "moving_radius_m", "speed_mps"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name}=[{lo:g}, {hi:g}]: a range is [low, high]; allowed: low <= high")
        return self

    @property
    def count(self) -> int:
        return self.static + self.moving


class FloorplanConfig(StrictModel):
    """Generated floor plans (``env.rooms='floorplan'``, ``quicknav_core.env.floorplan``): rooms cut
    by one-cell walls, joined by doors, off a corridor. Sizes in cells."""

    min_room: int = Field(4, ge=1, le=64, description="smallest room side, cells")
    max_room: int = Field(
        12, ge=1, le=128,
        description="rooms up to this side may stay uncut (the chance grows as they shrink), cells",
    )  # fmt: skip
    door_width: int = Field(1, ge=1, le=16, description="door width, cells")
    door_width_max: int | None = Field(
        None, ge=1, le=16, description="doors from door_width up to this many cells wide, mixed in"
        " each plan (None: every door door_width wide)",
    )  # fmt: skip
    corridor_width: int = Field(
        1, ge=0, le=16, description="width of the corridor made by the first cut, cells (0: a wall)"
    )
    loop_prob: float = Field(
        0.1, ge=0.0, le=1.0,
        description="chance of a second door between two rooms already joined (a way round)",
    )  # fmt: skip

    @model_validator(mode="after")
    def _sizes(self) -> FloorplanConfig:
        if self.max_room < self.min_room:
            raise ValueError(f"max_room={self.max_room} < min_room={self.min_room}; allowed range"
                             f" max_room >= min_room")  # fmt: skip
        if self.door_width_max is not None and self.door_width_max < self.door_width:
            raise ValueError(f"door_width_max={self.door_width_max} < door_width={self.door_width};"
                             " allowed range door_width_max >= door_width")  # fmt: skip
        return self


class MapsConfig(StrictModel):
    """Maps of buildings as rooms (``env.rooms='maps'``, ``quicknav_core.env.maps``)."""

    train: list[str] = Field(
        min_length=1, max_length=256,
        description="map files: ROS map_server .yaml (with its .pgm) or .png/.pgm images",
    )  # fmt: skip
    test: list[str] | None = Field(
        None, min_length=1, max_length=256,
        description="held-out map files (None: the train maps, evaluated on held-out episodes)",
    )  # fmt: skip
    resolution: float | None = Field(
        None, gt=0.0, le=100.0, description="metres per pixel of plain images (a .yaml names its own)"
    )
    unknown: Literal["wall", "free"] = Field("wall", description="how unknown pixels count")
    occupied_thresh: float = Field(0.65, gt=0.0, le=1.0, description="plain images: occupied above")
    free_thresh: float = Field(0.196, ge=0.0, lt=1.0, description="plain images: free below")
    negate: bool = Field(False, description="plain images: white is occupied")

    def load_options(self) -> dict[str, Any]:
        """How a map file is read (``env.maps.load_map``'s keywords)."""
        return {"resolution": self.resolution, "occupied_thresh": self.occupied_thresh,
                "free_thresh": self.free_thresh, "negate": self.negate,
                "unknown_free": self.unknown == "free"}  # fmt: skip

    def reading(self) -> dict[str, Any]:
        """The fields that say how a map is read (all but the map lists)."""
        return self.model_dump(mode="json", exclude={"train", "test"})


class EnvConfig(StrictModel):
    """Everything that defines a QuickNav environment. ``build(split)`` returns ``(env, params)``."""

    # Room and procedural generation
    rooms: Literal["carved", "floorplan", "maps"] = Field(
        "carved",
        description="where rooms come from: 'carved' (random-walk caves, the paper's), 'floorplan'"
        " (generated rooms, doors and a corridor: env.floorplan) or 'maps' (building maps: env.maps)",
    )
    floorplan: FloorplanConfig = Field(
        default_factory=FloorplanConfig, description="the floor-plan generator (rooms='floorplan')"
    )
    maps: MapsConfig | None = Field(None, description="the map files (rooms='maps')")
    room_size: float = Field(
        8.0, gt=0.0, le=1000.0, description="side of the square room, metres (of a non-square one, its longer side)", json_schema_extra=TRACED
    )
    grid_size: int = Field(
        16, ge=GRID_SIZE_RANGE[0], le=GRID_SIZE_RANGE[1], description="cells per side (outer ring is wall); of a non-square room (grid_rows, grid_cols), its longer side", json_schema_extra=STATIC
    )
    grid_rows: int | None = Field(
        None, ge=GRID_SIZE_RANGE[0], le=GRID_SIZE_RANGE[1], json_schema_extra=STATIC,
        description="cells along y of a non-square room (rooms='maps': a map's grid follows its"
        " shape); None: grid_size. One of grid_rows and grid_cols is grid_size, the other at most",
    )
    grid_cols: int | None = Field(
        None, ge=GRID_SIZE_RANGE[0], le=GRID_SIZE_RANGE[1], json_schema_extra=STATIC,
        description="cells along x of a non-square room; None: grid_size (see grid_rows)",
    )
    carve_fraction: float = Field(
        0.8, gt=0.0, le=1.0, description="fraction of inner cells carved free"
    )
    return_prob: float = Field(
        0.05, ge=0.0, lt=1.0, description="chance per carving step to jump back to the centre"
    )
    carve_max_steps: int | None = Field(
        None, ge=1, le=100_000_000, description="carving step cap; None = 1000 x inner cells"
    )
    carver: Literal["auto", "paper", "centre", "carved"] = Field(
        "auto",
        description="how the carving walk runs (env.rooms): 'paper' returns to the centre with one"
        " PRNG key per step (the rooms of generator version 1, bit for bit); 'centre' the same walk"
        " with random numbers drawn a block of steps at a time (same look, other rooms, ~4x"
        " faster); 'carved' returns to a random carved cell instead of the centre (reaches the"
        " far cells of large grids); 'auto' picks paper while a room needs few steps, else centre"
        " while that stays cheap, else carved",
    )
    room_seed: int = Field(0, ge=0, le=2**31 - 1, description="seed of the room banks")
    train_rooms: int = Field(1024, ge=1, le=1_000_000, description="rooms in the train bank")
    test_rooms: int = Field(256, ge=1, le=1_000_000, description="rooms in the held-out test bank")

    # Robot
    robot_radius: float = Field(
        0.15, gt=0.0, le=100.0, description="robot disc radius, metres", json_schema_extra=TRACED
    )
    max_wheel_speed: float = Field(
        1.0, gt=0.0, le=100.0, description="wheel speed at |action|=1, m/s", json_schema_extra=TRACED
    )
    wheel_base: float = Field(
        0.3, gt=0.0, le=100.0, description="distance between wheels, metres", json_schema_extra=TRACED
    )
    dt: float = Field(
        0.1, gt=0.0, le=10.0, description="control period, seconds", json_schema_extra=TRACED
    )

    # Lidar
    lidar_beams: int = Field(
        16, ge=1, le=1024, description="number of lidar beams", json_schema_extra=STATIC
    )
    lidar_fov_deg: float = Field(
        360.0, gt=0.0, le=360.0, description="lidar field of view, degrees", json_schema_extra=STATIC
    )
    lidar_max_range: float = Field(
        10.0, gt=0.0, le=10000.0, description="lidar range cap, metres", json_schema_extra=TRACED
    )
    lidar_method: Literal["auto", "crossings", "dda"] = Field(
        "auto",
        description="how beams are cast (same results): 'crossings' (all line crossings at once,"
        " bit-packed walls), 'dda' (a cell walk per beam); 'auto' picks the faster for the backend",
        json_schema_extra=STATIC,
    )

    # Task
    goal_candidates: int = Field(
        5, ge=1, le=64, description="random free cells drawn; the farthest becomes the goal",
        json_schema_extra=STATIC,
    )
    goal_radius: float = Field(
        0.3, gt=0.0, le=100.0, description="goal disc radius, metres", json_schema_extra=TRACED
    )
    max_steps: int = Field(
        300, ge=1, le=1_000_000, description="episode truncation limit",
        json_schema_extra=traced("max_steps_in_episode"),
    )
    observe_goal: Flag = Field(
        True, description="include goal position/distance/bearing in obs", json_schema_extra=STATIC
    )
    observe_pose: Flag = Field(
        True, description="include the robot's position and heading in the room frame in obs"
        " (a policy meant for buildings it never saw leaves them out: they are the room's frame,"
        " not the robot's)", json_schema_extra=STATIC,
    )  # fmt: skip
    observe_plan: Flag = Field(
        False, description="include the global plan in obs: the next waypoints of the shortest"
        " path on the known map to the goal, in the robot's frame, and the path's length left"
        " (the env plans at every episode start; see docs: a learned local planner)",
        json_schema_extra=STATIC,
    )  # fmt: skip
    plan_lookahead: int = Field(
        3, ge=1, le=64, description="cells along the planned path between waypoints (the"
        " waypoint i is i * plan_lookahead cells ahead)", json_schema_extra=STATIC,
    )  # fmt: skip
    plan_waypoints: int = Field(
        2, ge=1, le=8, description="waypoints observed (observe_plan)", json_schema_extra=STATIC
    )
    end_on_collision: Flag = Field(
        False, description="a collision (touching a wall or an obstacle) ends the episode, a"
        " failure, as navigation benchmarks count it (off: the paper's env, where the robot slides"
        " along the wall and pays collision_penalty)", json_schema_extra=STATIC,
    )  # fmt: skip
    final_obs: Flag = Field(
        True,
        description="put the pre-reset observation in info['final_obs'] (costs a 2nd lidar cast;"
        " trainers switch it off: none of them reads it)",
        json_schema_extra=STATIC,
    )
    reward: RewardConfig = Field(default_factory=RewardConfig)
    randomize: RandomizeConfig | None = Field(
        None,
        description="sensor and actuator randomisation drawn per env per episode (None: off, the"
        " plain env); see RandomizeConfig",
    )
    obstacles: ObstaclesConfig | None = Field(
        None, description="obstacles the map does not show, seen only by the lidar (None: none,"
        " the paper's env); see ObstaclesConfig",
    )  # fmt: skip

    # properties that fix compiled code besides the STATIC fields (a randomised env carries its
    # perturbation in the state; a robot wider than a cell tests more cells for collisions)
    DERIVED_STATIC: ClassVar[tuple[str, ...]] = (
        "randomized", "collision_reach", "obstacle_counts", "lidar_lines",
    )  # fmt: skip

    def compile_key(self) -> tuple:
        """What the env's compiled code depends on: the STATIC fields and DERIVED_STATIC. Envs
        with equal keys share compiled programs (numbers and banks are traced)."""
        names = (*static_fields(type(self)), *self.DERIVED_STATIC)
        return tuple((name, getattr(self, name)) for name in names)

    @property
    def obstacle_counts(self) -> tuple[int, int] | None:
        """(static, moving) obstacles per episode, None without them: they fix the state's shape."""
        o = self.obstacles
        return None if o is None or o.count == 0 else (o.static, o.moving)

    @property
    def lidar_lines(self) -> int:
        """Grid lines per axis the lidar crosses around the robot: its range in cells, not the
        grid's size, sets the work per beam (``env.lidar.lidar_window``)."""
        from quicknav_core.env.lidar import lidar_window

        return lidar_window(self.grid_size, self.cell_size, self.lidar_max_range)

    @property
    def lidar_reads_window(self) -> bool:
        """Whether the lidar crosses only the lines within its range, read from the room bank
        laid out for it (``EnvParams.room_col_window``): the crossings caster on a grid above 32
        cells whose range is shorter than the grid."""
        from quicknav_core.env.lidar import resolve_lidar_method, uses_window

        return resolve_lidar_method(self.lidar_method) == "crossings" and uses_window(
            self.grid_size, self.lidar_lines)  # fmt: skip

    @property
    def randomized(self) -> bool:
        """Whether sensor and actuator randomisation is on (``randomize`` is set)."""
        return self.randomize is not None

    @property
    def cell_size(self) -> float:
        """Side of one grid cell in metres, to 12 significant digits: a room laid as grid x cell
        (a map at a policy's cells) gives back that cell exactly, where the plain quotient can
        fall short of it (48 x 0.1 / 48 reads 0.09999999999999999), so the checks and choices
        made from it (a step at most one cell, a robot narrower than a cell, how many cells its
        disc reaches) are those of the policy's own env."""
        return float(f"{self.room_size / self.grid_size:.12g}")

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(rows, cols) of the room's grid: (grid_size, grid_size) unless ``grid_rows`` or
        ``grid_cols`` makes it non-square (the cells stay square: room_size / grid_size)."""
        g = self.grid_size
        return (self.grid_rows or g, self.grid_cols or g)

    @property
    def inner_cells(self) -> int:
        """Number of cells inside the outer wall ring."""
        rows, cols = self.grid_shape
        return (rows - 2) * (cols - 2)

    @property
    def carve_target(self) -> int:
        """Free cells a generated room must reach (at least 2: start and goal differ)."""
        return max(2, math.ceil(self.carve_fraction * self.inner_cells - 1e-9))

    @property
    def carve_step_cap(self) -> int:
        """Carving steps after which generation stops even if the target is not met."""
        return self.carve_max_steps if self.carve_max_steps is not None else 1000 * self.inner_cells

    @property
    def resolved_carver(self) -> str:
        """The carver that builds the rooms: ``carver``, with ``auto`` decided (``env.carving``)."""
        if self.carver != "auto":
            return self.carver
        from quicknav_core.env import carving

        return carving.choose_carver(self.grid_size, self.return_prob, self.carve_target)

    @property
    def spawn_radius(self) -> float:
        """The widest robot an episode may have: starts and goals are drawn where it fits."""
        r = self.randomize
        high = r.robot_radius_m[1] if r is not None and r.robot_radius_m is not None else 0.0
        return max(self.robot_radius, high)

    @property
    def collision_reach(self) -> int:
        """0 for a robot narrower than a cell (the four-cell collision test), else how many cells
        away the widest robot's disc reaches (``env.clearance.reach_cells``)."""
        from quicknav_core.env.clearance import narrow, reach_cells

        r, c = self.spawn_radius, self.cell_size
        return 0 if narrow(r, c) else reach_cells(r, c)

    @property
    def obs_dim(self) -> int:
        """Length of the flat observation vector (``env.constants.observation_parts``)."""
        from quicknav_core.env.constants import observation_size

        return observation_size(self)

    @model_validator(mode="after")
    def _check_geometry(self) -> EnvConfig:
        c = self.cell_size
        # a robot as wide as a cell or wider is allowed: it starts and drives only where its disc
        # fits (env.clearance); a bank where it fits nowhere is refused when the bank is built
        step = self.max_wheel_speed * self.dt
        if step > c:
            raise ValueError(
                f"max_wheel_speed*dt = {step:g} m per step exceeds the cell size {c:g} m, so the"
                " robot could pass through walls; allowed range max_wheel_speed*dt <= room_size/grid_size"
            )
        self._check_randomize()
        self._check_obstacles()
        self._check_plan()
        self._check_source()
        self._check_shape()
        if self.rooms != "carved":
            return self
        if self.carve_target > self.inner_cells:
            raise ValueError(
                f"carve_fraction={self.carve_fraction}: grid_size={self.grid_size} has only"
                f" {self.inner_cells} inner cells but at least 2 must be free"
            )
        if self.carve_step_cap < self.carve_target:
            raise ValueError(
                f"carve_max_steps={self.carve_max_steps} can never carve {self.carve_target} cells;"
                f" allowed range carve_max_steps >= {self.carve_target}"
            )
        self._check_carving()
        return self

    def _check_shape(self) -> None:
        """A non-square grid: maps only (the generators lay square rooms), its longer side is
        grid_size (room_size / grid_size stays the cell)."""
        if self.grid_rows is None and self.grid_cols is None:
            return
        rows, cols = self.grid_shape
        if self.rooms != "maps":
            raise ValueError(f"grid_rows/grid_cols ({rows} x {cols}) apply only with rooms='maps'"
                             f" (rooms={self.rooms!r} lays square rooms: leave them unset)")  # fmt: skip
        if max(rows, cols) != self.grid_size:
            raise ValueError(f"grid_rows={rows}, grid_cols={cols}: the longer side must be"
                             f" grid_size={self.grid_size}; allowed: one of them {self.grid_size},"
                             f" the other from {GRID_SIZE_RANGE[0]} to {self.grid_size}")  # fmt: skip

    def _check_source(self) -> None:
        """Fields of one room source are refused under another (they would be ignored)."""
        if self.rooms == "maps" and self.maps is None:
            raise ValueError("rooms='maps' needs env.maps.train: the map files to train on")
        if self.rooms != "maps" and self.maps is not None:
            raise ValueError(f"env.maps applies only with rooms='maps' (rooms={self.rooms!r})")
        if self.rooms != "floorplan" and self.floorplan != FloorplanConfig():
            raise ValueError(f"env.floorplan applies only with rooms='floorplan' (rooms={self.rooms!r})")
        if self.rooms != "carved":
            carving = {"carve_fraction": 0.8, "return_prob": 0.05, "carve_max_steps": None, "carver": "auto"}
            changed = [k for k, v in carving.items() if getattr(self, k) != v]
            if changed:
                raise ValueError(f"{', '.join(changed)} shape carved rooms only; with rooms="
                                 f"{self.rooms!r} leave {'it' if len(changed) == 1 else 'them'} unset")  # fmt: skip

    def _check_plan(self) -> None:
        if self.reward.progress == "path" and not self.observe_plan:
            raise ValueError("reward.progress='path' pays for the planned path's decrease, and only"
                             " an env that plans has one; allowed: with observe_plan=true, or"
                             " progress 'sign', 'linear' or 'potential'")  # fmt: skip

    def _check_obstacles(self) -> None:
        """Obstacles narrower than a cell: their wall test and the robot's are the four-cell one."""
        o = self.obstacles
        if o is None:
            return
        c = self.cell_size
        for name in ("static_radius_m", "moving_radius_m"):
            if getattr(o, name)[1] >= 0.5 * c:
                raise ValueError(f"obstacles.{name}={list(getattr(o, name))}: an obstacle's disc must"
                                 f" be narrower than a cell of {c:g} m; allowed: radius below"
                                 f" {0.5 * c:g} m")  # fmt: skip
        if o.moving and o.speed_mps[1] * self.dt >= c:
            raise ValueError(f"obstacles.speed_mps={list(o.speed_mps)}: a person would pass"
                             f" through walls at {o.speed_mps[1] * self.dt:g} m per step; allowed:"
                             f" below {c / self.dt:g} m/s")  # fmt: skip

    def _check_randomize(self) -> None:
        """The randomised robot keeps the geometry rules of the plain one at its extremes."""
        r = self.randomize
        if r is None:
            return
        c = self.cell_size
        fastest = self.max_wheel_speed * self.dt * r.wheel_scale_max
        if fastest > c:
            raise ValueError(
                f"randomize.wheel_scale_*: at a wheel scale of {r.wheel_scale_max:g} the robot moves"
                f" {fastest:g} m per step, more than the cell size {c:g} m, so it could pass through"
                f" walls; allowed range wheel scale <= {c / (self.max_wheel_speed * self.dt):.3g}"
            )

    def _check_carving(self) -> None:
        """Refuse rooms the carving walk cannot make within its step cap (``env.carving``)."""
        from quicknav_core.env import carving

        g, p, target, cap = self.grid_size, self.return_prob, self.carve_target, self.carve_step_cap
        carver = self.resolved_carver
        # the walk's occupation depends on the grid and return_prob only: solved once, for this
        # check and every fraction a refusal tries (a grid-128 refusal took 7 s of sparse solves
        # when each try solved again)
        pi = carving.occupation(g, p) if carver != "carved" and p > 0 else None
        if carving.feasible(g, p, target, cap, carver, pi):
            return
        steps = carving.carver_steps(carver, g, p, target, pi)
        slowest = carving.SLOWEST_ROOM_FACTOR
        named = repr(carver) if self.carver == carver else f"'auto' (here {carver!r})"
        f_max = next(
            (f / 100 for f in range(int(self.carve_fraction * 100), 0, -1)
             if carving.feasible(g, p, max(2, math.ceil(f / 100 * self.inner_cells - 1e-9)), cap,
                                 carver, pi)),
            0.0,
        )  # fmt: skip
        if carver == "carved":
            raise ValueError(
                f"carver={named} at grid_size={g} with return_prob={p} and carve_fraction="
                f"{self.carve_fraction}: carving {target} cells takes about {steps:,.0f} steps per"
                f" room (the slowest rooms up to {slowest:g}x that), beyond carve_max_steps"
                f" ({cap:,}); allowed: carve_max_steps >= {math.ceil(slowest * steps):,}, or"
                f" carve_fraction <= {f_max:g}"
            )
        p_max = carving.largest_return_prob(g, target, cap)
        g_max = self._largest_feasible_grid()
        other = (
            ", or carver='carved' (returns to carved cells)"
            if carving.feasible(g, p, target, cap, "carved") else ""
        )  # fmt: skip
        raise ValueError(
            f"carver={named} at grid_size={g} with return_prob={p} and carve_fraction="
            f"{self.carve_fraction}: the carving walk jumps back to the centre every"
            f" {1 / p if p else math.inf:.0f} steps on average and rarely gets far, so carving"
            f" {target} cells takes about {steps:,.0f} steps per room (the slowest rooms up to"
            f" {slowest:g}x that), beyond carve_max_steps ({cap:,}); allowed: return_prob <="
            f" {p_max:g}, or carve_fraction <= {f_max:g}, or grid_size <= {g_max}{other}"
        )

    def _largest_feasible_grid(self) -> int:
        """The largest grid below this one whose walk (this return_prob, carve_fraction and step
        cap rule) is expected to carve its rooms, 4 when none is: a bisection over grid sizes,
        ~7 sparse solves instead of one for each grid size below this one. The steps needed grow
        with the grid; where rounding the target makes feasibility step back and forth at small
        grids (a fixed cap of a few thousand steps), it names a feasible grid at such a step, not
        always the largest one."""
        from quicknav_core.env import carving

        def ok(h: int) -> bool:
            target = max(2, math.ceil(self.carve_fraction * (h - 2) ** 2 - 1e-9))
            cap = self.carve_max_steps or 1000 * (h - 2) ** 2
            return carving.feasible(h, self.return_prob, target, cap)

        lo, hi = 4, self.grid_size  # hi: refused (this grid)
        if not ok(lo):
            return 4
        while hi - lo > 1:  # ok(lo), not ok(hi)
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if ok(mid) else (lo, mid)
        return lo

    def build(self, split: Split = "train", runtime: Runtime | None = None
              ) -> tuple[QuickNavEnv, EnvParams]:  # fmt: skip
        """Return the gymnax environment and its params with the ``split`` room bank, the banks
        built (or found) in ``runtime`` (None: a fresh one, nothing shared)."""
        from quicknav_core.env.quicknav import build_env

        return build_env(self, split, runtime)
