"""Scripted policies, the baselines every learned agent is compared with: random and the oracle.

The oracle follows the shortest collision-free path of the robot's disc (``planning``) with the
robot's own differential drive; it is also what ``quicknav env demo`` drives by default.
"""

from __future__ import annotations

import jax

from quicknav_core.config import EnvConfig
from quicknav_core.eval.agents import Agent
from quicknav_core.eval.planning import oracle_action, oracle_plan

BASELINES = ("random", "oracle")


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
        plan = jax.vmap(lambda rb, g: oracle_plan(rb, g, params.room_size, params.robot_radius,
                                                  reach=env.reach))  # fmt: skip
        return plan(states.row_bits, states.goal)

    def act(self, plans, obs, states, start, key, deterministic, payload):
        act = jax.vmap(
            lambda pl, p, th, g: oracle_action(pl, p, th, g, self.room_size, self.goal_radius)
        )
        return plans, act(plans, states.pos, states.theta, states.goal)


def baseline_agent(policy: str, env_config: EnvConfig) -> Agent:
    """A built-in baseline: 'random' or 'oracle'."""
    if policy == "random":
        return RandomAgent()
    if policy == "oracle":
        return OracleAgent(env_config.room_size, env_config.goal_radius)
    raise ValueError(f"policy={policy!r}: allowed values are {', '.join(BASELINES)}")
