"""Pydantic configuration models: the only objects that cross a boundary (CLI, REST, gRPC, files).

Every field is validated on construction; a bad value raises ``pydantic.ValidationError`` whose
message names the field and the allowed range. Fields that change array shapes (``grid_size``,
``lidar_beams``, ``observe_goal``, bank sizes) are fixed when the environment is built; every other
number ends up in the traced ``EnvParams`` pytree and can be vmapped without recompiling.
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

if TYPE_CHECKING:  # pragma: no cover - import only for type checkers, keeps this module JAX-free
    from quicknav_core.env.quicknav import QuickNavEnv
    from quicknav_core.env.types import EnvParams

Split = Literal["train", "test"]


class _Strict(BaseModel):
    """Base: unknown fields are errors, models are immutable and JSON-serialisable."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class RewardConfig(_Strict):
    """Reward weights of the paper's formula.

    r_t = -step_penalty - 1[collision]*collision_penalty - min(C_t, cycle_cap)*cycle_penalty
          + progress_term + 1[goal reached]*goal_reward + 1[new cell]*exploration_reward
    with progress_term = sign(d_{t-1} - d_t) * progress_reward (``progress="sign"``) or
    progress_reward * (d_{t-1} - d_t) / (max_wheel_speed * dt) (``progress="linear"``).
    """

    step_penalty: float = Field(0.1, ge=0.0, le=1000.0, description="λs, paid every step")
    collision_penalty: float = Field(10.0, ge=0.0, le=1000.0, description="λw, per wall collision")
    cycle_penalty: float = Field(
        0.0, ge=0.0, le=1000.0, description="λc, times min(C_t, cycle_cap)"
    )
    progress_reward: float = Field(1.0, ge=0.0, le=1000.0, description="λp, progress towards goal")
    goal_reward: float = Field(50.0, ge=0.0, le=10000.0, description="λg, on reaching the goal")
    cycle_cap: int = Field(10, ge=0, le=1_000_000, description="cap on the revisit count C_t")
    exploration_reward: float = Field(
        0.0,
        ge=0.0,
        le=1000.0,
        description="λe, paid on entering a cell not yet visited this episode (0 = the paper's formula)",
    )
    progress: Literal["sign", "linear"] = Field("sign", description="shape of the progress term")


class EnvConfig(_Strict):
    """Everything that defines a QuickNav environment. ``build(split)`` returns ``(env, params)``."""

    # Room and procedural generation
    room_size: float = Field(8.0, gt=0.0, le=1000.0, description="side of the square room, metres")
    grid_size: int = Field(16, ge=4, le=128, description="cells per side (outer ring is wall)")
    carve_fraction: float = Field(
        0.8, gt=0.0, le=1.0, description="fraction of inner cells carved free"
    )
    return_prob: float = Field(
        0.05, ge=0.0, lt=1.0, description="chance per carving step to jump back to the centre"
    )
    carve_max_steps: int | None = Field(
        None, ge=1, le=100_000_000, description="carving step cap; None = 1000 x inner cells"
    )
    room_seed: int = Field(0, ge=0, le=2**31 - 1, description="seed of the room banks")
    train_rooms: int = Field(1024, ge=1, le=1_000_000, description="rooms in the train bank")
    test_rooms: int = Field(256, ge=1, le=1_000_000, description="rooms in the held-out test bank")

    # Robot
    robot_radius: float = Field(0.15, gt=0.0, le=100.0, description="robot disc radius, metres")
    max_wheel_speed: float = Field(
        1.0, gt=0.0, le=100.0, description="wheel speed at |action|=1, m/s"
    )
    wheel_base: float = Field(0.3, gt=0.0, le=100.0, description="distance between wheels, metres")
    dt: float = Field(0.1, gt=0.0, le=10.0, description="control period, seconds")

    # Lidar
    lidar_beams: int = Field(16, ge=1, le=1024, description="number of lidar beams")
    lidar_fov_deg: float = Field(
        360.0, gt=0.0, le=360.0, description="lidar field of view, degrees"
    )
    lidar_max_range: float = Field(10.0, gt=0.0, le=10000.0, description="lidar range cap, metres")

    # Task
    goal_candidates: int = Field(
        5, ge=1, le=64, description="random free cells drawn; the farthest becomes the goal"
    )
    goal_radius: float = Field(0.3, gt=0.0, le=100.0, description="goal disc radius, metres")
    max_steps: int = Field(300, ge=1, le=1_000_000, description="episode truncation limit")
    observe_goal: bool = Field(True, description="include goal position/distance/bearing in obs")
    final_obs: bool = Field(
        True, description="put the pre-reset observation in info['final_obs'] (costs a 2nd cast)"
    )
    reward: RewardConfig = Field(default_factory=RewardConfig)

    @property
    def cell_size(self) -> float:
        """Side of one grid cell in metres."""
        return self.room_size / self.grid_size

    @property
    def inner_cells(self) -> int:
        """Number of cells inside the outer wall ring."""
        return (self.grid_size - 2) ** 2

    @property
    def carve_target(self) -> int:
        """Free cells a generated room must reach (at least 2: start and goal differ)."""
        return max(2, math.ceil(self.carve_fraction * self.inner_cells - 1e-9))

    @property
    def carve_step_cap(self) -> int:
        """Carving steps after which generation stops even if the target is not met."""
        return self.carve_max_steps if self.carve_max_steps is not None else 1000 * self.inner_cells

    @property
    def obs_dim(self) -> int:
        """Length of the flat observation vector."""
        return 4 + 3 * self.lidar_beams + (5 if self.observe_goal else 0)

    @model_validator(mode="after")
    def _check_geometry(self) -> EnvConfig:
        c = self.cell_size
        if 2 * self.robot_radius >= c:
            raise ValueError(
                f"robot_radius={self.robot_radius} m: the robot (diameter {2 * self.robot_radius:g} m)"
                f" must be narrower than a one-cell corridor; allowed range 0 < robot_radius"
                f" < {c / 2:g} m (cell size room_size/grid_size = {c:g} m)"
            )
        step = self.max_wheel_speed * self.dt
        if step > c:
            raise ValueError(
                f"max_wheel_speed*dt = {step:g} m per step exceeds the cell size {c:g} m, so the"
                " robot could pass through walls; allowed range max_wheel_speed*dt <= room_size/grid_size"
            )
        if self.carve_target > self.inner_cells:
            raise ValueError(
                f"carve_fraction={self.carve_fraction}: grid_size={self.grid_size} has only"
                f" {self.inner_cells} inner cells but at least 2 must be free"
            )
        if self.carve_step_cap < self.carve_target:
            raise ValueError(
                f"carve_max_steps={self.carve_max_steps} can never carve {self.carve_target} cells;"
                f" allowed range carve_max_steps >= {self.carve_target}"
            )
        return self

    def build(self, split: Split = "train") -> tuple[QuickNavEnv, EnvParams]:
        """Return the gymnax environment and its params with the ``split`` room bank."""
        from quicknav_core.env.quicknav import build_env

        return build_env(self, split)


