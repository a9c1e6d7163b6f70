"""What QuickNav puts into rejax's PPO, SAC and TD3: the networks its config names, and a replay
buffer whose sampling cost does not grow with its size.

rejax builds its own networks in ``create_agent``, and not always from what it is given: its SAC
reads ``hidden_layer_sizes`` from a key QuickNav did not pass and trained 64x64 whatever the config
said, its TD3 fixes 64x64, and its PPO starts the log std at 0 whatever the config names. So every
network is built here, from the config, and put in place of rejax's.

rejax's ``ReplayBuffer.sample`` draws a minibatch without replacement with ``jax.random.choice``
over every slot of the buffer, weighted by which are filled: work proportional to the buffer (500k
slots for paper-sac) on every gradient step. ``UniformReplayBuffer`` draws uniform indices among the
filled slots, with replacement (as Stable-Baselines3 and most SAC implementations do), and gathers
them: work proportional to the minibatch. For a 512-minibatch from 500,000 transitions the two differ
in a repeated index about a quarter of the time, one sample in 512.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
import rejax
from flax.linen.initializers import constant
from flax.training.train_state import TrainState
from rejax.algos.algorithm import register_init
from rejax.buffers import Minibatch, ReplayBuffer
from rejax.networks import (
    MLP,
    DeterministicPolicy,
    GaussianPolicy,
    QNetwork,
    SquashedGaussianPolicy,
    VNetwork,
)

from quicknav_core.config import TrainConfig
from quicknav_core.config.train import TRAINER_LOG_STD
from quicknav_core.runtime import Runtime

ACTION_RANGE = (-1.0, 1.0)
ACTION_DIM = 2
# rejax's SAC clips the per-state log std to this range
SAC_LOG_STD_RANGE = (-10.0, 2.0)


class UniformReplayBuffer(ReplayBuffer):
    """rejax's circular replay buffer, sampled uniformly with replacement in O(minibatch)."""

    @partial(jax.jit, static_argnames=("num",))
    def sample(self, num: int, rng: jax.Array) -> Minibatch:
        index = jax.random.randint(rng, (num,), 0, jnp.maximum(self.num_entries, 1))
        return jax.tree.map(lambda arr: arr[index], self.data)


class _UniformReplay:
    """Mixed into rejax's SAC and TD3: their replay buffer is a ``UniformReplayBuffer``."""

    @register_init
    def initialize_replay_buffer(self, rng):
        return {"replay_buffer": UniformReplayBuffer.empty(self.buffer_size, self.obs_space,
                                                           self.action_space)}  # fmt: skip


class SAC(_UniformReplay, rejax.SAC):
    pass


class TD3(_UniformReplay, rejax.TD3):
    pass


class PPOGaussianPolicy(GaussianPolicy):
    """rejax's PPO policy with its log std starting where the config says."""

    init_log_std: float = 0.0

    def setup(self):  # rejax's, with the initial value of the log std
        self.features = MLP(self.hidden_layer_sizes, self.activation)
        self.action_mean = nn.Dense(self.action_dim)
        self.action_log_std = self.param(
            "action_log_std", constant(self.init_log_std), (self.action_dim,)
        )


def rejax_networks(config: TrainConfig) -> dict[str, nn.Module]:
    """The actor and critic of a rejax trainer, as ``config.network`` names them (ReLU MLPs)."""
    net, kind = config.network, config.trainer_kind
    hidden = tuple(net.hidden_sizes)
    mlp = {"hidden_layer_sizes": hidden, "activation": nn.relu}
    if kind == "rejax-ppo":
        init = net.init_log_std if net.init_log_std is not None else TRAINER_LOG_STD[kind][1]
        return {"actor": PPOGaussianPolicy(ACTION_DIM, ACTION_RANGE, init_log_std=init, **mlp),
                "critic": VNetwork(**mlp)}  # fmt: skip
    if kind == "rejax-sac":
        return {"actor": SquashedGaussianPolicy(ACTION_DIM, ACTION_RANGE,
                                                log_std_range=SAC_LOG_STD_RANGE, **mlp),
                "critic": QNetwork(**mlp)}  # fmt: skip
    if kind == "rejax-td3":
        return {"actor": DeterministicPolicy(ACTION_DIM, ACTION_RANGE, **mlp),
                "critic": QNetwork(**mlp)}  # fmt: skip
    raise ValueError(f"{kind} is not a rejax trainer")



# rejax's ``init_state`` makes a new state class and a new optimiser (closures over the learning
# rate) on every call, and jit keys its cache on both: every run would trace and compile its
# program anew, even one that differs from the last only in a reward weight. One class per state
# layout and one optimiser per (learning rate, gradient clip), kept in the runtime, make the runs
# of one process share it.
def shareable_state(state, learning_rate: float, max_grad_norm: float, runtime: Runtime):
    """``state`` (from a rejax ``init_state``) rebuilt from the runtime's shared class and optimiser."""
    key = (float(learning_rate), float(max_grad_norm))
    tx = runtime.program(("rejax-optimiser", key),
                         lambda: optax.chain(optax.clip(key[1]), optax.adam(learning_rate=key[0])))  # fmt: skip
    fields = {f.name: getattr(state, f.name) for f in dataclasses.fields(state)}
    fields = {k: v.replace(tx=tx) if isinstance(v, TrainState) else v for k, v in fields.items()}
    layout = (type(state).__name__, tuple(fields))
    cls = runtime.program(("rejax-state-class", layout), lambda: type(state))
    return cls(**fields)
