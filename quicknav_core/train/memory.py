"""A job's memory, estimated from its config before it runs (no JAX: the service checks it at
submission against its budget).

The parts that grow with the config: the replay buffer of SAC/TD3 (``buffer_size`` transitions of
two observations, an action, a reward and a done flag), the room banks, the env batch, PPO's
rollout, the networks, and, for an evaluation, every episode's trajectory and its planner's fields.
Factors were measured on this project's CPU VM (peak RSS of a process that trains as a worker
does, ``quicknav_core.bench.memory``): 810-1,110 MB for the interpreter, JAX and the compiled
programs depending on the trainer and network, and about 2.7 bytes of peak for each byte of replay buffer
(the buffer lives once in the train state, once more while a compiled unit writes its output, and
once more while a checkpoint is serialised).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from quicknav_core.config import EnvConfig, EvalConfig, PPOConfig, SweepConfig, TrainConfig
from quicknav_core.config.eval import EVAL_BATCH, plan_batch

MB = 2**20
# a gRPC server's Rollout stream (python, jax, grpc, the env's compiled programs): measured with
# `python -m quicknav_core.bench.memory` (a fresh process with the server's imports that builds the
# stream's envs and steps them, compiling every program). The plan's programs (``observe_plan``)
# weigh ~80 MB more to compile; a batch of envs peaks at about six times its states and
# observations (XLA's buffers for the step's inputs, outputs and temporaries: measured slopes of
# 5.0 KB per demo env and 27 KB per building env against 0.8 and 4.7 KB of state and observation)
ROLLOUT_RUNTIME_BYTES = 525 * MB
ROLLOUT_PLAN_BYTES = 80 * MB
ROLLOUT_BATCH_FACTOR = 6.0
# a Policy stream's (python, jax, grpc, the loaded network and its compiled act), by network kind
# (GTrXL's attention programs weigh most to compile), measured as above with a policy acting for 8
# rows; what acting for POLICY_MAX_ROWS rows adds follows ``policy_row_floats`` at about five times
# the floats it counts (measured 11-78 MB at 4,096 rows)
POLICY_RUNTIME_BYTES = {"mlp": 340 * MB, "lstm": 335 * MB, "gtrxl": 390 * MB}
POLICY_ROW_FACTOR = 5.0
POLICY_MAX_ROWS = 4096  # robots one Policy stream may act for (``load.rows``)
# an evaluation's: what its peak holds beside the banks, the episodes and the plans (inferred as
# 760-775 MB: random-policy evaluations' peaks at grids 45 and 103, 876 and 908 MB, less the
# other parts as estimated). Lowered in 2026-11 once evaluations stopped importing seaborn
# (``deferred_imports``) and scipy.stats (``eval.aggregate`` imports it where a statistic is
# computed): the oracle's evaluations at grids 45, 103 and 203 measured 971 -> 839,
# 1,196 -> 1,104 and 2,466 -> 2,388 MB (2-core AMD EPYC VM; the largest one's peak, where the
# plans weigh most, moved least), so the constant sits where all three are within -3/+10 %
EVAL_RUNTIME_BYTES = 685 * MB
# Python, JAX, XLA and the compiled programs of a training run, by trainer and network: the peak
# of compiling them differs (GTrXL's attention programs take the most). Measured with
# `python -m quicknav_core.bench.memory` (peak RSS of a process that trains a few chunks and writes
# checkpoints, as a worker does, compiling every program), at two sizes each; README has the table.
# One case's peak reads up to 9 % either side of its middle, by machine and by load (XLA's compile
# threads overlap less when the other core is busy), so each constant puts its larger case's
# estimate inside what that case has read on 2-core AMD EPYC VMs (Zen 4 and Zen 5), quiet and in
# CI: ppo-mlp-2048 865-935 MB (estimate 927), mlp-memory-1024 846-1,003 (921), lstm-1024 835-944
# (904); gtrxl-2048 1,278-1,327 (1,276: just under the lowest reading, 4 % under the highest).
# CHANGELOG says when and why each moved
TRAIN_RUNTIME_BYTES = {
    "rejax-ppo": 855 * MB,
    "rejax-sac": 1010 * MB,
    "rejax-td3": 915 * MB,
    "recurrent-mlp": 855 * MB,
    "recurrent-lstm": 840 * MB,
    "recurrent-gtrxl": 1150 * MB,
}
REPLAY_FACTOR = 2.85  # peak bytes per replay-buffer byte (measured 2.69 for SAC and TD3; a margin)
TRANSIENT_FACTOR = 2.0  # inputs and outputs of a compiled call alive together
# the oracle's and DWA's plans, kept for every episode of a batch for the whole episode: two
# distance fields (float32) and two usable masks over 5 x 5 nodes per cell; peak bytes per byte
# of them (measured 1.0-1.5 at square grids 45 to 203 and at the maps' own grids, 29 x 45 to
# 203 x 123: the planners' work beside them; 1.4 was 5 % under the 203 x 123 peak)
PLAN_FACTOR = 1.5


@dataclass(frozen=True)
class Estimate:
    """Estimated peak bytes, by part; ``field`` is the config field of the largest part."""

    parts: dict[str, int]
    fields: dict[str, str]

    @property
    def total(self) -> int:
        return sum(self.parts.values())

    @property
    def largest(self) -> str:
        return max(self.parts, key=self.parts.get)

    @property
    def field(self) -> str:
        return self.fields.get(self.largest, "")

    def describe(self) -> str:
        shown = sorted(self.parts.items(), key=lambda kv: -kv[1])
        return ", ".join(f"{name} {size / MB:,.0f} MB" for name, size in shown if size >= MB)


def _words(g: int) -> int:
    return -(-g // 32)


def bank_bytes(env: EnvConfig, split: str = "train") -> int:
    """The room banks of a split: a generated test bank is made beside the train bank it must
    avoid; a map's test bank repeats the map alone (``MapRooms``, no train bank built)."""
    rows, cols = env.grid_shape
    # bool walls, row- and column-packed bits, the free-cell table, its count
    per_room = rows * cols + (rows * _words(cols) + cols * _words(rows)) * 4 + rows * cols * 4 + 4
    if env.lidar_reads_window:  # the packed bits laid out for the lidar's window, padded
        from quicknav_core.env.lidar import side_words

        half, m = (env.lidar_lines - 1) // 2, side_words(env.lidar_lines)
        per_room += ((rows + 2 * half) * (_words(cols) + 2 * m)
                     + (cols + 2 * half) * (_words(rows) + 2 * m)) * 4  # fmt: skip
    if split == "test":
        rooms = env.test_rooms + (0 if env.rooms == "maps" else env.train_rooms)
    else:
        rooms = env.train_rooms
    return per_room * rooms


