"""Training configuration: networks, algorithms and ``TrainConfig`` (a whole run).

Fields marked ``TRACED`` (learning rate, gamma, clip, ...) are numbers inside the compiled program;
trials that differ only in them train side by side (``quicknav_core.train.batched``).
"""

from __future__ import annotations

import itertools
from typing import Annotated, Literal

from pydantic import Field, model_validator

from quicknav_core.config.base import TRACED, Flag, StrictModel, tag_required
from quicknav_core.config.env import EnvConfig

MAX_DEVICES = 1024  # local accelerators one process can address

_LEARNED_LOG_STD = (
    "the policy's log std comes from a layer (per state) instead of one parameter per action;"
    " null: what the trainer does (resolve writes it in: false for PPO, true for SAC, null for"
    " TD3, whose policy is deterministic)"
)
_INIT_LOG_STD = (
    "initial log std of the policy; null: the trainer's own (resolve writes it in: -0.5 for"
    " QuickNav's PPO, 0.0 for rejax's PPO; SAC learns it per state and TD3 has none: null)"
)


class MLPNetwork(StrictModel):
    """ReLU MLP; ``memory_size > 0`` adds the paper's memory head (a recurrent carry)."""

    model_config = tag_required("kind")

    kind: Literal["mlp"] = "mlp"
    hidden_sizes: tuple[int, ...] = Field((128, 128), min_length=1, max_length=8)
    memory_size: int = Field(0, ge=0, le=1024, description="memory head size; 0 = memoryless")
    frames: int = Field(
        1, ge=1, le=8,
        description="observations the MLP reads at once: the current one and the frames-1 before"
        " it (at an episode's start the current one stands in for those not yet seen). 2 lets a"
        " policy read motion, such as people walking, from two lidar scans; its carry is the"
        " frames-1 last observations, so it trains with QuickNav's PPO; needs memory_size=0",
    )  # fmt: skip
    frame_stride: int = Field(
        1, ge=1, le=10,
        description="steps between the frames the MLP reads (frames > 1): 1 reads consecutive"
        " observations (one control period apart), 3 the one 3 steps before and so on; its carry"
        " is the (frames-1) x frame_stride last observations",
    )  # fmt: skip
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0,
        description="dropout after each hidden layer; no trainer applies it (PPO's probability ratio"
        " needs the same network when it collects and when it updates), so resolve refuses > 0",
    )  # fmt: skip
    learned_log_std: Flag | None = Field(None, description=_LEARNED_LOG_STD)
    init_log_std: float | None = Field(None, ge=-5.0, le=2.0, description=_INIT_LOG_STD)

    @model_validator(mode="after")
    def _sizes(self) -> MLPNetwork:
        for i, size in enumerate(self.hidden_sizes):
            if not 1 <= size <= 4096:
                raise ValueError(f"hidden_sizes[{i}]={size}: allowed range 1..4096")
        if self.frames > 1 and self.memory_size:
            raise ValueError(
                f"frames={self.frames} with memory_size={self.memory_size}: an MLP reads past"
                " observations or keeps a memory head, not both; allowed: frames=1 or memory_size=0"
            )
        if self.frame_stride > 1 and self.frames == 1:
            raise ValueError(
                f"frame_stride={self.frame_stride} with frames=1: the stride is the distance"
                " between the frames an MLP reads, and it reads one; allowed: frames >= 2 or"
                " frame_stride=1"
            )
        return self


class LSTMNetwork(StrictModel):
    """Stacked LSTM."""

    model_config = tag_required("kind")

    kind: Literal["lstm"] = "lstm"
    num_layers: int = Field(2, ge=1, le=16)
    hidden_size: int = Field(15, ge=1, le=1024)
    learned_log_std: Flag | None = Field(None, description=_LEARNED_LOG_STD)
    init_log_std: float | None = Field(None, ge=-5.0, le=2.0, description=_INIT_LOG_STD)


class GTrXLNetwork(StrictModel):
    """Gated Transformer-XL."""

    model_config = tag_required("kind")

    kind: Literal["gtrxl"] = "gtrxl"
    embed_size: int = Field(8, ge=1, le=1024)
    num_heads: int = Field(2, ge=1, le=32)
    head_size: int = Field(4, ge=1, le=256)
    num_layers: int = Field(2, ge=1, le=16)
    memory_length: int = Field(32, ge=1, le=1024)
    gate_bias: float = Field(2.0, ge=-10.0, le=10.0)
    learned_log_std: Flag | None = Field(None, description=_LEARNED_LOG_STD)
    init_log_std: float | None = Field(None, ge=-5.0, le=2.0, description=_INIT_LOG_STD)


