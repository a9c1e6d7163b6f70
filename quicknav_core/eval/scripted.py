"""Scripted policies, the baselines every learned agent is compared with: random, the oracle and
the dynamic window approach.

The oracle follows the shortest collision-free path of the robot's disc (``planning``) with the
robot's own differential drive (pure pursuit, blind to what the map does not show); it is also
what ``quicknav env demo`` drives by default. ``dwa`` follows the same plan with a classic local
planner that avoids what its lidar sees (``dwa``).
"""

from __future__ import annotations

import jax

from quicknav_core.config import EnvConfig
from quicknav_core.config.eval import plan_batch
from quicknav_core.eval.agents import Agent
from quicknav_core.eval.planning import oracle_action, oracle_plan

BASELINES = ("random", "oracle", "dwa")


class RandomAgent(Agent):
    """Uniformly random wheel commands."""

    name = "random"

    def act(self, agent_state, obs, states, start, key, deterministic, payload):
        return agent_state, jax.random.uniform(key, (obs.shape[0], 2), minval=-1.0, maxval=1.0)


class OracleAgent(Agent):
    """Follows the shortest disc path with the real differential drive (``planning``)."""

    name = "oracle"

    def __init__(self, room_size: float, goal_radius: float):
        self.room_size = room_size
        self.goal_radius = goal_radius

    def static_key(self):
        return ("oracle", self.room_size, self.goal_radius)

    def init(self, env, params, states, payload):
        plan = lambda a: oracle_plan(a[0], a[1], params.room_size, params.robot_radius,  # noqa: E731
                                     reach=env.reach, cols=env.cols)  # fmt: skip
        n = states.pos.shape[0]  # a few episodes at a time: the fields are (grid * 5)^2 nodes each
        return jax.lax.map(plan, (states.row_bits, states.goal), batch_size=plan_batch(env.config.grid_shape, n))

    def act(self, plans, obs, states, start, key, deterministic, payload):
        act = jax.vmap(
            lambda pl, p, th, g: oracle_action(pl, p, th, g, self.room_size, self.goal_radius)
        )
        return plans, act(plans, states.pos, states.theta, states.goal)


class DwaAgent(OracleAgent):
    """The oracle's plan followed by the dynamic window approach on the lidar (``dwa``)."""

    name = "dwa"

    def __init__(self, env_config: EnvConfig):
        super().__init__(env_config.room_size, env_config.goal_radius)
        c = env_config
        self.numbers = dict(beams=c.lidar_beams, fov_deg=c.lidar_fov_deg, room_size=c.room_size,
                            goal_radius=c.goal_radius, radius=c.robot_radius,
                            max_wheel_speed=c.max_wheel_speed, wheel_base=c.wheel_base, dt=c.dt,
                            max_range=c.lidar_max_range)  # fmt: skip

    def static_key(self):
        return ("dwa", tuple(sorted(self.numbers.items())))

    def act(self, plans, obs, states, start, key, deterministic, payload):
        from quicknav_core.eval.dwa import dwa_action

        act = jax.vmap(lambda pl, p, th, g, r, h: dwa_action(pl, p, th, g, r, h, **self.numbers))
        return plans, act(plans, states.pos, states.theta, states.goal, states.lidar_ranges,
                          states.lidar_hits)  # fmt: skip


def baseline_agent(policy: str, env_config: EnvConfig) -> Agent:
    """A built-in baseline: 'random', 'oracle' or 'dwa'."""
    if policy == "random":
        return RandomAgent()
    if policy == "oracle":
        return OracleAgent(env_config.room_size, env_config.goal_radius)
    if policy == "dwa":
        return DwaAgent(env_config)
    raise ValueError(f"policy={policy!r}: allowed values are {', '.join(BASELINES)}")