def env_state_bytes(env: EnvConfig) -> int:
    """One env's state (bit-packed walls and visits, pose, lidar, counters and, for a policy that
    follows the plan, the plan's distance field over the grid)."""
    rows, cols = env.grid_shape
    plan = rows * cols * 4 if env.observe_plan else 0
    packed = (2 * rows * _words(cols) + cols * _words(rows)) * 4  # walls by row and column, visits
    return packed + env.lidar_beams * 8 + 64 + plan


def network_params(cfg: TrainConfig) -> int:
    """Parameters of the policy and value networks (an upper estimate)."""
    obs, net = cfg.env.obs_dim, cfg.network
    if net.kind == "mlp":
        sizes = [obs * net.frames + net.memory_size, *net.hidden_sizes]
        body = sum(a * b + b for a, b in itertools.pairwise(sizes))
        return 2 * body + (net.memory_size + 8) * sizes[-1]  # actor and critic (or shared + heads)
    if net.kind == "lstm":
        h = net.hidden_size
        return 4 * h * (obs + h + 1) + (net.num_layers - 1) * 4 * h * (2 * h + 1) + 8 * h
    e = net.embed_size
    per_layer = 4 * e * net.num_heads * net.head_size + 8 * e * e + 12 * e * e
    return obs * e + net.num_layers * per_layer + (net.memory_length + 1) * e * net.num_layers


