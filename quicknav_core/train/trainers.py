"""Trainers behind one interface: rejax's PPO/SAC/TD3 for memoryless MLPs, our recurrent PPO otherwise.

``make_trainer(TrainConfig, runtime)`` returns a ``Trainer`` (on the env its config builds; ``env=``
gives it another, a test's probe env) with
  init_state() -> state              (from the config's seed)
  run_unit(state) -> (state, unit metrics)   one compiled call of ``updates_per_unit`` updates
  finish_chunk(state, [unit metrics]) -> (state, metrics)   a chunk's metrics, episode totals cleared
  run_chunk(state) -> (state, metrics)   ``updates_per_chunk`` updates (units), then finish_chunk
  env_steps(state) -> int
  policy(state) -> Policy                for evaluation and serving
  to_bytes(state) / from_bytes(data)     checkpoints (msgpack via flax.serialization, no pickle)
  train_batch(configs, env_params, on_chunk)   several trials that differ only in traced numbers,
                                         side by side in one compiled program (``train.batched``)

No trainer reads ``info["final_obs"]`` (rejax's PPO and ours treat a truncation like an ending),
so trainers build their env with ``final_obs`` off and skip its second lidar cast per step.

Data parallel (``TrainConfig.devices`` > 1): the state's per-env fields (env states, observations,
recurrent carries, episode statistics: ``BATCH_FIELDS``) are sharded over a one-axis device mesh
along the env batch, everything else (parameters, optimiser state, keys) is replicated, and the
chunk is compiled for those shardings. XLA's SPMD partitioner then runs each device's slice of the
rollout where it lives and sums the loss gradient over devices (an all-reduce: the pmean of
data-parallel training), so the run computes what the one-device run computes, up to the order of
float reductions. PPO's minibatches are drawn from the whole batch, as on one device. SAC and TD3
shard their env stepping the same way; their replay buffer and updates stay replicated.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import serialization

from quicknav_core.config import PPOConfig, SACConfig, TD3Config, TrainConfig, traced_fields
from quicknav_core.networks import make_network
from quicknav_core.runtime import Runtime, runtime_or_new
from quicknav_core.train.recurrent_ppo import PPOHyper, RecurrentPPO
from quicknav_core.train.stats import StatsWrapper, summarize

# A chunk callback of batched training: (chunk index, per-trial metrics) -> stop?
ChunkCallback = Callable[[int, list[dict[str, float]]], bool | None]


def _stack(trees: list) -> Any:
    return jax.tree.map(lambda *a: jnp.stack(a), *trees)


def _unstack(tree: Any, k: int) -> list:
    return [jax.tree.map(lambda x, i=i: x[i], tree) for i in range(k)]


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
    # the Gaussian's mean, computed as rejax's ``_action_dist`` does without building the
    # distribution (distrax objects cannot be traced for export)
    return module.action_mean(module.features(obs))


def _sac_mode(module, obs):
    return module.action_loc + jnp.tanh(module.action_mean(module.features(obs))) * module.action_scale


# --------------------------------------------------------------------------- base
# Env steps of one compiled call ("unit"), at least one update: small enough that progress,
# cancellation and time-bounded chunks happen within about a second on a CPU, large enough that
# the call's dispatch costs nothing next to it.
UNIT_STEPS = 4096


def local_devices(requested: int | str) -> list:
    """The devices a run spans: the first ``requested`` local devices (or all of them); a
    ValueError naming ``devices`` when the process has fewer."""
    devices = jax.local_devices()
    if requested == "all":
        return devices
    if requested > len(devices):
        raise ValueError(
            f"devices={requested} but this process sees {len(devices)} {devices[0].platform}"
            f" device(s); allowed: 1..{len(devices)} or 'all'"
        )
    return devices[:requested]


def _largest_divisor_at_most(n: int, cap: int) -> int:
    return max(d for d in range(1, min(n, max(cap, 1)) + 1) if n % d == 0)


class Trainer:
    """A training run's compiled programs. The run is ``num_updates`` updates: the fewest whole
    units that make ``total_steps`` env steps (a unit is one update for PPO). Chunks (metrics,
    checkpoints, progress) are ``updates_per_chunk`` updates of units; the unit sequence, and so
    the result, does not depend on how units are grouped into chunks."""

    config: TrainConfig
    # top-level state fields whose leading axis is the env batch (sharded over devices)
    BATCH_FIELDS: tuple[str, ...] = ()

    def __init__(self, config: TrainConfig, runtime: Runtime | None = None, env: tuple | None = None):
        self.config = config
        self.runtime = runtime_or_new(runtime)
        self.devices = local_devices(config.devices)
        if config.num_envs % len(self.devices):
            raise ValueError(
                f"devices={config.devices} gives {len(self.devices)} devices, which must divide"
                f" num_envs={config.num_envs}; allowed: a device count that divides num_envs"
            )
        self.mesh = (jax.sharding.Mesh(self.devices, ("envs",)) if len(self.devices) > 1
                     else None)  # fmt: skip
        if env is not None:
            # (env, params) instead of config.env's: a probe env that learns in seconds (tests), any
            # gymnax env whose step reports info["goal_reached"] and info["collision"]
            if config.curriculum.enabled:
                raise ValueError("curriculum.enabled draws its pool from config.env; a trainer given"
                                 " its own env takes curriculum.enabled=false")  # fmt: skip
            self.env, self.env_params = env
        else:
            # nothing here reads the final observations: do not pay a second lidar cast for them
            self.env, self.env_params = config.env.model_copy(update={"final_obs": False}).build(
                "train", self.runtime
            )
        self.pool = None
        if config.curriculum.enabled:
            from quicknav_core.train.curriculum import first_level, make_pool, with_pool

            self.pool = make_pool(self.env_params, config.env, config.curriculum, config.seed)
            start = self.pool.level_counts[first_level(self.pool)]
            self.env_params = with_pool(self.env_params, self.pool, start)
        updates = max(1, math.ceil(config.total_steps / config.steps_per_update))
        self.updates_per_chunk = min(config.updates_per_chunk, updates)
        unit_cap = math.ceil(UNIT_STEPS / config.steps_per_update)
        self.updates_per_unit = _largest_divisor_at_most(self.updates_per_chunk, unit_cap)
        self.num_updates = math.ceil(updates / self.updates_per_unit) * self.updates_per_unit

    @property
    def steps_per_chunk(self) -> int:
        return self.updates_per_chunk * self.config.steps_per_update

    @property
    def steps_per_unit(self) -> int:
        return self.updates_per_unit * self.config.steps_per_update

    @property
    def total_env_steps(self) -> int:
        """Env steps the whole run makes (``total_steps`` rounded up to whole units)."""
        return self.num_updates * self.config.steps_per_update

    def updates_done(self, state) -> int:
        return self.env_steps(state) // self.config.steps_per_update

    def init_state(self) -> Any:
        raise NotImplementedError

    def run_unit(self, state) -> tuple[Any, Any]:
        """One compiled call of ``updates_per_unit`` updates; returns when it has finished."""
        raise NotImplementedError

    def finish_chunk(self, state, units: list) -> tuple[Any, dict[str, float]]:
        """The chunk's metrics (algorithm metrics averaged over its units, episode statistics
        since the last chunk) and the state with the episode totals cleared."""
        raise NotImplementedError

    def run_chunk(self, state) -> tuple[Any, dict[str, float]]:
        """``updates_per_chunk`` updates (fewer if the run ends sooner), then the chunk's metrics."""
        units = []
        target = min(self.num_updates, self.updates_done(state) + self.updates_per_chunk)
        while self.updates_done(state) < target:
            state, metrics = self.run_unit(state)
            units.append(metrics)
        return self.finish_chunk(state, units)

    def env_steps(self, state) -> int:
        raise NotImplementedError

    def policy(self, state) -> Policy:
        raise NotImplementedError

    def pool_count(self, state) -> int:
        """Curriculum: the episodes of the pool in use (the level), read from the state."""
        raise NotImplementedError

    def with_pool_count(self, state, count: int) -> Any:
        raise NotImplementedError

    def curriculum(self, state, metrics: dict[str, float]) -> tuple[Any, dict[str, float]]:
        """After a chunk: record the level it trained at and open the next one when the chunk's
        training success reached ``curriculum.promote_at``. The level lives in the state (it is
        checkpointed, and changing it recompiles nothing)."""
        if self.pool is None:
            return state, metrics
        level = self.pool.level_of(self.pool_count(state))
        metrics = {**metrics, "curriculum_level": float(level),
                   "curriculum_max_path": self.pool.max_length(level)}  # fmt: skip
        success = metrics.get("success_rate", float("nan"))
        last = len(self.pool.level_counts) - 1
        if level < last and success >= self.config.curriculum.promote_at:
            nxt = level + 1
            while nxt < last and self.pool.level_counts[nxt] == self.pool.level_counts[level]:
                nxt += 1  # a level that adds no episode is skipped
            state = self.place(self.with_pool_count(state, self.pool.level_counts[nxt]))
        return state, metrics

    def to_bytes(self, state, with_replay: bool = True) -> bytes:
        """The state as msgpack (flax); without the replay buffer if ``with_replay`` is False."""
        data = serialization.to_state_dict(jax.device_get(state))
        if not with_replay:
            data = {k: v for k, v in data.items() if k != "replay_buffer"}
        return serialization.msgpack_serialize(data)

    def has_replay(self, state) -> bool:
        return hasattr(state, "replay_buffer")

    def replay_to_bytes(self, state) -> bytes:
        return serialization.to_bytes(jax.device_get(state.replay_buffer))

    def with_replay_bytes(self, state, data: bytes):
        """``state`` with the replay buffer ``replay_to_bytes`` gave."""
        buffer = serialization.from_bytes(jax.device_get(state.replay_buffer), data)
        return self.place(state.replace(replay_buffer=buffer))

    def from_bytes(self, data: bytes):
        """A state from ``to_bytes``; fields added since the checkpoint was written (the
        curriculum's ``pool_count``) take their fresh values instead of failing the restore.

        The state's structure and shapes come from tracing ``init_state`` (``jax.eval_shape``):
        nothing is compiled or computed, as loading needs none of its values. Only a checkpoint
        that lacks a field pays for a real ``init_state``, for that field's value."""
        raw = serialization.msgpack_restore(data)
        target = jax.eval_shape(self.init_state)
        fresh = serialization.to_state_dict(target)
        if _lacks_a_field(fresh, raw):
            target = jax.device_get(self.init_state())
            fresh = serialization.to_state_dict(target)
        loaded = _with_missing(fresh, raw)
        _check_shapes(fresh, loaded, self.config)
        return self.place(serialization.from_state_dict(target, loaded))

    def state_sharding(self, state) -> Any:
        """Per leaf: split along the env batch (a ``BATCH_FIELDS`` leaf) or replicated."""
        from jax.sharding import NamedSharding, PartitionSpec

        split = NamedSharding(self.mesh, PartitionSpec("envs"))
        whole = NamedSharding(self.mesh, PartitionSpec())

        def pick(path, leaf):
            top = getattr(path[0], "name", None) if path else None
            batched = (top in self.BATCH_FIELDS and getattr(leaf, "ndim", 0) >= 1
                       and leaf.shape[0] == self.config.num_envs)  # fmt: skip
            return split if batched else whole

        return jax.tree_util.tree_map_with_path(pick, state)

    def place(self, state) -> Any:
        """The state on this run's devices (unchanged on one device)."""
        if self.mesh is None:
            return state
        return jax.device_put(state, self.state_sharding(state))

    def compile_sharded(self, fn: Callable, state) -> Callable:
        """``fn(state) -> (state, metrics)`` compiled to keep the state's shardings."""
        sharding = self.state_sharding(state)
        return jax.jit(fn, in_shardings=(sharding,), out_shardings=(sharding, None))

    def train_batch(self, configs: list[TrainConfig], env_params: list, on_chunk: ChunkCallback | None = None):
        """Train ``configs`` (this trainer's config up to traced numbers) side by side.

        ``env_params[i]`` are trial i's env params (its reward weights). Returns (per-trial final
        states, history: per chunk, per-trial episode metrics).
        """
        raise NotImplementedError