def _parse_value(text: str):
    """A --set value: JSON where it parses (numbers, true/false, null, lists), else the raw string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _submodel(annotation, data: dict) -> type[BaseModel] | None:
    """The model class a nested field holds: itself, or the union member ``data`` selects."""
    import typing

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is Annotated:
        return _submodel(args[0], data)
    for member in args:
        if isinstance(member, type) and issubclass(member, BaseModel):
            tags = [f for f in ("kind", "name") if f in member.model_fields and f in data]
            if tags and all(member.model_fields[t].default == data[t] for t in tags):
                return member
    return None


def apply_overrides(model: BaseModel, overrides: list[str]) -> BaseModel:
    """Return a copy of ``model`` with ``key.sub=value`` overrides applied and re-validated.

    Unknown keys raise ``ValueError`` naming the key and the known fields.
    """
    data = model.model_dump(mode="json")
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"--set {item!r}: expected key=value, e.g. grid_size=8")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        node, schema = data, type(model)
        for i, part in enumerate(parts):
            if schema is None:  # a field pydantic will check (unknown keys are rejected there)
                node[part] = (
                    _parse_value(value) if i == len(parts) - 1 else node.setdefault(part, {})
                )
                if i < len(parts) - 1:
                    node = node[part]
                continue
            fields = schema.model_fields
            if part not in fields:
                where = ".".join(parts[:i]) or type(model).__name__
                raise ValueError(
                    f"--set {key}: unknown field {part!r} in {where}; known: {', '.join(fields)}"
                )
            if i == len(parts) - 1:
                node[part] = _parse_value(value)
            else:
                if not isinstance(node.get(part), dict):
                    raise ValueError(f"--set {key}: {part!r} has no sub-fields")
                node = node[part]
                schema = _submodel(fields[part].annotation, node)
    return type(model).model_validate(data)


def format_validation_error(error: ValidationError, prefix: str = "") -> str:
    """One line per bad field: ``field.path: message (got value)``; ``prefix`` goes before paths."""
    lines = []
    for e in error.errors():
        loc = ".".join(str(p) for p in e["loc"]) or error.title
        loc = f"{prefix}.{loc}" if prefix and e["loc"] else (prefix or loc)
        msg = e["msg"].removeprefix("Value error, ")
        got = e.get("input")
        shown = "" if isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"{loc}: {msg}{shown}")
    return "invalid configuration:\n  " + "\n  ".join(lines)


# --------------------------------------------------------------------------- networks
class MLPNetwork(_Strict):
    """ReLU MLP; ``memory_size > 0`` adds the paper's memory head (a recurrent carry)."""

    kind: Literal["mlp"] = "mlp"
    hidden_sizes: tuple[int, ...] = Field((128, 128), min_length=1, max_length=8)
    memory_size: int = Field(0, ge=0, le=1024, description="memory head size; 0 = memoryless")
    dropout: float = Field(0.0, ge=0.0, lt=1.0, description="dropout after each hidden layer")
    learned_log_std: bool = Field(False, description="state-dependent log std (else a parameter)")
    init_log_std: float = Field(-0.5, ge=-5.0, le=2.0)

    @model_validator(mode="after")
    def _sizes(self) -> MLPNetwork:
        for i, size in enumerate(self.hidden_sizes):
            if not 1 <= size <= 4096:
                raise ValueError(f"hidden_sizes[{i}]={size}: allowed range 1..4096")
        return self