def train_memory(cfg: TrainConfig, trials: int = 1) -> Estimate:
    """Peak memory of training ``cfg`` (``trials`` side by side, as a sweep's group does)."""
    env, algo = cfg.env, cfg.algorithm
    obs = env.obs_dim
    family = cfg.trainer_kind
    if family == "recurrent-ppo":
        family = f"recurrent-{cfg.network.kind}"
    parts = {
        "runtime": TRAIN_RUNTIME_BYTES.get(family, max(TRAIN_RUNTIME_BYTES.values())),
        "room banks": 2 * bank_bytes(env, "train"),  # the bank, and a copy while it is built
        "env batch": int(TRANSIENT_FACTOR * trials * cfg.num_envs * (env_state_bytes(env) + obs * 8)),
        "networks": int(trials * network_params(cfg) * 4 * 6),  # params, grads, adam moments, targets
    }
    fields = {"room banks": "env.train_rooms", "env batch": "num_envs", "networks": "network"}
    if isinstance(algo, PPOConfig):
        per_step = obs * 4 + 2 * 4 + 6 * 4  # observation, action, logp/value/reward/done/adv/target
        rollout = trials * cfg.num_envs * algo.num_steps * per_step
        if cfg.recurrent_network:
            rollout *= 2  # replayed sequences keep activations for the gradient
        parts["rollout"] = int(TRANSIENT_FACTOR * rollout)
        fields["rollout"] = "algorithm.num_steps"
    else:
        transition = 2 * obs * 4 + 2 * 4 + 4 + 1
        parts["replay buffer"] = int(REPLAY_FACTOR * trials * algo.buffer_size * transition)
        fields["replay buffer"] = "algorithm.buffer_size"
    return Estimate(parts, fields)


def sweep_memory(cfg: SweepConfig) -> Estimate:
    """Peak memory of a sweep: ``parallel`` trials of the base config trained side by side."""
    est = train_memory(cfg.base, trials=cfg.parallel)
    fields = {k: ("parallel" if k not in ("runtime", "room banks") else v)
              for k, v in est.fields.items()}  # fmt: skip
    return Estimate(est.parts, fields)


def eval_memory(cfg: EvalConfig) -> Estimate:
    """Peak memory of an evaluation: a batch of episodes with their planners, every trajectory."""
    env = cfg.env or EnvConfig()
    steps = env.max_steps + 1
    batch = min(cfg.episodes, EVAL_BATCH)
    nodes = env.grid_shape[0] * env.grid_shape[1] * 25  # the planner's refined grid (k = 5)
    planner = nodes * (4 * 2 + 1) * 3  # distance fields and usable masks, plain and with margin
    kept_steps = steps * (2 * 4)  # every episode's positions
    gif = min(cfg.gif_episodes, cfg.episodes) * steps * (env.lidar_beams * 8 + 16)
    per_episode = env_state_bytes(env) * 2 + kept_steps
    planners = plan_batch(env.grid_shape, batch)  # side by side (``jax.lax.map``), not the batch
    parts = {
        "runtime": EVAL_RUNTIME_BYTES,
        "room banks": 2 * bank_bytes(env, cfg.split),
        "episode batch": int(TRANSIENT_FACTOR * (batch * per_episode + planners * planner)),
        "trajectories": cfg.episodes * kept_steps * 2 + gif,
    }
    # a map's test bank is its largest bank; a generated test bank is made beside the train bank
    only_test = cfg.split == "test" and env.rooms == "maps"
    fields = {"room banks": "env.test_rooms" if only_test else "env.train_rooms",
              "episode batch": "env.grid_size", "trajectories": "episodes"}  # fmt: skip
    if cfg.policy in ("oracle", "dwa"):
        parts["plans"] = int(PLAN_FACTOR * batch * nodes * (4 + 1) * 2)
        fields["plans"] = "env.grid_size"
    return Estimate(parts, fields)