def _with_missing(fresh: Any, loaded: Any) -> Any:
    """``loaded`` (a restored state dict) with the keys only ``fresh`` has filled in from it."""
    if not isinstance(fresh, dict) or not isinstance(loaded, dict):
        return loaded
    return {k: _with_missing(v, loaded[k]) if k in loaded else v for k, v in fresh.items()}


def _lacks_a_field(fresh: Any, loaded: Any) -> bool:
    """Whether a restored state dict lacks a key the fresh one has (at any depth)."""
    if not isinstance(fresh, dict) or not isinstance(loaded, dict):
        return False
    return any(k not in loaded or _lacks_a_field(v, loaded[k]) for k, v in fresh.items())


def policy_from_bytes(config: TrainConfig, data: bytes) -> Policy:
    """The policy of a checkpoint (``Trainer.to_bytes``) of ``config``'s trainer, read without
    building the trainer: its network (from ``config.network``) and the parameters the state holds
    for it. Evaluation, export and the Policy stream need nothing else: no room bank, no
    algorithm, no state traced. A ValueError names an array whose shape the config does not give."""
    raw = serialization.msgpack_restore(data)
    obs_dim, key = config.env.obs_dim, jax.random.PRNGKey(0)
    obs = jnp.zeros((1, obs_dim), jnp.float32)
    if config.trainer_kind == "recurrent-ppo":
        module: nn.Module = make_network(config.network, obs_dim=obs_dim)
        kind, where = "recurrent", ("params",)
        start = jnp.ones((1,), bool)
        expected = jax.eval_shape(lambda k: module.init(k, module.initial_carry(1), obs, start), key)
    else:
        from quicknav_core.train.rejax_parts import rejax_networks

        module = rejax_networks(config)["actor"]
        kind, where = config.trainer_kind, ("actor_ts", "params")
        # rejax's own call: PPO's and SAC's actors take a key after the observations
        extra = () if kind == "rejax-td3" else (key,)
        expected = jax.eval_shape(lambda k: module.init(k, obs, *extra), key)
    params = raw
    for name in where:
        if not isinstance(params, dict) or name not in params:
            raise ValueError(f"checkpoint has no /{'/'.join(where)}: not a {config.trainer_kind}"
                             " checkpoint of this run's config")  # fmt: skip
        params = params[name]
    want = serialization.to_state_dict(expected)
    _check_shapes(want, params, config, "/" + "/".join(where))
    if jax.tree.structure(want) != jax.tree.structure(params):
        raise ValueError(f"checkpoint's /{'/'.join(where)} holds other arrays than this run's"
                         f" network ({config.network.kind}) has")  # fmt: skip
    return Policy(kind, module, jax.tree.map(jnp.asarray, params))


