"""QuickNav's recurrent PPO: PPO for policies that carry memory (memory MLP, LSTM, GTrXL).

Ideas from purejaxrl's ``ppo_rnn`` written against today's Flax API and typed state:
- every transition stores the episode-start flag of its observation, and the carry is reset to its
  initial value wherever that flag is set (the network does this itself);
- the rollout keeps the carry it started from, and the loss replays whole sequences from it, so the
  log-probabilities in the loss are those recorded while acting (before the first gradient step);
- minibatches are sets of whole env sequences: shuffled across envs, never across time;
- GAE, clipped surrogate, clipped value loss, entropy bonus, global-norm gradient clipping and a
  linearly annealed learning rate.
Hyperparameters that only change numbers (learning rate, gamma, lambda, clip, coefficients) live
in the traced ``PPOHyper`` inside the state, so many of them can train side by side under vmap.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from quicknav_core.env.batch import batched_step
from quicknav_core.networks import PolicyOutput, gaussian_entropy, gaussian_log_prob
from quicknav_core.train.stats import EpisodeStats


@struct.dataclass
class PPOHyper:
    """Traced PPO hyperparameters: exactly the fields of ``PPOConfig`` marked ``TRACED``."""

    learning_rate: jax.Array
    gamma: jax.Array
    gae_lambda: jax.Array
    clip_eps: jax.Array
    ent_coef: jax.Array
    vf_coef: jax.Array
    max_grad_norm: jax.Array

    @classmethod
    def from_config(cls, algo) -> PPOHyper:
        return cls(**{f.name: jnp.float32(getattr(algo, f.name)) for f in dataclasses.fields(cls)})


@struct.dataclass
class Trajectory:
    """One rollout, time-major: (T, B, ...)."""

    obs: jax.Array  # (T, B, obs_dim)
    start: jax.Array  # (T, B) bool: obs is the first of an episode
    action: jax.Array  # (T, B, A) raw Gaussian sample (the env gets it clipped to [-1, 1])
    log_prob: jax.Array  # (T, B)
    value: jax.Array  # (T, B)
    reward: jax.Array  # (T, B)
    done: jax.Array  # (T, B) bool: the episode ended with this step


@struct.dataclass
class RecurrentPPOState:
    params: Any
    opt_state: Any
    env_state: Any  # batched EnvState
    obs: jax.Array  # (B, obs_dim) current observation
    start: jax.Array  # (B,) bool: obs starts an episode
    carry: Any  # network carry after the previous step
    key: jax.Array
    update: jax.Array  # () int32 updates done (env steps done = update * num_envs * num_steps,
    #                    counted on the host: an int32 count of env steps wrapped at 2.1 billion)
    stats: EpisodeStats  # batched (B,)
    hyper: PPOHyper
    env_params: Any  # EnvParams: traced, so reward weights can differ per vmapped trial


def explained_variance(values: jax.Array, targets: jax.Array) -> jax.Array:
    """1 - Var(targets - values) / Var(targets) over a rollout: 1 = the critic predicts the value
    targets, 0 = no better than their mean, < 0 = worse. The critic's health in one number."""
    return 1.0 - jnp.var(targets - values) / (jnp.var(targets) + 1e-8)


