"""QuickNav: differential-drive lidar navigation in procedurally carved rooms, as a gymnax env."""

from __future__ import annotations

from functools import cached_property, partial
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from gymnax.environments import environment, spaces

from quicknav_core.env.bits import BankRows, num_words, pack_rows, pack_rows_np, read_bit, set_bit
from quicknav_core.env.clearance import spawn_cells
from quicknav_core.env.constants import (
    BIG,
    HIT_GOAL,
    HIT_NONE,
    HIT_WALL,
    PATH_SCALE_M,
    check_split,
    observation_bounds,
)
from quicknav_core.env.dynamics import drive, move_with_sliding, wall_distance, wheel_command
from quicknav_core.env.lidar import (
    beam_directions,
    cast_lidar_packed,
    cast_lidar_window,
    window_bits,
)
from quicknav_core.env.obstacles import (
    OBSTACLE_WORDS,
    absent,
    obstacle_numbers,
    overlaps,
    place,
    ray_distances,
)
from quicknav_core.env.obstacles import move as move_obstacles
from quicknav_core.env.perturb import (
    PERTURBATION_WORDS,
    apply_command,
    at_rest,
    draw,
    perturb_scan,
    randomize_numbers,
)
from quicknav_core.env.plan import (
    cell_field,
    disc_fits,
    path_length_from,
    plan_features,
    plan_waypoints,
)
from quicknav_core.env.reward import reward_terms, total_reward
from quicknav_core.env.rng import hash_key_bits, uniform_from_bits
from quicknav_core.env.room_sources import RoomSource, free_cell_table, room_source
from quicknav_core.env.types import EnvParams, EnvState, Obstacles, Perturbation
from quicknav_core.markers import traced_values

if TYPE_CHECKING:  # pragma: no cover - the env reads its config's fields, never imports the module
    from quicknav_core.config import EnvConfig, Split
    from quicknav_core.runtime import Runtime