def _check_shapes(fresh: Any, loaded: Any, config: TrainConfig, path: str = "") -> None:
    """A ValueError naming the first array of a checkpoint whose shape is not what the config's
    network and buffers give (instead of flax failing later, in the middle of an evaluation)."""
    if isinstance(fresh, dict) and isinstance(loaded, dict):
        for k, v in fresh.items():
            if k in loaded:
                _check_shapes(v, loaded[k], config, f"{path}/{k}")
        return
    want, got = getattr(fresh, "shape", None), getattr(loaded, "shape", None)
    if want is not None and got is not None and tuple(want) != tuple(got):
        hint = ""
        if config.trainer_kind == "rejax-sac":
            hint = (" (SAC checkpoints written before QuickNav 0.2 hold 64x64 networks whatever"
                    " network.hidden_sizes said: rejax ignored it; set network.hidden_sizes to"
                    " [64, 64] in the run's config.json to load one)")  # fmt: skip
        raise ValueError(f"checkpoint array {path} has shape {tuple(got)}; this run's config"
                         f" gives {tuple(want)}{hint}")  # fmt: skip


def _floats(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items()}


def _mean_of_units(units: list[dict[str, Any]]) -> dict[str, float]:
    """Algorithm metrics averaged over a chunk's units (units have equal numbers of updates)."""
    if not units:
        return {}
    host = jax.device_get(units)
    return {k: float(sum(float(u[k]) for u in host) / len(host)) for k in host[0]}


