"""Probe environments: tasks so small that a working trainer solves them in seconds and a broken one
cannot (the idea of rejax's and CleanRL's probe tests). A trainer is given one with
``make_trainer(config, env=(probe, probe.default_params))``; the config's network and algorithm
are what train.

Each probe has QuickNav's trainer interface: two wheel commands in [-1, 1], ``obs_dim``,
``info["goal_reached"]`` and ``info["collision"]`` (the episode statistics), ``config.observe_plan``
(off), and parameters with ``pool_count`` / ``pool_room`` (no curriculum).

- ``Target``: one-step episodes. The observation is a point t drawn in [-0.75, 0.75]^2; the reward
  is ``1 - |a - t|``. Solved by a policy that maps what it sees to what it does (reward near 1);
  one that ignores its observation earns about 0.43 at best (a = 0). Checks that a trainer's actor
  learns from its critic (PPO's advantages, SAC's and TD3's Q-gradients).
- ``Cue``: two-step episodes. The first observation shows a cue c = -1 or +1 (and a first-step
  flag); the second shows neither. The second step's reward is ``c * a[0]`` (the first step's is
  0). Solved only by a policy that remembers the first observation (a recurrent carry, a memory
  head, or two frames); a memoryless one earns 0 in expectation. Checks recurrent PPO's carry,
  its replay and its gradients through time.
"""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
from flax import struct
from gymnax.environments import environment, spaces


@struct.dataclass
class ProbeState:
    cue: jax.Array  # (2,) Target's point, or (c, 0) for Cue
    time: jax.Array  # steps taken in the episode


@struct.dataclass
class ProbeParams:
    max_steps_in_episode: int = 2
    pool_count: int = 0  # the trainers' curriculum fields: no pool
    pool_room: None = None


class _Probe(environment.Environment):
    config = SimpleNamespace(observe_plan=False)
    obs_dim = 2
    steps = 1  # episode length

    def __hash__(self) -> int:  # jit's static argument: one compiled program per probe kind
        return hash(type(self).__name__)

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self)

    @property
    def default_params(self) -> ProbeParams:
        return ProbeParams(max_steps_in_episode=self.steps)

    @property
    def name(self) -> str:
        return type(self).__name__

    @property
    def num_actions(self) -> int:
        return 2

    def action_space(self, params=None) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (2,), jnp.float32)

    def observation_space(self, params=None) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, (self.obs_dim,), jnp.float32)

    def is_terminal(self, state: ProbeState, params=None) -> jax.Array:
        return state.time >= self.steps

    def reward(self, state: ProbeState, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(reward, solved) of ``action`` taken in ``state``."""
        raise NotImplementedError

    def step_env(self, key, state: ProbeState, action, params):
        action = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        reward, solved = self.reward(state, action)
        state = state.replace(time=state.time + 1)
        done = self.is_terminal(state)
        info = {"goal_reached": done & solved, "collision": jnp.bool_(False)}
        return self.get_obs(state), state, reward, done, info


class Target(_Probe):
    """See the module docstring."""

    steps = 1

    def reset_env(self, key, params):
        state = ProbeState(jax.random.uniform(key, (2,), jnp.float32, -0.75, 0.75), jnp.int32(0))
        return self.get_obs(state), state

    def get_obs(self, state: ProbeState, params=None, key=None) -> jax.Array:
        return state.cue

    def reward(self, state, action):
        miss = jnp.linalg.norm(action - state.cue)
        return 1.0 - miss, miss < 0.2


class Cue(_Probe):
    """See the module docstring."""

    steps = 2

    def reset_env(self, key, params):
        c = jnp.where(jax.random.bernoulli(key), 1.0, -1.0).astype(jnp.float32)
        state = ProbeState(jnp.stack([c, jnp.float32(0.0)]), jnp.int32(0))
        return self.get_obs(state), state

    def get_obs(self, state: ProbeState, params=None, key=None) -> jax.Array:
        first = state.time == 0
        return jnp.where(first, jnp.stack([state.cue[0], jnp.float32(1.0)]), jnp.zeros(2, jnp.float32))

    def reward(self, state, action):
        last = state.time == self.steps - 1
        paid = state.cue[0] * action[0]
        return jnp.where(last, paid, 0.0), paid > 0.5


def target_miss(policy, episodes: int = 512) -> float:
    """Mean distance between the policy's deterministic action and Target's point, on fresh points."""
    points = jax.random.uniform(jax.random.PRNGKey(123), (episodes, 2), jnp.float32, -0.75, 0.75)
    _, action = policy.act(policy.initial_carry(episodes), points, jnp.ones(episodes, bool),
                           jax.random.PRNGKey(0))  # fmt: skip
    return float(jnp.mean(jnp.linalg.norm(action - points, axis=-1)))


def cue_return(policy, episodes: int = 512) -> float:
    """Cue's mean second-step reward for the policy's deterministic actions (``c * a[0]``; 1 is
    solved; a memoryless policy's second action is one and the same for both cues: 0 on these
    episodes, half of each cue)."""
    cues = jnp.tile(jnp.array([1.0, -1.0], jnp.float32), episodes // 2)
    n = cues.shape[0]
    first = jnp.stack([cues, jnp.ones(n, jnp.float32)], axis=-1)
    key = jax.random.PRNGKey(0)
    carry, _ = policy.act(policy.initial_carry(n), first, jnp.ones(n, bool), key)
    _, action = policy.act(carry, jnp.zeros((n, 2), jnp.float32), jnp.zeros(n, bool), key)
    return float(jnp.mean(cues * action[:, 0]))