NetworkConfig = Annotated[MLPNetwork | LSTMNetwork | GTrXLNetwork, Field(discriminator="kind")]


def network_is_recurrent(network: MLPNetwork | LSTMNetwork | GTrXLNetwork) -> bool:
    """Whether a network carries memory between steps (everything but the plain MLP)."""
    return not (
        isinstance(network, MLPNetwork) and network.memory_size == 0 and network.frames == 1
    )


# --------------------------------------------------------------------------- algorithms
class PPOConfig(StrictModel):
    """PPO. Memoryless MLPs train with rejax's PPO; recurrent networks with QuickNav's recurrent PPO."""

    model_config = tag_required("name")

    name: Literal["ppo"] = "ppo"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0, json_schema_extra=TRACED)
    num_steps: int = Field(128, ge=1, le=100_000, description="rollout length per env per update")
    num_minibatches: int = Field(4, ge=1, le=65_536)
    num_epochs: int = Field(4, ge=1, le=1000)
    gamma: float = Field(0.99, gt=0.0, le=1.0, json_schema_extra=TRACED)
    gae_lambda: float = Field(0.95, ge=0.0, le=1.0, json_schema_extra=TRACED)
    clip_eps: float = Field(0.2, gt=0.0, le=10.0, json_schema_extra=TRACED)
    ent_coef: float = Field(0.01, ge=0.0, le=10.0, json_schema_extra=TRACED)
    vf_coef: float = Field(0.5, ge=0.0, le=100.0, json_schema_extra=TRACED)
    max_grad_norm: float = Field(0.5, gt=0.0, le=1e6, json_schema_extra=TRACED)
    anneal_lr: Flag = Field(True, description="decay the learning rate linearly to 0")
    implementation: Literal["auto", "rejax", "quicknav"] = Field(
        "auto", description="auto: rejax for memoryless MLPs, QuickNav's recurrent PPO otherwise"
    )


class SACConfig(StrictModel):
    """Soft actor-critic (rejax), memoryless MLPs only."""

    model_config = tag_required("name")

    name: Literal["sac"] = "sac"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0, json_schema_extra=TRACED)
    gamma: float = Field(0.99, gt=0.0, le=1.0, json_schema_extra=TRACED)
    batch_size: int = Field(256, ge=1, le=1_000_000)
    buffer_size: int = Field(131_072, ge=1, le=100_000_000)
    fill_buffer: int = Field(2048, ge=0, le=100_000_000, description="random steps before learning")
    polyak: float = Field(0.99, ge=0.0, le=1.0, json_schema_extra=TRACED)
    target_entropy_ratio: float = Field(0.98, ge=0.0, le=1.0, json_schema_extra=TRACED)
    target_update_freq: int = Field(1, ge=1, le=1000)
    num_epochs: int = Field(1, ge=1, le=1000, description="gradient steps per env step batch")
    max_grad_norm: float = Field(10.0, gt=0.0, le=1e6, json_schema_extra=TRACED)


class TD3Config(StrictModel):
    """TD3 (rejax), memoryless MLPs only."""

    model_config = tag_required("name")

    name: Literal["td3"] = "td3"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0, json_schema_extra=TRACED)
    gamma: float = Field(0.99, gt=0.0, le=1.0, json_schema_extra=TRACED)
    batch_size: int = Field(256, ge=1, le=1_000_000)
    buffer_size: int = Field(131_072, ge=1, le=100_000_000)
    fill_buffer: int = Field(2048, ge=0, le=100_000_000)
    polyak: float = Field(0.99, ge=0.0, le=1.0, json_schema_extra=TRACED)
    exploration_noise: float = Field(0.3, ge=0.0, le=10.0, json_schema_extra=TRACED)
    target_noise: float = Field(0.2, ge=0.0, le=10.0, json_schema_extra=TRACED)
    target_noise_clip: float = Field(0.5, ge=0.0, le=10.0, json_schema_extra=TRACED)
    policy_delay: int = Field(2, ge=1, le=1000)
    num_epochs: int = Field(1, ge=1, le=1000)
    max_grad_norm: float = Field(10.0, gt=0.0, le=1e6, json_schema_extra=TRACED)


AlgorithmConfig = Annotated[PPOConfig | SACConfig | TD3Config, Field(discriminator="name")]


