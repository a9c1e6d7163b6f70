"""State and parameter pytrees of the QuickNav environment.

Wall and visited grids travel bit-packed (``bits.py``): the state stays small, so copying it
(auto-reset selects between two whole states every step) and reading it are cheap. The ``walls``
and ``visited`` properties give the plain bool grids.
"""

from __future__ import annotations

import jax
from flax import struct

from quicknav_core.env.bits import unpack_rows


@struct.dataclass
class Perturbation:
    """One episode's draws of the sensor and actuator randomisation (``EnvConfig.randomize``) and
    the queue of past wheel commands that the latency reads. Shapes for one env."""

    noise_seed: jax.Array  # () uint32 stream of this episode's per-step lidar noise
    lidar_noise_m: jax.Array  # () float32 std of additive range noise, metres
    lidar_noise_frac: jax.Array  # () float32 std of range noise per metre of range
    lidar_bias_m: jax.Array  # () float32 range offset, metres
    beam_dropout: jax.Array  # () float32 chance per beam per step of no return
    wheel_scale: jax.Array  # (2,) float32 (left, right) wheel speed / command
    latency_steps: jax.Array  # () int32 steps between a command and the wheels turning
    robot_radius: jax.Array  # () float32 disc radius, metres
    past_commands: jax.Array  # (LATENCY_MAX_STEPS, 2) float32 commands, most recent first


@struct.dataclass
class RandomizeRanges:
    """The ``[low, high]`` ranges the perturbations are drawn from (traced: no recompile)."""

    lidar_noise_m: jax.Array  # (2,) float32
    lidar_noise_frac: jax.Array  # (2,) float32
    lidar_bias_m: jax.Array  # (2,) float32
    beam_dropout: jax.Array  # (2,) float32
    wheel_scale: jax.Array  # (2, 2) float32 [(left, right), (low, high)]
    latency_steps: jax.Array  # (2,) int32
    robot_radius: jax.Array  # (2,) float32


@struct.dataclass
class Obstacles:
    """One episode's obstacles the map does not show (``env.obstacles``). Shapes for one env,
    N = obstacles.static + obstacles.moving; an absent one has radius 0."""

    pos: jax.Array  # (N, 2) float32 centres, metres
    vel: jax.Array  # (N, 2) float32 m/s (0 for static ones)
    radius: jax.Array  # (N,) float32 metres (0: absent this episode)


@struct.dataclass
class ObstacleRanges:
    """What obstacles are drawn from (traced: no recompile)."""

    static_radius: jax.Array  # (2,) float32 [low, high] metres
    moving_radius: jax.Array  # (2,) float32
    speed: jax.Array  # (2,) float32 m/s
    clearance: jax.Array  # () float32 metres kept from the start and the goal


@struct.dataclass
class EnvState:
    """Per-environment state. All fields are JAX arrays; shapes are for one (unbatched) env."""

    pos: jax.Array  # (2,) float32 robot centre (x, y) in metres
    theta: jax.Array  # () float32 heading in radians, in [-pi, pi)
    goal: jax.Array  # (2,) float32 goal centre (x, y) in metres
    col_bits: jax.Array  # (cols, Wr) uint32 walls packed by column: bit r of col c = walls[r, c]
    row_bits: jax.Array  # (rows, Wc) uint32 walls packed by row: bit c of row r = walls[r, c]
    room_index: jax.Array  # () int32 index of the room in the bank (-1: loaded by hand)
    visited_bits: jax.Array  # (rows, Wc) uint32 row-packed cells entered so far this episode
    cell: jax.Array  # (2,) int32 (row, col) of the cell holding the robot centre
    cycle_count: jax.Array  # () int32 C_t: steps this episode that re-entered a visited cell
    collisions: jax.Array  # () int32 wall collisions so far this episode
    lidar_ranges: jax.Array  # (beams,) float32 metres, capped at lidar_max_range
    lidar_hits: jax.Array  # (beams,) int32 HIT_NONE / HIT_WALL / HIT_GOAL
    time: jax.Array  # () int32 steps taken this episode
    # the episode's randomisation draws (None: the env is not randomised, ``EnvConfig.randomize``)
    perturbation: Perturbation | None = None
    # the global plan (``EnvConfig.observe_plan``; None otherwise): (rows, cols) float32 shortest
    # path length from every cell to the goal's cell, in cells, on the known map (env.plan)
    plan: jax.Array | None = None
    # obstacles the map does not show (``EnvConfig.obstacles``; None without them)
    obstacles: Obstacles | None = None

    @property
    def walls(self) -> jax.Array:
        """(..., rows, cols) bool, walls[row, col], row = y index, col = x index."""
        return unpack_rows(self.row_bits, self.col_bits.shape[-2])

    @property
    def visited(self) -> jax.Array:
        """(..., rows, cols) bool cells entered so far this episode."""
        return unpack_rows(self.visited_bits, self.col_bits.shape[-2])