class QuickNavEnv(environment.Environment[EnvState, EnvParams]):
    """A disc robot with a 2-D lidar must drive to a goal in a carved grid room.

    Observation (float32, flat, ``obs_dim = 4 + 3*B (+ 5 if observe_goal)``, B = lidar_beams):
        [0:4]        x / room_size, y / room_size, sin(theta), cos(theta)
        [4:4+B]      lidar ranges / lidar_max_range (1.0 = nothing in range)
        [4+B:4+2B]   1.0 where the beam hit a wall
        [4+2B:4+3B]  1.0 where the beam hit the goal
        [4+3B:+5]    (observe_goal only) goal x / room_size, goal y / room_size,
                     distance to goal / room_size, sin and cos of the goal bearing in the robot frame
    Beam i points at ``heading + angle_i`` (counter-clockwise; see ``lidar.beam_angles``).
    Action: float32 (2,) in [-1, 1] = (left, right) wheel speed / max_wheel_speed; NaN counts as 0.
    Reward: the paper's formula (``reward.reward_terms``); terms are reported in ``info``.
    Termination: goal reached (centre within goal_radius). Truncation: ``max_steps`` steps.
    Randomisation (``EnvConfig.randomize``, off by default): each episode draws lidar noise, bias
    and dropout, wheel scales, an action latency and a radius (``state.perturbation``); the
    observation's lidar entries are then what the perturbed lidar reports (``env.perturb``).
    ``step`` auto-resets: a finished episode's next observation is the first of a new episode, and
    ``info["final_obs"]`` holds the last observation of the finished one (if ``final_obs``).

    Public step phases, for batched steppers and trainers that compose their own step:
    ``transition`` (drive, collide, reward; lidar left stale), ``spawn`` (a fresh episode, lidar
    not cast) and ``with_lidar`` (cast the lidar for a state's pose).

    >>> env, params = EnvConfig(grid_size=8).build("train")  # a Runtime shares banks: build("train", rt)
    >>> obs, state = env.reset(jax.random.PRNGKey(0), params)
    >>> obs, state, reward, done, info = env.step(jax.random.PRNGKey(1), state, jnp.ones(2), params)
    """

    def __init__(self, config: EnvConfig, rooms: RoomSource | None = None):
        super().__init__()
        self.config = config
        # where the room banks come from (the env never asks which source it is)
        self.rooms = rooms if rooms is not None else room_source(config)
        self.grid_size = config.grid_size  # cell = room_size / grid_size
        self.rows, self.cols = config.grid_shape  # the room's grid (square unless a map's is not)
        self.num_beams = config.lidar_beams
        self.observe_goal = config.observe_goal
        self.final_obs = config.final_obs
        self.randomized = config.randomize is not None
        self.obstacle_count = config.obstacles.count if config.obstacle_counts else 0
        self.reach = config.collision_reach  # 0: narrower than a cell (the four-cell test)
        # the lidar reads its range window from the bank laid out for it (EnvParams.room_*_window)
        self.lidar_window = config.lidar_reads_window
        # rows of more than one word: a step reads the walls near the robot from the bank's room
        # by index (bits.BankRows), not from the state's own copy of it
        self.bank_rows = num_words(self.cols) > 1

    # Identity: jit treats the env as a static argument. Two envs are the same static argument
    # when their compiled code is the same: the config's compile key (its STATIC fields and what
    # derives from them). Numbers (rewards, speeds, radii) and the room bank live in EnvParams, so
    # configs that differ only in them share compiled code.
    @property
    def static_key(self) -> tuple:
        return self.config.compile_key()

    def __hash__(self) -> int:
        return hash(("QuickNavEnv", self.static_key))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, QuickNavEnv) and other.static_key == self.static_key

    @property
    def name(self) -> str:
        return "QuickNav"

    @property
    def obs_dim(self) -> int:
        return self.config.obs_dim

    @cached_property
    def _default_params(self) -> EnvParams:
        return make_params(self.config, "train", self.rooms)

    @property
    def default_params(self) -> EnvParams:
        """Params with the train room bank of this env's config."""
        return self._default_params

    # ------------------------------------------------------------------ gymnax API
    # ``params=None`` (this config's train params) is filled in before the compiled call: equal
    # envs share compiled code, so nothing of one config's numbers may be baked into it.
    def step(
        self,
        key: jax.Array,
        state: EnvState,
        action: jax.Array,
        params: EnvParams | None = None,
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        """Step with auto-reset: the lidar is cast for the kept pose (fresh or moved), and once more
        for the pre-reset pose when ``final_obs`` is on (under vmap both casts run for every env)."""
        return self._jit_step(key, state, action, self.default_params if params is None else params)

    def reset(self, key: jax.Array, params: EnvParams | None = None) -> tuple[jax.Array, EnvState]:
        """A fresh episode (see ``reset_env``)."""
        return self._jit_reset(key, self.default_params if params is None else params)

    @partial(jax.jit, static_argnames=("self",))
    def _jit_reset(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        return self.reset_env(key, params)

    @partial(jax.jit, static_argnames=("self",))
    def _jit_step(
        self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        # The dynamics are deterministic: the key only feeds the reset.
        moved, reward, info = self.transition(key, state, action, params)
        done = info["terminated"] | info["truncated"]
        # under vmap both sides are computed for every env: with observe_plan that is a plan per
        # env per step (batched_step, which QuickNav's PPO and the Rollout server use, plans only
        # for the envs that ended)
        fresh = self.with_plan(self.spawn(key, params), params)
        kept = jax.tree.map(lambda a, b: jax.lax.select(done, a, b), fresh, moved)
        kept = self.with_lidar(kept, params)
        if self.final_obs:
            info["final_obs"] = self.get_obs(self.with_lidar(moved, params), params)
        return self.get_obs(kept, params), kept, reward, done, info

    def step_env(
        self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
    ) -> tuple[jax.Array, EnvState, jax.Array, jax.Array, dict[str, Any]]:
        """One transition without auto-reset."""
        moved, reward, info = self.transition(key, state, action, params)
        moved = self.with_lidar(moved, params)
        done = info["terminated"] | info["truncated"]
        return self.get_obs(moved, params), moved, reward, done, info

    def reset_env(self, key: jax.Array, params: EnvParams) -> tuple[jax.Array, EnvState]:
        """Pick a room from the bank, spawn robot and goal, plan (``observe_plan``), cast the
        first lidar scan."""
        state = self.with_lidar(self.with_plan(self.spawn(key, params), params), params)
        return self.get_obs(state, params), state

    def load_state(
        self,
        walls: jax.Array,
        pos: jax.Array,
        theta: jax.Array | float,
        goal: jax.Array,
        params: EnvParams | None = None,
        room_index: int = -1,
        perturbation: Perturbation | None = None,
        obstacles: Obstacles | None = None,
    ) -> tuple[jax.Array, EnvState]:
        """Start an episode in a given room, pose and goal (for tests, replays and the twin).

        A randomised env takes the episode's ``perturbation`` too (default: one that changes
        nothing, ``perturb.at_rest``); an env with obstacles its ``obstacles`` (default: none
        present). On a grid above 32 cells ``room_index`` must name the bank room whose walls
        ``walls`` are: the lidar reads the walls near the robot from the bank by index."""
        if params is None:
            params = self.default_params
        if self.randomized and perturbation is None:
            perturbation = at_rest(params.robot_radius)
        elif not self.randomized and perturbation is not None:
            raise ValueError("perturbation given, but this env is not randomised (EnvConfig.randomize)")
        walls = jnp.asarray(walls, bool)
        if walls.shape != (self.rows, self.cols):
            raise ValueError(
                f"walls has shape {walls.shape}; expected ({self.rows}, {self.cols}) for"
                f" grid_size={self.grid_size}" + ("" if self.rows == self.cols else
                                                  f", grid_rows={self.rows}, grid_cols={self.cols}")
            )
        if self.lidar_window or self.bank_rows:
            self._check_bank_room(walls, room_index, params)
        pos = jnp.asarray(pos, jnp.float32).reshape(2)
        rc = self._cell_of(pos, params.room_size / self.grid_size)
        state = self._episode_start(
            pos, theta, goal, pack_rows(walls.T), pack_rows(walls), jnp.int32(room_index), rc,
            perturbation,
        )  # fmt: skip
        if obstacles is not None:
            if not self.obstacle_count:
                raise ValueError("obstacles given, but this env has none (EnvConfig.obstacles)")
            get = obstacles.get if isinstance(obstacles, dict) else lambda k: getattr(obstacles, k)
            given = Obstacles(**{k: jnp.asarray(get(k), jnp.float32) for k in ("pos", "vel", "radius")})
            state = state.replace(obstacles=given)
        state = self.with_lidar(self.with_plan(state, params), params)
        return self.get_obs(state, params), state

    def _check_bank_room(self, walls: jax.Array, room_index: int, params: EnvParams) -> None:
        """An env above 32 cells reads the walls near the robot from the bank's rooms by index
        (``with_lidar``, ``_rows``): a state must name the bank room its walls are."""
        n = int(params.rooms.shape[0])
        if not 0 <= int(room_index) < n or not bool(jnp.array_equal(params.rooms[room_index], walls)):
            raise ValueError(
                f"load_state: room_index={int(room_index)} must name the bank room whose walls"
                f" these are (0 .. {n - 1}): on a grid above 32 cells (grid_size={self.grid_size})"
                " the lidar reads the walls near the robot from the room bank by index. Build the"
                " env with a room source that holds these walls (rooms='maps') and give the room's"
                " index"
            )

    def get_obs(self, state: EnvState, params: EnvParams | None = None, key=None) -> jax.Array:
        """Flat float32 observation (layout in the class docstring)."""
        if params is None:
            params = self.default_params
        room = jnp.asarray(params.room_size, jnp.float32)
        sin_t, cos_t = jnp.sin(state.theta), jnp.cos(state.theta)
        parts = [state.pos / room, sin_t[None], cos_t[None]] if self.config.observe_pose else []
        parts += [
            state.lidar_ranges / params.lidar_max_range,
            (state.lidar_hits == HIT_WALL).astype(jnp.float32),
            (state.lidar_hits == HIT_GOAL).astype(jnp.float32),
        ]
        if self.observe_goal:
            rel = state.goal - state.pos
            dist = jnp.sqrt(jnp.sum(rel * rel))
            # the goal direction rotated into the robot frame: (cos, sin) of the bearing, no atan2
            inv = jnp.where(dist > 0.0, 1.0 / jnp.maximum(dist, 1e-12), 0.0)
            fwd = (cos_t * rel[0] + sin_t * rel[1]) * inv
            left = (cos_t * rel[1] - sin_t * rel[0]) * inv
            fwd = jnp.where(dist > 0.0, fwd, 1.0)
            parts += [state.goal / room, (dist / room)[None], left[None], fwd[None]]
        if self.config.observe_plan:
            parts.append(self.plan_observation(state, params))
        return jnp.concatenate(parts).astype(jnp.float32)

    def is_terminal(self, state: EnvState, params: EnvParams) -> jax.Array:
        """Goal reached or step limit hit."""
        dist = jnp.linalg.norm(state.goal - state.pos)
        return (dist <= params.goal_radius) | (state.time >= params.max_steps_in_episode)

    def action_space(self, params: EnvParams | None = None) -> spaces.Box:
        """(left, right) wheel commands in [-1, 1]."""
        return spaces.Box(-1.0, 1.0, (2,), jnp.float32)

    def observation_space(self, params: EnvParams | None = None) -> spaces.Box:
        """Exact bounds of every observation entry."""
        low, high = observation_bounds(self.config)
        return spaces.Box(jnp.asarray(low), jnp.asarray(high), (self.obs_dim,), jnp.float32)

    def state_space(self, params: EnvParams | None = None) -> spaces.Dict:
        """Not used by trainers; provided for completeness of the gymnax API."""
        return spaces.Dict(
            {
                "pos": spaces.Box(0.0, self.config.room_size, (2,), jnp.float32),
                "theta": spaces.Box(-jnp.pi, jnp.pi, (), jnp.float32),
                "walls": spaces.Box(0, 1, (self.rows, self.cols), jnp.bool_),
            }
        )

    @property
    def num_actions(self) -> int:
        return 2

    # ------------------------------------------------------------------ step phases
    def _cell_of(self, pos: jax.Array, cell) -> jax.Array:
        """(row, col) int32 of the cell holding ``pos``, clipped to the grid."""
        rc = jnp.floor(pos[::-1] / cell).astype(jnp.int32)
        return jnp.clip(rc, 0, jnp.array([self.rows - 1, self.cols - 1], jnp.int32))

    def _flat_rc(self, flat: jax.Array) -> jax.Array:
        """(row, col) of flat cell indices (row * cols + col), stacked on the first axis."""
        return jnp.stack([flat // self.cols, flat % self.cols])

    def spawn(self, key: jax.Array, params: EnvParams) -> EnvState:
        """A fresh episode (lidar not yet cast): room, start pose and the farthest goal candidate."""
        g, k = self.grid_size, self.config.goal_candidates
        cell = params.room_size / g
        # One PRNG call for everything a reset draws (the reset runs every step under vmap); the
        # randomisation's words come after the plain env's, which stay what they were.
        p_words = PERTURBATION_WORDS if self.randomized else 0
        bits = hash_key_bits(key, 5 + k + p_words + OBSTACLE_WORDS * self.obstacle_count)
        u = uniform_from_bits(bits[: 5 + k])
        u_room, u_start, jitter_u, u_head, u_goal = u[0], u[1], u[2:4], u[4], u[5:]
        perturbation = draw(params.randomize, bits[5 + k : 5 + k + p_words]) if self.randomized else None
        radius = params.robot_radius if perturbation is None else perturbation.robot_radius
        if params.pool_room is not None:
            state = self._spawn_from_pool(params, u_room, jitter_u, u_head, perturbation, radius)
            return self.with_obstacles(state, params, bits[5 + k + p_words :])
        n_rooms = params.rooms.shape[0]
        room = jnp.minimum(jnp.floor(u_room * n_rooms).astype(jnp.int32), n_rooms - 1)
        n_free = params.num_free[room]
        # Start: a uniformly chosen free cell, uniformly placed where the disc clears the cell walls.
        s = jnp.minimum(jnp.floor(u_start * n_free).astype(jnp.int32), n_free - 1)
        start = params.free_cells[room, s]
        start_rc = self._flat_rc(start)
        slack = jnp.maximum(0.5 * cell - radius, 0.0)
        pos = (start_rc[::-1].astype(jnp.float32) + 0.5) * cell + (2.0 * jitter_u - 1.0) * slack
        # Goal: the farthest of K free cells drawn from the cells other than the start cell.
        j = jnp.minimum(jnp.floor(u_goal * (n_free - 1)).astype(jnp.int32), n_free - 2)
        j = j + (j >= s).astype(jnp.int32)
        cand = params.free_cells[room, j]
        cand_xy = (self._flat_rc(cand)[::-1].T.astype(jnp.float32) + 0.5) * cell
        goal = cand_xy[jnp.argmax(jnp.sum((cand_xy - pos) ** 2, axis=-1))]
        theta = (2.0 * u_head - 1.0) * jnp.pi
        state = self._episode_start(
            pos, theta, goal, params.room_col_bits[room], params.room_row_bits[room], room, start_rc,
            perturbation,
        )  # fmt: skip
        return self.with_obstacles(state, params, bits[5 + k + p_words :])

    def with_obstacles(self, state: EnvState, params: EnvParams, bits: jax.Array) -> EnvState:
        """State with its episode's obstacles placed from ``bits`` (``env.obstacles``; unchanged
        without obstacles)."""
        if not self.obstacle_count:
            return state
        c = self.config.obstacles
        room = state.room_index
        return state.replace(obstacles=place(
            params.obstacles, bits, c.static, c.moving, params.free_cells[room],
            params.num_free[room], state.row_bits, params.room_size / self.grid_size, state.pos,
            state.goal, self.cols,
        ))  # fmt: skip

    def _spawn_from_pool(
        self, params: EnvParams, u_pick, jitter_u, u_head, perturbation, radius
    ) -> EnvState:
        """A curriculum episode: one of the pool's first ``pool_count`` (room, start, goal) cells,
        the start jittered and the heading drawn as in ``spawn``."""
        g = self.grid_size
        cell = params.room_size / g
        count = jnp.clip(jnp.asarray(params.pool_count, jnp.int32), 1, params.pool_room.shape[0])
        i = jnp.minimum(jnp.floor(u_pick * count).astype(jnp.int32), count - 1)
        room, start, goal_cell = params.pool_room[i], params.pool_start[i], params.pool_goal[i]
        start_rc = self._flat_rc(start)
        slack = jnp.maximum(0.5 * cell - radius, 0.0)
        pos = (start_rc[::-1].astype(jnp.float32) + 0.5) * cell + (2.0 * jitter_u - 1.0) * slack
        goal = (self._flat_rc(goal_cell)[::-1].astype(jnp.float32) + 0.5) * cell
        theta = (2.0 * u_head - 1.0) * jnp.pi
        return self._episode_start(
            pos, theta, goal, params.room_col_bits[room], params.room_row_bits[room], room, start_rc,
            perturbation,
        )  # fmt: skip

    def _episode_start(
        self, pos, theta, goal, col_bits, row_bits, room_index, start_rc, perturbation=None
    ) -> EnvState:
        """The state at an episode's first step (lidar not yet cast, only the start cell visited)."""
        rows, cols, b = self.rows, self.cols, self.num_beams
        return EnvState(
            pos=jnp.asarray(pos, jnp.float32).reshape(2),
            theta=jnp.asarray(theta, jnp.float32),
            goal=jnp.asarray(goal, jnp.float32).reshape(2),
            col_bits=col_bits,
            row_bits=row_bits,
            room_index=jnp.asarray(room_index, jnp.int32),
            visited_bits=set_bit(
                jnp.zeros((rows, num_words(cols)), jnp.uint32), start_rc[0], start_rc[1]
            ),
            cell=jnp.asarray(start_rc, jnp.int32),
            cycle_count=jnp.int32(0),
            collisions=jnp.int32(0),
            lidar_ranges=jnp.zeros((b,), jnp.float32),
            lidar_hits=jnp.zeros((b,), jnp.int32),
            time=jnp.int32(0),
            perturbation=perturbation,
            # planned by ``with_plan`` (a placeholder until then, so every state has one shape)
            plan=jnp.zeros((rows, cols), jnp.float32) if self.config.observe_plan else None,
            # placed by ``with_obstacles`` (none until then)
            obstacles=absent(self.obstacle_count) if self.obstacle_count else None,
        )

    def transition(
        self, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams
    ) -> tuple[EnvState, jax.Array, dict[str, Any]]:
        """Drive, collide/slide, count revisits, reward; the lidar is left stale for the caller."""
        del key  # the dynamics are deterministic
        g = self.grid_size
        cell = params.room_size / g
        command = wheel_command(action)
        perturbation, radius = state.perturbation, params.robot_radius
        if perturbation is not None:
            command, perturbation = apply_command(perturbation, command)
            radius = perturbation.robot_radius
        delta, theta = drive(
            state.theta, command, params.max_wheel_speed, params.wheel_base, params.dt
        )
        rows = self._rows(state, params)
        pos, collided = move_with_sliding(state.pos, delta, rows, cell, radius, self.reach)
        obstacles = state.obstacles
        if obstacles is not None:
            # a move into an obstacle is not made (no sliding around a disc); then people walk
            hit = overlaps(pos, radius, obstacles)
            pos, collided = jnp.where(hit, state.pos, pos), collided | hit
            obstacles = move_obstacles(obstacles, rows, cell, params.dt, pos, radius)
        rc = self._cell_of(pos, cell)
        entered = jnp.any(rc != state.cell)
        seen = read_bit(state.visited_bits[rc[0]], rc[1])
        revisit = entered & seen
        new_cell = entered & ~seen
        cycle_count = state.cycle_count + revisit.astype(jnp.int32)
        visited_bits = set_bit(state.visited_bits, rc[0], rc[1])
        dist_prev = jnp.linalg.norm(state.goal - state.pos)
        # a robot that did not move made no progress: XLA may round the two norms of one point
        # differently (fused multiply-adds), which would turn sign(0) into a penalty or a reward
        dist = jnp.where(jnp.all(pos == state.pos), dist_prev, jnp.linalg.norm(state.goal - pos))
        goal_reached = dist <= params.goal_radius
        path_prev = path = None
        if self.config.observe_plan:  # the planned path left, before and after (env.plan)
            metres = state.plan * cell
            path_prev = path_length_from(metres, state.pos, params.room_size, 1)
            path = jnp.where(jnp.all(pos == state.pos), path_prev,
                             path_length_from(metres, pos, params.room_size, 1))  # fmt: skip
        # how close the robot's edge came to a wall or an obstacle (the proximity term)
        near = wall_distance(pos, rows, cell)
        if obstacles is not None:
            gaps = jnp.linalg.norm(obstacles.pos - pos[None, :], axis=-1) - obstacles.radius
            near = jnp.minimum(near, jnp.min(jnp.where(obstacles.radius > 0.0, gaps, BIG)))
        terms = reward_terms(collided, cycle_count, dist_prev, dist, goal_reached, params, new_cell,
                             path_prev, path, near - radius)  # fmt: skip
        time = state.time + 1
        truncated = (time >= params.max_steps_in_episode) & ~goal_reached
        if self.config.end_on_collision:
            truncated = truncated & ~collided
        moved = state.replace(
            pos=pos,
            theta=theta,
            visited_bits=visited_bits,
            cell=rc,
            cycle_count=cycle_count,
            collisions=state.collisions + collided.astype(jnp.int32),
            time=time,
            perturbation=perturbation,
            obstacles=obstacles,
        )
        ended = goal_reached | collided if self.config.end_on_collision else goal_reached
        info = {
            "terminated": ended,
            "truncated": truncated,
            "goal_reached": goal_reached,
            "collision": collided,
            "revisit": revisit,
            "reward_terms": terms,
        }
        return moved, total_reward(terms), info

    def _rows(self, state: EnvState, params: EnvParams):
        """The room's packed rows a step reads near the robot: the bank's, by the state's room
        index (``bank_rows``), or the state's own."""
        return BankRows(params.room_row_bits, state.room_index) if self.bank_rows else state.row_bits

    def with_lidar(self, state: EnvState, params: EnvParams) -> EnvState:
        """State with the lidar scan of its current pose."""
        if self.lidar_window:  # the room's lines near the robot, read from the bank by its index
            ranges, hits = cast_lidar_window(
                state.pos, state.theta, state.goal, params.room_col_window, params.room_row_window,
                state.room_index, self.num_beams, self.config.lidar_fov_deg,
                params.room_size / self.grid_size, params.lidar_max_range, params.goal_radius,
                self.config.lidar_lines,
            )  # fmt: skip
            return self._with_unmapped(state, params, ranges, hits)
        ranges, hits = cast_lidar_packed(self.config.lidar_method)(
            state.pos,
            state.theta,
            state.goal,
            state.col_bits,
            state.row_bits,
            self.num_beams,
            self.config.lidar_fov_deg,
            params.room_size / self.grid_size,
            params.lidar_max_range,
            params.goal_radius,
            self.config.lidar_lines,
        )
        return self._with_unmapped(state, params, ranges, hits)

    def _with_unmapped(self, state: EnvState, params: EnvParams, ranges, hits) -> EnvState:
        """State with the scan of the walls ``ranges``/``hits``, the obstacles the map does not
        show seen in it, and the sensor's perturbation."""
        if state.obstacles is not None:  # the discs the map does not show, seen as walls
            dx, dy = beam_directions(state.theta, self.num_beams, self.config.lidar_fov_deg)
            t_obs = ray_distances(state.pos, dx, dy, state.obstacles)
            nearest = jnp.where(hits == HIT_NONE, BIG, ranges)
            closer = (t_obs < nearest) & (t_obs <= params.lidar_max_range)
            ranges = jnp.where(closer, t_obs, ranges).astype(jnp.float32)
            hits = jnp.where(closer, HIT_WALL, hits)
        if state.perturbation is not None:
            ranges, hits = perturb_scan(
                state.perturbation, state.time, ranges, hits, params.lidar_max_range
            )
        return state.replace(lidar_ranges=ranges, lidar_hits=hits)

    # ------------------------------------------------------------------ the global plan
    def _plan_usable(self, state: EnvState, params: EnvParams) -> jax.Array:
        """(rows, cols) bool: the cells the disc's centre may pass on the known map."""
        radius = params.robot_radius if state.perturbation is None else state.perturbation.robot_radius
        return disc_fits(state.walls, params.room_size / self.grid_size, radius, self.reach)

    def with_plan(self, state: EnvState, params: EnvParams) -> EnvState:
        """State with the global plan of its episode (``observe_plan``; unchanged otherwise): the
        shortest path length from every cell to the goal's cell on the room's known map."""
        if not self.config.observe_plan:
            return state
        goal_rc = self._cell_of(state.goal, params.room_size / self.grid_size)
        return state.replace(plan=cell_field(self._plan_usable(state, params), goal_rc))

    def plan_observation(self, state: EnvState, params: EnvParams) -> jax.Array:
        """The plan's part of the observation (``env.plan.plan_features``)."""
        c = self.config
        cell = params.room_size / self.grid_size
        usable = self._plan_usable(state, params)
        points = plan_waypoints(state.plan, usable, state.cell, state.goal, cell, c.plan_lookahead,
                                c.plan_waypoints)  # fmt: skip
        return plan_features(state.pos, state.theta, points, state.plan, state.cell, cell,
                             c.plan_lookahead, PATH_SCALE_M)  # fmt: skip


def traced_numbers(config: EnvConfig) -> dict[str, Any]:
    """The ``EnvParams`` numbers of a config: every field marked traced, of the env and its reward
    (``markers.traced_values``), and the randomisation ranges. Declared on the fields, so
    configs that differ only in these share compiled code and vmap side by side."""
    values = {**traced_values(config), **traced_values(config.reward)}
    numbers = {k: np.int32(v) if isinstance(v, int) else np.float32(v) for k, v in values.items()}
    return {**numbers, "randomize": randomize_numbers(config), "obstacles": obstacle_numbers(config)}


def make_params(config: EnvConfig, split: Split = "train", rooms: RoomSource | None = None
                ) -> EnvParams:  # fmt: skip
    """EnvParams for ``config`` holding the ``split`` bank of ``rooms`` (default: the config's
    room source in a fresh runtime)."""
    source = rooms if rooms is not None else room_source(config)
    bank = source.bank(check_split(split))
    free, counts = free_cell_table(~spawn_cells(bank, config, split))
    col_bits = jnp.asarray(pack_rows_np(np.swapaxes(bank, 1, 2)))
    row_bits = jnp.asarray(pack_rows_np(bank))
    window = {}
    if config.lidar_reads_window:
        lines = config.lidar_lines
        window = {"room_col_window": window_bits(col_bits, lines),
                  "room_row_window": window_bits(row_bits, lines)}  # fmt: skip
    return EnvParams(
        rooms=jnp.asarray(bank),
        room_col_bits=col_bits,
        room_row_bits=row_bits,
        free_cells=jnp.asarray(free),
        num_free=jnp.asarray(counts),
        **traced_numbers(config),
        **window,
    )


def build_env(config: EnvConfig, split: Split = "train", runtime: Runtime | None = None
              ) -> tuple[QuickNavEnv, EnvParams]:  # fmt: skip
    """The env and its params for one split (``EnvConfig.build`` calls this)."""
    env = QuickNavEnv(config, room_source(config, runtime))
    params = env.default_params if split == "train" else make_params(config, check_split(split), env.rooms)
    return env, params