class CurriculumConfig(StrictModel):
    """Training episodes from short oracle paths to long ones.

    At the start of the run a pool of ``episodes_per_room`` episodes (start cell, goal cell) is
    drawn for every room of the train bank by the env's own spawn rule, and the oracle planner
    measures each one's shortest path (on the cell grid). Level i trains only on episodes whose
    path is shorter than ``levels[i]`` x the room's side; after a chunk whose training success is
    at least ``promote_at`` the next level opens; past the last level every pool episode is used.
    The eval banks never use the pool.
    """

    enabled: Flag = Field(False, description="train from short paths to long ones")
    levels: tuple[float, ...] = Field(
        (0.25, 0.5, 0.75), min_length=1, max_length=16,
        description="path-length limits of the levels before the full pool, as fractions of the"
        " room's side (increasing)",
    )  # fmt: skip
    promote_at: float = Field(
        0.8, gt=0.0, le=1.0, description="training success of a chunk that opens the next level"
    )
    episodes_per_room: int = Field(32, ge=1, le=1024, description="pool episodes drawn per room")

    @model_validator(mode="after")
    def _levels(self) -> CurriculumConfig:
        for i, (a, b) in enumerate(itertools.pairwise(self.levels)):
            if not b > a:
                raise ValueError(f"levels[{i + 1}]={b} must be greater than levels[{i}]={a}")
        for i, v in enumerate(self.levels):
            if not 0.0 < v <= 10.0:
                raise ValueError(f"levels[{i}]={v}: allowed range (0, 10] (fractions of the room side)")
        return self