def rollout_memory(env: EnvConfig, num_envs: int, split: str = "train") -> Estimate:
    """Peak memory of a gRPC Rollout stream: the server's runtime, the banks, and ``num_envs``
    envs stepped together (states, observations and final observations, in and out of each step)."""
    parts = {
        "runtime": ROLLOUT_RUNTIME_BYTES + (ROLLOUT_PLAN_BYTES if env.observe_plan else 0),
        "room banks": 2 * bank_bytes(env, split),
        "env batch": int(ROLLOUT_BATCH_FACTOR * num_envs * (env_state_bytes(env) + 2 * env.obs_dim * 4)),
    }
    return Estimate(parts, {"room banks": f"{split}_rooms", "env batch": "num_envs"})


# what part of a stream's batch stays resident between its steps: the rest is one step's
# transients, which streams stepped side by side did not add up (four `building` streams of
# 4,096 envs stepped by four threads in one process on 2 cores peaked at 751 MB, one alone at 700
# MB: each further stream added about its states and observations, 17 MB, not its 112 MB peak)
RESIDENT_SHARE = {"env batch": 1.0 / ROLLOUT_BATCH_FACTOR, "episode batch": 1.0 / TRANSIENT_FACTOR}
TRANSIENTS = "one step's transients"


def together(estimates: list[Estimate]) -> Estimate:
    """The peak of several streams open at once in one server process: its runtime once (the
    largest any of them needs), every stream's room banks and resident batch added up, and the
    largest stream's step transients once (a gRPC server's open Rollout streams,
    ``quicknav_service.rollout.common.StreamMemory``). One stream's is its own estimate."""
    parts: dict[str, int] = {"runtime": 0}
    fields: dict[str, str] = {TRANSIENTS: "num_envs"}
    transients = 0
    for est in estimates:
        extra = 0
        for name, size in est.parts.items():
            if name == "runtime":
                parts[name] = max(parts[name], size)
                continue
            kept = int(size * RESIDENT_SHARE.get(name, 1.0))
            parts[name] = parts.get(name, 0) + kept
            extra += size - kept
        transients = max(transients, extra)
        fields = {**est.fields, **fields}
    if transients:
        parts[TRANSIENTS] = transients
    return Estimate(parts, fields)


def policy_row_floats(cfg: TrainConfig) -> int:
    """Floats one row of a policy's act holds: its observation (every frame), its carry, and its
    widest activations (an MLP's hidden layers, an LSTM's gates, GTrXL's memory and its keys and
    values with the attention scores)."""
    obs, net = cfg.env.obs_dim, cfg.network
    if net.kind == "mlp":
        return obs * net.frames + 2 * net.memory_size + sum(net.hidden_sizes)
    if net.kind == "lstm":
        return obs + 6 * net.num_layers * net.hidden_size
    span = net.memory_length + 1
    return obs + net.num_layers * span * (2 * net.embed_size + net.num_heads)


def policy_memory(cfg: TrainConfig, rows: int = POLICY_MAX_ROWS) -> Estimate:
    """Peak memory of serving a trained policy (the Policy stream): the server's runtime for its
    network kind, its networks, and acting for ``rows`` robots at once (one stream's most)."""
    parts = {
        "runtime": POLICY_RUNTIME_BYTES[cfg.network.kind],
        "networks": int(network_params(cfg) * 4 * 2),
        "rows": int(POLICY_ROW_FACTOR * rows * policy_row_floats(cfg) * 4),
    }
    return Estimate(parts, {"networks": "network", "rows": "network"})


def megabytes(n: int) -> int:
    return math.ceil(n / MB)
