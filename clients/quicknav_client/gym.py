"""Gymnasium adapters over a Rollout stream: any gymnasium agent trains on remote QuickNav envs.

``RemoteVectorEnv`` is a ``gymnasium.vector.VectorEnv`` with same-step auto-reset (the protocol's):
when env i ends, ``obs[i]`` is already the first observation of its next episode and the last one
is in ``info["final_obs"][i]`` (mask ``info["_final_obs"]``), as gymnasium's
``AutoresetMode.SAME_STEP`` prescribes. ``RemoteEnv`` is a single ``gymnasium.Env`` (one env per
stream) for tools that expect one, such as gymnasium's env checker.

With ``groups`` > 1, ``RemoteVectorEnv`` also has EnvPool's asynchronous interface: the envs are
split into groups stepped on their own, ``recv()`` returns the next group that is ready (its
``info["env_id"]`` says which envs) and ``send(actions, env_id)`` sends that group's actions back,
so the server steps one group while the agent works on another::

    env = RemoteVectorEnv(target, num_envs=4096, groups=2)
    env.async_reset()
    while training:
        obs, rew, term, trunc, info = env.recv()
        env.send(policy(obs), info["env_id"])

Needs the ``gym`` extra: ``pip install "quicknav-client[gym]"``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

try:
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, VectorEnv
    from gymnasium.vector.utils import batch_space
except ImportError as e:  # pragma: no cover - depends on the install
    raise ImportError(
        "quicknav_client.gym needs gymnasium: pip install 'quicknav-client[gym]'"
    ) from e

from quicknav_client.rollout import RolloutClient, Space


def _box(space: Space) -> gym.spaces.Box:
    return gym.spaces.Box(
        low=space.low.astype(np.float32), high=space.high.astype(np.float32), dtype=np.float32
    )


def _seed_of(seed: int | list[int] | None) -> int | None:
    if seed is None or isinstance(seed, int | np.integer):
        return None if seed is None else int(seed)
    raise ValueError(
        f"seed={seed!r}: a RemoteVectorEnv takes one int seed for the whole batch (each env's"
        " episodes follow from it)"
    )


class RemoteVectorEnv(VectorEnv):
    """``num_envs`` QuickNav envs stepped on a remote server, one gRPC message per batch step."""

    metadata: ClassVar[dict] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        target: str = "127.0.0.1:50051",
        num_envs: int = 1,
        config: dict[str, Any] | str | None = None,
        seed: int = 0,
        split: str = "train",
        token: str | None = None,
        client: RolloutClient | None = None,
        groups: int = 1,
    ):
        self.client = client or RolloutClient(target, token=token)
        started = self.client.start(num_envs=num_envs, seed=seed, config=config, split=split,
                                    groups=groups)  # fmt: skip
        self.groups = started.groups
        self.group_size = started.num_envs // started.groups
        self._ready: list[tuple[int, np.ndarray]] = []  # (group, first observations) to recv
        self.num_envs = started.num_envs
        self.env_config = started.env_config
        self.max_steps = started.max_steps
        self.single_observation_space = _box(started.observation_space)
        self.single_action_space = _box(started.action_space)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._first_obs = started.observations
        self._closed = False

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """New episodes in every env; the same seed gives the same episodes."""
        s = _seed_of(seed)
        if s is None and self._first_obs is not None:
            obs = self._first_obs  # the episodes Start already began
        else:
            obs = self.client.reset(s)
        self._first_obs = None
        return np.array(obs), {}

    def step(self, actions):
        t = self.client.step(np.asarray(actions, np.float32).reshape(self.num_envs, -1))
        self._first_obs = None
        return _step_result(t, self.num_envs)

    # ------------------------------------------------------------------ asynchronous mode
    def async_reset(self) -> None:
        """Start (or restart) asynchronous stepping: every group's first observations are the
        next ``recv()`` results, group by group."""
        obs = self._first_obs if self._first_obs is not None else self.client.reset()
        self._first_obs = None
        k = self.group_size
        self._ready = [(g, np.array(obs[g * k:(g + 1) * k])) for g in range(self.groups)]

    def recv(self):
        """The next ready group: ``(obs, rewards, terminated, truncated, info)`` for its envs,
        ``info["env_id"]`` their indices (all zeros and False for a group's first observations)."""
        k = self.group_size
        if self._ready:
            g, obs = self._ready.pop(0)
            zeros = np.zeros(k, bool)
            return obs, np.zeros(k, np.float32), zeros, zeros.copy(), {"env_id": self._ids(g)}
        t = self.client.recv()
        obs, rew, term, trunc, info = _step_result(t, k)
        info["env_id"] = self._ids(t.group)
        return obs, rew, term, trunc, info

    def send(self, actions, env_id=None) -> None:
        """Send one group's actions; ``env_id`` is the ``info["env_id"]`` its ``recv()`` gave."""
        k = self.group_size
        ids = np.arange(k) if env_id is None else np.asarray(env_id)
        group = int(ids[0]) // k if ids.size else -1
        if ids.shape != (k,) or not np.array_equal(ids, self._ids(group)):
            raise ValueError(f"env_id must be one group's ids as recv() gave them ({k} envs,"
                             f" a multiple of {k} up); got {ids[:8].tolist()}")  # fmt: skip
        self.client.send(np.asarray(actions, np.float32).reshape(k, -1), group=group)

    def _ids(self, group: int) -> np.ndarray:
        return np.arange(group * self.group_size, (group + 1) * self.group_size)

    def close_extras(self, **kwargs) -> None:
        if not self._closed:
            self._closed = True
            self.client.close()


def _step_result(t, n: int):
    """A Transition as gymnasium's step tuple, with same-step auto-reset's final observations."""
    info: dict[str, Any] = {"collision": t.collisions, "_collision": np.ones(n, bool)}
    if t.done_indices.size:
        final = np.full(n, None, dtype=object)
        for j, i in enumerate(t.done_indices):
            final[i] = np.array(t.final_observations[j])
        mask = np.zeros(n, bool)
        mask[t.done_indices] = True
        info["final_obs"] = final
        info["_final_obs"] = mask
    return np.array(t.observations), np.array(t.rewards), np.array(t.terminated), \
        np.array(t.truncated), info  # fmt: skip


class RemoteEnv(gym.Env):
    """One remote QuickNav env as a ``gymnasium.Env`` (call ``reset`` after an episode ends)."""

    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(
        self,
        target: str = "127.0.0.1:50051",
        config: dict[str, Any] | str | None = None,
        seed: int = 0,
        split: str = "train",
        token: str | None = None,
    ):
        self.client = RolloutClient(target, token=token)
        started = self.client.start(num_envs=1, seed=seed, config=config, split=split)
        self.env_config = started.env_config
        self.observation_space = _box(started.observation_space)
        self.action_space = _box(started.action_space)
        self._seed = seed

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is None:
            # continue the session's key stream, seeded from the np_random gymnasium keeps
            seed = int(self.np_random.integers(0, 2**63 - 1))
        obs = self.client.reset(seed)
        return np.array(obs[0]), {}

    def step(self, action):
        t = self.client.step(np.asarray(action, np.float32).reshape(1, 2))
        # the server auto-resets: report the finished episode's last observation
        obs = t.final_observations[0] if t.done_indices.size else t.observations[0]
        info = {"collision": bool(t.collisions[0])}
        return np.array(obs), float(t.rewards[0]), bool(t.terminated[0]), \
            bool(t.truncated[0]), info  # fmt: skip

    def close(self) -> None:
        self.client.close()