class TrainConfig(StrictModel):
    """A whole training run: environment, algorithm, network, budget and seed."""

    env: EnvConfig = Field(default_factory=EnvConfig)
    algorithm: AlgorithmConfig = Field(default_factory=PPOConfig)
    network: NetworkConfig = Field(default_factory=MLPNetwork)
    total_steps: int = Field(1_000_000, ge=1, le=10_000_000_000, description="env steps to train")
    num_envs: int = Field(64, ge=1, le=1_048_576)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    chunk_steps: int = Field(
        50_000, ge=1, le=1_000_000_000, description="env steps per jit-compiled chunk (progress)"
    )
    curriculum: CurriculumConfig = Field(default_factory=CurriculumConfig)
    devices: Annotated[int, Field(ge=1, le=MAX_DEVICES)] | Literal["all"] = Field(
        1,
        description="local JAX devices the run spans, data parallel: the env batch is split over"
        " them, parameters are replicated, gradients averaged ('all': every device the process"
        " sees; must divide num_envs)",
    )  # fmt: skip

    @property
    def recurrent_network(self) -> bool:
        """Whether the network carries memory between steps."""
        return network_is_recurrent(self.network)

    @property
    def trainer_kind(self) -> str:
        """'rejax-ppo', 'rejax-sac', 'rejax-td3' or 'recurrent-ppo'."""
        algo = self.algorithm
        if isinstance(algo, PPOConfig):
            if algo.implementation == "quicknav" or (
                algo.implementation == "auto" and self.recurrent_network
            ):
                return "recurrent-ppo"
            return "rejax-ppo"
        return f"rejax-{algo.name}"

    @property
    def steps_per_update(self) -> int:
        """Env steps collected per update (PPO) or per chunk unit (off-policy: num_envs)."""
        if isinstance(self.algorithm, PPOConfig):
            return self.num_envs * self.algorithm.num_steps
        return self.num_envs

    @property
    def updates_per_chunk(self) -> int:
        return max(1, self.chunk_steps // self.steps_per_update)

    @model_validator(mode="after")
    def _check_combination(self) -> TrainConfig:
        algo = self.algorithm
        if isinstance(self.devices, int) and self.num_envs % self.devices:
            divisors = [d for d in range(1, min(self.num_envs, MAX_DEVICES) + 1) if self.num_envs % d == 0]
            raise ValueError(
                f"devices={self.devices} must divide num_envs={self.num_envs} (each device steps an"
                f" equal slice of the env batch); allowed: {', '.join(map(str, divisors[:12]))}"
                f"{', ...' if len(divisors) > 12 else ''}"
            )
        if isinstance(algo, PPOConfig):
            batch = self.num_envs * algo.num_steps
            if self.trainer_kind == "recurrent-ppo":
                if self.num_envs % algo.num_minibatches:
                    raise ValueError(
                        f"algorithm.num_minibatches={algo.num_minibatches} must divide"
                        f" num_envs={self.num_envs}: recurrent PPO splits minibatches across envs"
                        " (whole sequences); allowed: a divisor of num_envs"
                    )
            elif batch % algo.num_minibatches:
                raise ValueError(
                    f"algorithm.num_minibatches={algo.num_minibatches} must divide the batch"
                    f" num_envs*num_steps = {batch}; allowed: a divisor of {batch}"
                )
            if algo.implementation == "rejax" and self.recurrent_network:
                raise ValueError(
                    "algorithm.implementation='rejax' needs a memoryless MLP network"
                    f" (network.kind={self.network.kind!r}, memory_size=0, frames=1); use 'auto'"
                    " or 'quicknav'"
                )
        else:
            if self.recurrent_network:
                raise ValueError(
                    f"algorithm.name={algo.name!r} trains memoryless MLPs only"
                    f" (network.kind={self.network.kind!r}, memory_size>0, frames>1 or recurrent);"
                    " use algorithm.name='ppo' for recurrent networks"
                )
            if algo.batch_size > algo.buffer_size:
                raise ValueError(
                    f"algorithm.batch_size={algo.batch_size} exceeds algorithm.buffer_size="
                    f"{algo.buffer_size}; allowed: batch_size <= buffer_size"
                )
        if self.total_steps < self.steps_per_update:
            raise ValueError(
                f"total_steps={self.total_steps} is less than one update"
                f" ({self.steps_per_update} env steps); allowed: total_steps >= {self.steps_per_update}"
            )
        return self


# --------------------------------------------------------------------------- what trainers honour
# rejax keeps its env-step count (global_step) in an int32
REJAX_MAX_STEPS = 2**31 - 1
# The policy's standard deviation as each trainer builds it when the config leaves it to the
# trainer (None): (learned_log_std, init_log_std)
TRAINER_LOG_STD: dict[str, tuple[bool | None, float | None]] = {
    "recurrent-ppo": (False, -0.5),
    "rejax-ppo": (False, 0.0),
    "rejax-sac": (True, None),
    "rejax-td3": (None, None),
}


def unhonoured_fields(config: TrainConfig) -> list[tuple[str, str]]:
    """``(config path, message)`` for every field this config's trainer cannot do what it says;
    resolve refuses the config with these (a field that runs differently is never kept)."""
    net, kind = config.network, config.trainer_kind
    out = []
    if isinstance(net, MLPNetwork) and net.dropout > 0:
        out.append(("network.dropout", (
            f"network.dropout={net.dropout}: no trainer applies dropout (PPO's probability ratio"
            " needs the same network when it collects and when it updates; rejax's networks have"
            " none); allowed: 0")))  # fmt: skip
    if kind.startswith("rejax-") and config.total_steps > REJAX_MAX_STEPS:
        out.append(("total_steps", (
            f"total_steps={config.total_steps}: rejax's {kind[6:].upper()} counts env steps in a"
            f" 32-bit integer; allowed: up to {REJAX_MAX_STEPS}"
            + (", or algorithm.implementation='quicknav' (QuickNav's PPO counts updates)"
               if kind == "rejax-ppo" else ""))))  # fmt: skip
    if kind.startswith("rejax-") and config.env.observe_plan:
        out.append(("env.observe_plan", (
            f"env.observe_plan=true: rejax's {kind[6:].upper()} steps its envs with vmap(env.step),"
            " which plans every env's next episode at every step (a shortest-path search each);"
            " QuickNav's PPO plans only for the envs that reset; allowed: false, or"
            " algorithm.implementation='quicknav' with PPO")))  # fmt: skip
    learned, init = net.learned_log_std, net.init_log_std
    if kind == "rejax-ppo" and learned:
        out.append(("network.learned_log_std", (
            "network.learned_log_std=true: rejax's PPO keeps one log std per action (a"
            " parameter); allowed: false or null, or algorithm.implementation='quicknav' for a"
            " per-state log std")))  # fmt: skip
    if kind == "rejax-sac":
        if learned is False:
            out.append(("network.learned_log_std", (
                "network.learned_log_std=false: SAC's policy outputs its log std per state (a"
                " layer); allowed: true or null")))  # fmt: skip
        if init is not None:
            out.append(("network.init_log_std", (
                f"network.init_log_std={init}: SAC's log std is a layer's output (clipped to"
                " [-10, 2]) with no initial value to set; allowed: null")))  # fmt: skip
    if kind == "rejax-td3":
        for name, value in (("learned_log_std", learned), ("init_log_std", init)):
            if value is not None:
                out.append((f"network.{name}", (
                    f"network.{name}={str(value).lower()}: TD3's policy is deterministic (its"
                    " exploration is algorithm.exploration_noise); allowed: null")))  # fmt: skip
    return out


def with_trainer_defaults(config: TrainConfig) -> TrainConfig:
    """``config`` with the fields it leaves to the trainer (None) set to what the trainer does."""
    learned, init = TRAINER_LOG_STD[config.trainer_kind]
    net = config.network
    update = {}
    if net.learned_log_std is None and learned is not None:
        update["learned_log_std"] = learned
    if net.init_log_std is None and init is not None:
        update["init_log_std"] = init
    if not update:
        return config
    return config.model_copy(update={"network": net.model_copy(update=update)})