class LSTMNetwork(_Strict):
    """Stacked LSTM."""

    kind: Literal["lstm"] = "lstm"
    num_layers: int = Field(2, ge=1, le=16)
    hidden_size: int = Field(15, ge=1, le=1024)
    learned_log_std: bool = False
    init_log_std: float = Field(-0.5, ge=-5.0, le=2.0)


class GTrXLNetwork(_Strict):
    """Gated Transformer-XL."""

    kind: Literal["gtrxl"] = "gtrxl"
    embed_size: int = Field(8, ge=1, le=1024)
    num_heads: int = Field(2, ge=1, le=32)
    head_size: int = Field(4, ge=1, le=256)
    num_layers: int = Field(2, ge=1, le=16)
    memory_length: int = Field(32, ge=1, le=1024)
    gate_bias: float = Field(2.0, ge=-10.0, le=10.0)
    learned_log_std: bool = False
    init_log_std: float = Field(-0.5, ge=-5.0, le=2.0)


NetworkConfig = Annotated[MLPNetwork | LSTMNetwork | GTrXLNetwork, Field(discriminator="kind")]


# --------------------------------------------------------------------------- algorithms
class PPOConfig(_Strict):
    """PPO. Memoryless MLPs train with rejax's PPO; recurrent networks with QuickNav's recurrent PPO."""

    name: Literal["ppo"] = "ppo"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0)
    num_steps: int = Field(128, ge=1, le=100_000, description="rollout length per env per update")
    num_minibatches: int = Field(4, ge=1, le=65_536)
    num_epochs: int = Field(4, ge=1, le=1000)
    gamma: float = Field(0.99, gt=0.0, le=1.0)
    gae_lambda: float = Field(0.95, ge=0.0, le=1.0)
    clip_eps: float = Field(0.2, gt=0.0, le=10.0)
    ent_coef: float = Field(0.01, ge=0.0, le=10.0)
    vf_coef: float = Field(0.5, ge=0.0, le=100.0)
    max_grad_norm: float = Field(0.5, gt=0.0, le=1e6)
    anneal_lr: bool = Field(True, description="decay the learning rate linearly to 0")
    implementation: Literal["auto", "rejax", "quicknav"] = Field(
        "auto", description="auto: rejax for memoryless MLPs, QuickNav's recurrent PPO otherwise"
    )


class SACConfig(_Strict):
    """Soft actor-critic (rejax), memoryless MLPs only."""

    name: Literal["sac"] = "sac"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0)
    gamma: float = Field(0.99, gt=0.0, le=1.0)
    batch_size: int = Field(256, ge=1, le=1_000_000)
    buffer_size: int = Field(131_072, ge=1, le=100_000_000)
    fill_buffer: int = Field(2048, ge=0, le=100_000_000, description="random steps before learning")
    polyak: float = Field(0.99, ge=0.0, le=1.0)
    target_entropy_ratio: float = Field(0.98, ge=0.0, le=1.0)
    target_update_freq: int = Field(1, ge=1, le=1000)
    num_epochs: int = Field(1, ge=1, le=1000, description="gradient steps per env step batch")
    max_grad_norm: float = Field(10.0, gt=0.0, le=1e6)


class TD3Config(_Strict):
    """TD3 (rejax), memoryless MLPs only."""

    name: Literal["td3"] = "td3"
    learning_rate: float = Field(3e-4, gt=0.0, le=1.0)
    gamma: float = Field(0.99, gt=0.0, le=1.0)
    batch_size: int = Field(256, ge=1, le=1_000_000)
    buffer_size: int = Field(131_072, ge=1, le=100_000_000)
    fill_buffer: int = Field(2048, ge=0, le=100_000_000)
    polyak: float = Field(0.99, ge=0.0, le=1.0)
    exploration_noise: float = Field(0.3, ge=0.0, le=10.0)
    target_noise: float = Field(0.2, ge=0.0, le=10.0)
    target_noise_clip: float = Field(0.5, ge=0.0, le=10.0)
    policy_delay: int = Field(2, ge=1, le=1000)
    num_epochs: int = Field(1, ge=1, le=1000)
    max_grad_norm: float = Field(10.0, gt=0.0, le=1e6)


AlgorithmConfig = Annotated[PPOConfig | SACConfig | TD3Config, Field(discriminator="name")]


class TrainConfig(_Strict):
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

    @property
    def recurrent_network(self) -> bool:
        """Whether the network carries memory between steps."""
        net = self.network
        return not (isinstance(net, MLPNetwork) and net.memory_size == 0)

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
                    f" (network.kind={self.network.kind!r}); use 'auto' or 'quicknav'"
                )
        else:
            if self.recurrent_network:
                raise ValueError(
                    f"algorithm.name={algo.name!r} trains memoryless MLPs only"
                    f" (network.kind={self.network.kind!r}, memory_size>0 or recurrent);"
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
