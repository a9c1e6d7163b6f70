"""Trainers behind one interface: rejax's PPO/SAC/TD3 for memoryless MLPs, our recurrent PPO otherwise.

``make_trainer(TrainConfig)`` returns a ``Trainer`` with
  init_state() -> state              (from the config's seed)
  run_chunk(state) -> (state, metrics)   one jit-compiled chunk of ``updates_per_chunk`` updates
  env_steps(state) -> int
  policy(state) -> Policy                for evaluation and serving
  to_bytes(state) / from_bytes(data)     checkpoints (msgpack via flax.serialization, no pickle)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import serialization

from quicknav_core.config import PPOConfig, SACConfig, TD3Config, TrainConfig
from quicknav_core.networks import make_network
from quicknav_core.train.recurrent_ppo import PPOHyper, RecurrentPPO
from quicknav_core.train.stats import StatsWrapper, summarize


# --------------------------------------------------------------------------- policies
@dataclass(frozen=True)
class Policy:
    """A trained policy with the recurrent interface, whatever trained it.

    ``act(carry, obs (B, O), start (B,), key, deterministic)`` -> ``(carry, action (B, 2) in [-1, 1])``.
    """

    kind: str  # "recurrent" | "rejax-ppo" | "rejax-sac" | "rejax-td3"
    module: nn.Module
    params: Any

    def initial_carry(self, batch_size: int):
        if self.kind == "recurrent":
            return self.module.initial_carry(batch_size)
        return ()

    def act(self, carry, obs, start, key, deterministic: bool = True):
        if self.kind == "recurrent":
            carry, out = self.module.apply(self.params, carry, obs, start)
            raw = out.mean
            if not deterministic:
                raw = raw + jnp.exp(out.log_std) * jax.random.normal(key, raw.shape)
            return carry, jnp.clip(raw, -1.0, 1.0)
        if deterministic:
            if self.kind == "rejax-ppo":
                action = self.module.apply(self.params, obs, method=_ppo_mean)
            elif self.kind == "rejax-sac":
                action = self.module.apply(self.params, obs, method=_sac_mode)
            else:
                action = self.module.apply(self.params, obs)
        elif self.kind == "rejax-td3":
            action = self.module.apply(self.params, obs)
            action = action + 0.1 * jax.random.normal(key, action.shape)
        else:
            action = self.module.apply(self.params, obs, key, method="act")
        return carry, jnp.clip(action, -1.0, 1.0)


def _ppo_mean(module, obs):
    return module._action_dist(obs).loc


def _sac_mode(module, obs):
    return module.action_loc + jnp.tanh(module._action_dist(obs).loc) * module.action_scale


# --------------------------------------------------------------------------- base
class Trainer:
    config: TrainConfig

    def __init__(self, config: TrainConfig):
        self.config = config
        self.env, self.env_params = config.env.build("train")
        # Whole chunks only: the run makes ``num_updates`` updates, at least ``total_steps`` steps.
        updates = max(1, math.ceil(config.total_steps / config.steps_per_update))
        self.updates_per_chunk = min(config.updates_per_chunk, updates)
        self.num_updates = math.ceil(updates / self.updates_per_chunk) * self.updates_per_chunk

    @property
    def steps_per_chunk(self) -> int:
        return self.updates_per_chunk * self.config.steps_per_update

    def init_state(self) -> Any:
        raise NotImplementedError

    def run_chunk(self, state) -> tuple[Any, dict[str, float]]:
        raise NotImplementedError

    def env_steps(self, state) -> int:
        raise NotImplementedError

    def policy(self, state) -> Policy:
        raise NotImplementedError

    def to_bytes(self, state) -> bytes:
        return serialization.to_bytes(jax.device_get(state))

    def from_bytes(self, data: bytes):
        return serialization.from_bytes(self.init_state(), data)


def _floats(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items()}


# --------------------------------------------------------------------------- recurrent PPO
class RecurrentPPOTrainer(Trainer):
    """QuickNav's recurrent PPO (any network, memoryless included)."""

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        algo: PPOConfig = config.algorithm
        self.network = make_network(config.network)
        self.algo = RecurrentPPO(
            self.env, self.env_params, self.network, num_envs=config.num_envs,
            num_steps=algo.num_steps, num_minibatches=algo.num_minibatches,
            num_epochs=algo.num_epochs, total_updates=self.num_updates, anneal_lr=algo.anneal_lr,
        )  # fmt: skip

    def init_state(self):
        return self.algo.init(
            jax.random.PRNGKey(self.config.seed), PPOHyper.from_config(self.config.algorithm)
        )

    def run_chunk(self, state):
        state, metrics = self.algo.train_chunk(state, self.updates_per_chunk)
        out = _floats(metrics)
        out.update(summarize(state.stats))
        state = state.replace(stats=jax.vmap(lambda s: s.clear_totals())(state.stats))
        return state, out

    def env_steps(self, state) -> int:
        return int(state.env_steps)

    def policy(self, state) -> Policy:
        return Policy("recurrent", self.network, state.params)