# --------------------------------------------------------------------------- recurrent PPO
class RecurrentPPOTrainer(Trainer):
    """QuickNav's recurrent PPO (any network, memoryless included)."""

    BATCH_FIELDS = ("env_state", "obs", "start", "carry", "stats")

    def __init__(self, config: TrainConfig, runtime: Runtime | None = None, env: tuple | None = None):
        super().__init__(config, runtime, env)
        algo: PPOConfig = config.algorithm
        self.network = make_network(config.network, obs_dim=self.env.obs_dim)
        self.algo = RecurrentPPO(
            self.env, self.env_params, self.network, num_envs=config.num_envs,
            num_steps=algo.num_steps, num_minibatches=algo.num_minibatches,
            num_epochs=algo.num_epochs, total_updates=self.num_updates, anneal_lr=algo.anneal_lr,
        )  # fmt: skip
        self._batched: dict[int, tuple] = {}
        self._clear = jax.jit(jax.vmap(lambda s: s.clear_totals()))
        self._sharded_unit = None

    def init_state(self):
        return self.place(self.algo.init(
            jax.random.PRNGKey(self.config.seed), PPOHyper.from_config(self.config.algorithm)
        ))  # fmt: skip

    def run_unit(self, state):
        if self.mesh is None:
            state, metrics = self.algo.train_chunk(state, self.updates_per_unit)
        else:
            if self._sharded_unit is None:
                algo, n = self.algo, self.updates_per_unit
                self._sharded_unit = self.compile_sharded(lambda s: algo.chunk(s, n), state)
            state, metrics = self._sharded_unit(state)
        return jax.block_until_ready((state, metrics))

    def finish_chunk(self, state, units):
        out = _mean_of_units(units)
        out.update(summarize(state.stats))
        state = state.replace(stats=self._clear(state.stats))
        # (the cleared totals may come back laid out otherwise: place again)
        return self.curriculum(self.place(state), out)

    def env_steps(self, state) -> int:
        return int(state.update) * self.config.steps_per_update

    def pool_count(self, state) -> int:
        return int(state.env_params.pool_count)

    def with_pool_count(self, state, count: int):
        return state.replace(env_params=state.env_params.replace(pool_count=jnp.int32(count)))

    def policy(self, state) -> Policy:
        return Policy("recurrent", self.network, state.params)

    def train_batch(self, configs, env_params, on_chunk=None):
        k = len(configs)
        if k not in self._batched:
            algo, updates = self.algo, self.updates_per_unit
            self._batched[k] = (
                jax.jit(jax.vmap(algo.init, in_axes=(None, 0, 0))),
                jax.jit(jax.vmap(lambda s: algo.chunk(s, updates))),
                jax.jit(jax.vmap(lambda s: s.replace(stats=jax.vmap(lambda x: x.clear_totals())(s.stats)))),
            )  # fmt: skip
        init, unit, clear = self._batched[k]
        hypers = _stack([PPOHyper.from_config(c.algorithm) for c in configs])
        states = init(jax.random.PRNGKey(configs[0].seed), hypers, _stack(env_params))
        history: list[list[dict[str, float]]] = []
        done = 0
        while done < self.num_updates:
            target = min(self.num_updates, done + self.updates_per_chunk)
            while done < target:
                states, _ = unit(states)
                done += self.updates_per_unit
            per_trial = [summarize(s) for s in _unstack(states.stats, k)]
            history.append(per_trial)
            states = clear(states)
            if on_chunk and on_chunk(len(history) - 1, per_trial):
                break
        return _unstack(states, k), history