class RecurrentPPO:
    """PPO with recurrent policies on a gymnax env. Static shapes here; numbers in ``PPOHyper``."""

    def __init__(
        self,
        env,
        env_params,
        network: nn.Module,
        num_envs: int,
        num_steps: int,
        num_minibatches: int,
        num_epochs: int,
        total_updates: int,
        anneal_lr: bool = True,
    ):
        if num_envs % num_minibatches:
            raise ValueError(f"num_minibatches={num_minibatches} must divide num_envs={num_envs}")
        self.env = env
        self.env_params = env_params
        self.network = network
        self.num_envs = num_envs
        self.num_steps = num_steps
        self.num_minibatches = num_minibatches
        self.num_epochs = num_epochs
        self.total_updates = max(int(total_updates), 1)
        self.anneal_lr = anneal_lr
        self.optimizer = optax.scale_by_adam(eps=1e-5)

    # ------------------------------------------------------------------ state
    def init(self, key: jax.Array, hyper: PPOHyper, env_params=None) -> RecurrentPPOState:
        """Fresh parameters, optimiser state and envs."""
        env_params = self.env_params if env_params is None else env_params
        k_net, k_env, k_run = jax.random.split(key, 3)
        b = self.num_envs
        obs, env_state = jax.vmap(self.env.reset, in_axes=(0, None))(
            jax.random.split(k_env, b), env_params
        )
        carry = self.network.initial_carry(b)
        start = jnp.ones((b,), bool)
        params = self.network.init(k_net, carry, obs, start)
        return RecurrentPPOState(
            params=params,
            opt_state=self.optimizer.init(params),
            env_state=env_state,
            obs=obs,
            start=start,
            carry=carry,
            key=k_run,
            update=jnp.int32(0),
            stats=jax.vmap(lambda _: EpisodeStats.zeros())(jnp.arange(b)),
            hyper=hyper,
            env_params=env_params,
        )

    # ------------------------------------------------------------------ acting
    def policy_step(self, params, carry, obs, start, key, deterministic: bool = False):
        """One acting step: (new carry, raw action, log prob, value, PolicyOutput)."""
        carry, out = self.network.apply(params, carry, obs, start)
        if deterministic:
            raw = out.mean
        else:
            raw = out.mean + jnp.exp(out.log_std) * jax.random.normal(key, out.mean.shape)
        return carry, raw, gaussian_log_prob(out.mean, out.log_std, raw), out.value, out

    def collect(self, state: RecurrentPPOState) -> tuple[RecurrentPPOState, Trajectory, Any]:
        """Roll out ``num_steps`` steps of every env; returns the rollout's initial carry too."""
        carry0 = state.carry
        if self.env.config.observe_plan:
            # plans only for the envs whose episode ended (vmap(env.step) would plan for every
            # env every step); the same transitions, see env.batch.batched_step
            def vstep(keys, env_state, action, params):
                obs, env_state, reward, info, _ = batched_step(self.env, keys, env_state, action,
                                                               params)  # fmt: skip
                return obs, env_state, reward, info["terminated"] | info["truncated"], info
        else:
            vstep = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))

        def step(s: RecurrentPPOState, _):
            key, k_act, k_env = jax.random.split(s.key, 3)
            carry, raw, logp, value, _ = self.policy_step(s.params, s.carry, s.obs, s.start, k_act)
            obs, env_state, reward, done, info = vstep(
                jax.random.split(k_env, self.num_envs), s.env_state, jnp.clip(raw, -1.0, 1.0),
                s.env_params,
            )  # fmt: skip
            stats = jax.vmap(EpisodeStats.record)(
                s.stats, reward, done, info["goal_reached"], info["collision"]
            )
            tr = Trajectory(s.obs, s.start, raw, logp, value, reward, done)
            s = s.replace(
                env_state=env_state, obs=obs, start=done, carry=carry, key=key, stats=stats,
            )  # fmt: skip
            return s, tr

        state, traj = jax.lax.scan(step, state, None, self.num_steps)
        return state, traj, carry0

    # ------------------------------------------------------------------ learning
    @staticmethod
    def gae(traj: Trajectory, last_value: jax.Array, gamma, lam) -> tuple[jax.Array, jax.Array]:
        """Generalised advantage estimates and value targets, (T, B) each."""

        def back(next_, t):
            adv_next, value_next = next_
            not_done = 1.0 - t.done.astype(jnp.float32)
            delta = t.reward + gamma * value_next * not_done - t.value
            adv = delta + gamma * lam * not_done * adv_next
            return (adv, t.value), adv

        _, adv = jax.lax.scan(back, (jnp.zeros_like(last_value), last_value), traj, reverse=True)
        return adv, adv + traj.value

    def replay(self, params, carry0, traj: Trajectory) -> PolicyOutput:
        """Run the network over a whole (T, b) sequence from its initial carry."""
        if getattr(self.network, "parallel_sequence", False):  # GTrXL: all steps at once
            return self.network.apply(params, carry0, traj.obs, traj.start)[1]

        def step(carry, xs):
            obs, start = xs
            carry, out = self.network.apply(params, carry, obs, start)
            return carry, out

        _, outs = jax.lax.scan(step, carry0, (traj.obs, traj.start))
        return outs

    def loss(self, params, carry0, traj: Trajectory, adv, targets, hyper: PPOHyper):
        out = self.replay(params, carry0, traj)
        logp = gaussian_log_prob(out.mean, out.log_std, traj.action)
        ratio = jnp.exp(logp - traj.log_prob)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = -jnp.minimum(
            ratio * adv, jnp.clip(ratio, 1 - hyper.clip_eps, 1 + hyper.clip_eps) * adv
        )
        v_clipped = traj.value + jnp.clip(out.value - traj.value, -hyper.clip_eps, hyper.clip_eps)
        v_loss = 0.5 * jnp.maximum((out.value - targets) ** 2, (v_clipped - targets) ** 2).mean()
        entropy = gaussian_entropy(out.log_std).mean()
        total = pg.mean() + hyper.vf_coef * v_loss - hyper.ent_coef * entropy
        aux = {
            "policy_loss": pg.mean(),
            "value_loss": v_loss,
            "entropy": entropy,
            "approx_kl": ((ratio - 1.0) - (logp - traj.log_prob)).mean(),
            "clip_fraction": (jnp.abs(ratio - 1.0) > hyper.clip_eps).astype(jnp.float32).mean(),
        }
        return total, aux

    def learning_rate(self, state: RecurrentPPOState) -> jax.Array:
        if not self.anneal_lr:
            return state.hyper.learning_rate
        frac = 1.0 - state.update.astype(jnp.float32) / self.total_updates
        return state.hyper.learning_rate * jnp.maximum(frac, 0.0)

    def update(self, state: RecurrentPPOState) -> tuple[RecurrentPPOState, dict[str, jax.Array]]:
        """Collect one rollout and run the PPO epochs on it."""
        state, traj, carry0 = self.collect(state)
        _, _, _, last_value, _ = self.policy_step(
            state.params, state.carry, state.obs, state.start, state.key, deterministic=True
        )
        hyper = state.hyper
        adv, targets = self.gae(traj, last_value, hyper.gamma, hyper.gae_lambda)
        lr = self.learning_rate(state)
        per_mb = self.num_envs // self.num_minibatches
        grad_fn = jax.value_and_grad(self.loss, has_aux=True)

        def minibatch(carry, idx):
            params, opt_state = carry
            take = lambda x: jnp.take(x, idx, axis=1)  # noqa: E731  (T, B, ...) -> (T, b, ...)
            mb_traj = jax.tree.map(take, traj)
            mb_carry0 = jax.tree.map(lambda x: jnp.take(x, idx, axis=0), carry0)
            (_, aux), grads = grad_fn(params, mb_carry0, mb_traj, take(adv), take(targets), hyper)
            norm = optax.tree.norm(grads)
            scale = jnp.minimum(1.0, hyper.max_grad_norm / (norm + 1e-6))
            grads = jax.tree.map(lambda g: g * scale, grads)
            updates, opt_state = self.optimizer.update(grads, opt_state, params)
            params = jax.tree.map(lambda p, u: p - lr * u, params, updates)
            aux["grad_norm"] = norm
            return (params, opt_state), aux

        def epoch(carry, key):
            order = jax.random.permutation(key, self.num_envs).reshape(self.num_minibatches, per_mb)
            return jax.lax.scan(minibatch, carry, order)

        key, k_epochs = jax.random.split(state.key)
        (params, opt_state), aux = jax.lax.scan(
            epoch, (state.params, state.opt_state), jax.random.split(k_epochs, self.num_epochs)
        )
        state = state.replace(params=params, opt_state=opt_state, key=key, update=state.update + 1)
        metrics = jax.tree.map(jnp.mean, aux)
        metrics["learning_rate"] = lr
        metrics["explained_variance"] = explained_variance(traj.value, targets)
        return state, metrics

    def chunk(self, state: RecurrentPPOState, num_updates: int):
        """``num_updates`` updates (not jitted: vmap it for batched trials); metrics averaged."""
        state, metrics = jax.lax.scan(lambda s, _: self.update(s), state, None, num_updates)
        return state, jax.tree.map(jnp.mean, metrics)

    @partial(jax.jit, static_argnames=("self", "num_updates"))
    def train_chunk(self, state: RecurrentPPOState, num_updates: int):
        """``num_updates`` updates in one compiled call; metrics averaged over them."""
        return self.chunk(state, num_updates)

    # Identity: jit treats the algorithm as a static argument. Two instances with the same
    # static shape (env shape, network, sizes, schedule length) share compiled code; everything
    # numeric (hyperparameters, env params) is in the state.
    def _static_key(self) -> tuple:
        return (self.env, self.network, self.num_envs, self.num_steps, self.num_minibatches,
                self.num_epochs, self.total_updates, self.anneal_lr)  # fmt: skip

    def __hash__(self) -> int:
        return hash(self._static_key())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RecurrentPPO) and other._static_key() == self._static_key()