@struct.dataclass
class EnvParams:
    """Traced parameters: numbers and the room bank. Changing them never recompiles."""

    # Room bank (shapes fixed per bank)
    rooms: jax.Array  # (rooms, rows, cols) bool
    room_col_bits: jax.Array  # (rooms, cols, Wr) uint32 column-packed walls
    room_row_bits: jax.Array  # (rooms, rows, Wc) uint32 row-packed walls
    free_cells: jax.Array  # (rooms, rows*cols) int32 flat indices (row * cols + col) of free cells, padded
    num_free: jax.Array  # (rooms,) int32 number of valid entries in free_cells
    # Geometry and robot
    room_size: jax.Array | float = 8.0
    robot_radius: jax.Array | float = 0.15
    max_wheel_speed: jax.Array | float = 1.0
    wheel_base: jax.Array | float = 0.3
    dt: jax.Array | float = 0.1
    # Lidar
    lidar_max_range: jax.Array | float = 10.0
    # Task
    goal_radius: jax.Array | float = 0.3
    max_steps_in_episode: jax.Array | int = 300
    # Reward weights
    step_penalty: jax.Array | float = 0.1
    collision_penalty: jax.Array | float = 10.0
    cycle_penalty: jax.Array | float = 0.0
    progress_reward: jax.Array | float = 1.0
    goal_reward: jax.Array | float = 50.0
    cycle_cap: jax.Array | int = 10
    exploration_reward: jax.Array | float = 0.0
    progress_mode: jax.Array | int = 0  # 0: sign(d_prev - d), 1: scaled difference, 2: potential
    potential_gamma: jax.Array | float = 0.99  # γ of the potential-based shaping (mode 2)
    proximity_penalty: jax.Array | float = 0.0  # per step at zero clearance, falling to 0 at proximity_m
    proximity_m: jax.Array | float = 0.2  # clearance (m) from which the proximity term starts
    # Curriculum episode pool (``train.curriculum``; None: episodes are drawn by the spawn rule).
    # Sorted by the oracle's path length (shortest first); resets draw from the first
    # ``pool_count`` entries.
    pool_room: jax.Array | None = None  # (P,) int32 room index in the bank
    pool_start: jax.Array | None = None  # (P,) int32 flat start cell (row * cols + col)
    pool_goal: jax.Array | None = None  # (P,) int32 flat goal cell
    pool_count: jax.Array | int = 0  # episodes of the pool in use (the curriculum's level)
    # Sensor and actuator randomisation (``env.perturb``; None: the env is not randomised)
    randomize: RandomizeRanges | None = None
    # Obstacles the map does not show (``env.obstacles``; None: none)
    obstacles: ObstacleRanges | None = None
    # The bank laid out for the lidar's range window (``lidar.window_bits``: every room's packed
    # lines with h = (lines - 1) // 2 free lines and m = ``lidar.side_words`` free words around
    # them), for an env whose lidar crosses only the lines within range (grids above 32 cells);
    # None otherwise
    room_col_window: jax.Array | None = None  # (rooms, cols + 2h, Wr + 2m) uint32
    room_row_window: jax.Array | None = None  # (rooms, rows + 2h, Wc + 2m) uint32