# --------------------------------------------------------------------------- rejax
class RejaxTrainer(Trainer):
    """rejax's PPO, SAC or TD3 on QuickNav (wrapped to record episode statistics)."""

    BATCH_FIELDS = ("env_state", "last_obs", "last_done", "rew_rms_state")

    def __init__(self, config: TrainConfig, runtime: Runtime | None = None, env: tuple | None = None):
        super().__init__(config, runtime, env)
        import rejax

        from quicknav_core.train import rejax_parts

        algo = config.algorithm
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
            }  # fmt: skip
        elif isinstance(algo, SACConfig):
            self.kind = "rejax-sac"
            cls = rejax_parts.SAC
            kwargs = {
                "batch_size": algo.batch_size, "buffer_size": algo.buffer_size,
                "fill_buffer": algo.fill_buffer, "polyak": algo.polyak,
                "target_entropy_ratio": algo.target_entropy_ratio,
                "target_update_freq": algo.target_update_freq, "num_epochs": algo.num_epochs,
            }  # fmt: skip
        elif isinstance(algo, TD3Config):
            self.kind = "rejax-td3"
            cls = rejax_parts.TD3
            kwargs = {
                "batch_size": algo.batch_size, "buffer_size": algo.buffer_size,
                "fill_buffer": algo.fill_buffer, "polyak": algo.polyak,
                "exploration_noise": algo.exploration_noise, "target_noise": algo.target_noise,
                "target_noise_clip": algo.target_noise_clip, "policy_delay": algo.policy_delay,
                "num_epochs": algo.num_epochs,
            }  # fmt: skip
        else:  # pragma: no cover - config validation prevents this
            raise TypeError(type(algo).__name__)
        steps = self.steps_per_unit
        created = cls.create(total_timesteps=steps, eval_freq=steps, **common, **kwargs)
        # rejax's own networks are not always what the config names (see rejax_parts)
        created = created.replace(**rejax_parts.rejax_networks(config))
        # One unit = one rejax "eval iteration" (its callback is a no-op: the env wrapper counts
        # episode statistics); calling it again continues from the train state.
        self.algo = created.replace(eval_callback=_stats_callback)
        self._sharded_train = None  # compiled on first use when the run spans several devices
        self._clear = jax.jit(jax.vmap(lambda s: s.clear_totals()))
        self._batched: dict[int, Any] = {}

    def init_state(self):
        from quicknav_core.train.rejax_parts import shareable_state

        state = self.algo.init_state(jax.random.PRNGKey(self.config.seed))
        algo = self.config.algorithm
        return self.place(shareable_state(state, algo.learning_rate, algo.max_grad_norm,
                                          self.runtime))  # fmt: skip

    def run_unit(self, state):
        if self.mesh is None:
            return jax.block_until_ready(_rejax_unit(self.algo, state)), {}
        if self._sharded_train is None:
            algo = self.algo
            self._sharded_train = self.compile_sharded(
                lambda ts: (algo.train(train_state=ts)[0], {}), state
            )
        return jax.block_until_ready(self._sharded_train(state)[0]), {}

    def finish_chunk(self, state, units):
        out = summarize(state.env_state.stats)
        env_state = state.env_state.replace(stats=self._clear(state.env_state.stats))
        return self.curriculum(self.place(state.replace(env_state=env_state)), out)

    def env_steps(self, state) -> int:
        return int(state.global_step)

    def pool_count(self, state) -> int:
        return int(state.env_state.pool_count[0])

    def with_pool_count(self, state, count: int):
        env_state = state.env_state
        pool = jnp.full_like(env_state.pool_count, count)
        return state.replace(env_state=env_state.replace(pool_count=pool))

    def policy(self, state) -> Policy:
        return Policy(self.kind, self.algo.actor, state.actor_ts.params)

    def train_batch(self, configs, env_params, on_chunk=None):
        # rejax builds its optimiser (a static closure over the learning rate) in init_state, so
        # init and training sit inside one vmapped call: the group trains in one go, one "chunk".
        k = len(configs)
        steps = self.num_updates * self.config.steps_per_update
        full = self.algo.replace(total_timesteps=steps, eval_freq=self.steps_per_unit)
        names = sorted(traced_fields(type(self.config.algorithm)))

        def trial(cfg: TrainConfig, params):
            numbers = {n: jnp.float32(getattr(cfg.algorithm, n)) for n in names if hasattr(full, n)}
            return full.replace(env_params=params, **numbers)

        algos = _stack([trial(c, p) for c, p in zip(configs, env_params, strict=True)])
        if k not in self._batched:
            self._batched[k] = jax.jit(jax.vmap(lambda a, key: a.train(key)[0], in_axes=(0, None)))
        final = self._batched[k](algos, jax.random.PRNGKey(configs[0].seed))
        per_trial = [summarize(s) for s in _unstack(final.env_state.stats, k)]
        if on_chunk:
            on_chunk(0, per_trial)
        return _unstack(final, k), [per_trial]


def _stats_callback(algo, ts, rng):
    return jnp.zeros(())


@jax.jit
def _rejax_unit(algo, train_state):
    """One unit of a rejax algorithm. The algorithm is an argument, not a closure: its numbers
    (learning rate, env params with the room bank) are traced, so runs that differ only in them
    share one compiled program."""
    return algo.train(train_state=train_state)[0]


def make_trainer(config: TrainConfig, runtime: Runtime | None = None, env: tuple | None = None) -> Trainer:
    """The trainer for a config (``config.trainer_kind`` says which); its room banks and
    shareable compiled parts come from ``runtime``. ``env``: (env, params) to train on instead of
    the env ``config.env`` builds (the tests' probe envs, ``tests/core/train/probes.py``)."""
    if config.trainer_kind == "recurrent-ppo":
        return RecurrentPPOTrainer(config, runtime, env)
    return RejaxTrainer(config, runtime, env)