# --------------------------------------------------------------------------- rejax
class RejaxTrainer(Trainer):
    """rejax's PPO, SAC or TD3 on QuickNav (wrapped to record episode statistics)."""

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        import rejax

        algo = config.algorithm
        net = config.network
        hidden = tuple(net.hidden_sizes)
        env = StatsWrapper(self.env)
        common = {
            "env": env, "env_params": self.env_params, "num_envs": config.num_envs,
            "learning_rate": algo.learning_rate, "gamma": algo.gamma,
            "max_grad_norm": algo.max_grad_norm, "skip_initial_evaluation": True,
        }  # fmt: skip
        if isinstance(algo, PPOConfig):
            self.kind = "rejax-ppo"
            cls = rejax.PPO
            kwargs = {
                "num_steps": algo.num_steps, "num_epochs": algo.num_epochs,
                "num_minibatches": algo.num_minibatches, "gae_lambda": algo.gae_lambda,
                "clip_eps": algo.clip_eps, "ent_coef": algo.ent_coef, "vf_coef": algo.vf_coef,
                "agent_kwargs": {"hidden_layer_sizes": hidden, "activation": "relu"},
            }  # fmt: skip
        elif isinstance(algo, SACConfig):
            self.kind = "rejax-sac"
            cls = rejax.SAC
            kwargs = {
                "batch_size": algo.batch_size, "buffer_size": algo.buffer_size,
                "fill_buffer": algo.fill_buffer, "polyak": algo.polyak,
                "target_entropy_ratio": algo.target_entropy_ratio,
                "target_update_freq": algo.target_update_freq, "num_epochs": algo.num_epochs,
                "agent_kwargs": {"hidden_layer_sizes": hidden, "activation": "relu"},
            }  # fmt: skip
        elif isinstance(algo, TD3Config):
            self.kind = "rejax-td3"
            cls = rejax.TD3
            kwargs = {
                "batch_size": algo.batch_size, "buffer_size": algo.buffer_size,
                "fill_buffer": algo.fill_buffer, "polyak": algo.polyak,
                "exploration_noise": algo.exploration_noise, "target_noise": algo.target_noise,
                "target_noise_clip": algo.target_noise_clip, "policy_delay": algo.policy_delay,
                "num_epochs": algo.num_epochs,
                "actor_kwargs": {"activation": "relu"}, "critic_kwargs": {"activation": "relu"},
            }  # fmt: skip
        else:  # pragma: no cover - config validation prevents this
            raise TypeError(type(algo).__name__)
        steps = self.steps_per_chunk
        created = cls.create(total_timesteps=steps, eval_freq=steps, **common, **kwargs)
        if self.kind == "rejax-td3":
            # rejax's TD3 fixes its networks at 64x64; put the configured sizes in their place
            from rejax.networks import DeterministicPolicy, QNetwork

            created = created.replace(
                actor=DeterministicPolicy(
                    2, (-1.0, 1.0), hidden_layer_sizes=hidden, activation=nn.relu
                ),
                critic=QNetwork(hidden_layer_sizes=hidden, activation=nn.relu),
            )
        # One chunk = one rejax "eval iteration"; the callback reports our episode statistics.
        self.algo = created.replace(eval_callback=_stats_callback)
        self._train = jax.jit(lambda ts: self.algo.train(train_state=ts))

    def init_state(self):
        return self.algo.init_state(jax.random.PRNGKey(self.config.seed))

    def run_chunk(self, state):
        state, _ = self._train(state)
        out = summarize(state.env_state.stats)
        env_state = state.env_state.replace(
            stats=jax.vmap(lambda s: s.clear_totals())(state.env_state.stats)
        )
        return state.replace(env_state=env_state), out

    def env_steps(self, state) -> int:
        return int(state.global_step)

    def policy(self, state) -> Policy:
        return Policy(self.kind, self.algo.actor, state.actor_ts.params)


def _stats_callback(algo, ts, rng):
    return jnp.zeros(())


def make_trainer(config: TrainConfig) -> Trainer:
    """The trainer for a config (``config.trainer_kind`` says which)."""
    if config.trainer_kind == "recurrent-ppo":
        return RecurrentPPOTrainer(config)
    return RejaxTrainer(config)
