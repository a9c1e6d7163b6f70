"""A gRPC ``Start`` read into what the stream will run, and admitted as every door admits a config.

``read_start`` turns the message into a ``StartRequest``: the env config (resolved like every env:
fields or dotted keys on the defaults, or on the env a policy trained in), the number of envs, the
split, the seed, the groups of the asynchronous mode, the policy. A field out of range is
INVALID_ARGUMENT naming ``start.<field>`` and what is allowed. ``admit_start`` then runs the one
admission of ``quicknav_core.admission`` (this server's limits, rooms, memory) and the stream's own
capacities (message size, sessions, policy envs): RESOURCE_EXHAUSTED when only capacity is short.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import grpc
from google.protobuf import json_format
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb

from quicknav_core.admission import RolloutRequest, admit
from quicknav_core.config import EnvConfig
from quicknav_core.runtime import Runtime
from quicknav_service.jobs.limits import server_limits
from quicknav_service.rollout.common import Refused
from quicknav_service.settings import Settings

SPLITS = {pb.SPLIT_UNSPECIFIED: "train", pb.SPLIT_TRAIN: "train", pb.SPLIT_TEST: "test"}
MAX_GROUPS = 64  # asynchronous mode: at most this many groups per stream
MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class StartRequest:
    """What a Start asks for, every field checked."""

    env: EnvConfig
    num_envs: int
    split: str
    seed: int
    groups: int
    policy_job: str | None  # a trained job's id: its episodes are streamed (policy mode)
    stochastic: bool

    @property
    def rollout(self) -> RolloutRequest:
        return RolloutRequest(self.env, self.num_envs, self.split, policy=self.policy_job is not None)


def invalid(message: str) -> Refused:
    return Refused(grpc.StatusCode.INVALID_ARGUMENT, message)


def env_fields(start: pb.Start) -> dict[str, Any]:
    """The EnvConfig fields a Start carries (JSON text or a protobuf Struct)."""
    which = start.WhichOneof("config")
    if which == "config_json":
        try:
            fields = json.loads(start.config_json or "{}")
        except json.JSONDecodeError as e:
            raise invalid(f"start.config_json is not valid JSON ({e})") from None
        except RecursionError:  # a client's mistake (or worse), not the server's
            raise invalid("start.config_json is nested too deep; it is a flat JSON object of"
                          " EnvConfig fields") from None  # fmt: skip
        if not isinstance(fields, dict):
            raise invalid("start.config_json must be a JSON object of EnvConfig fields")
        return fields
    if which == "config_fields":
        try:
            return _ints_where_integral(json_format.MessageToDict(start.config_fields))
        except RecursionError:
            raise invalid("start.config_fields is nested too deep") from None
        except (ValueError, json_format.Error) as e:  # NaN or infinity in the Struct
            raise invalid(f"start.config_fields: {str(e)[:200]}; EnvConfig fields are finite"
                          " numbers, strings, lists and objects") from None  # fmt: skip
    return {}


def _ints_where_integral(value):
    """protobuf Struct numbers are doubles: give integral ones back as ints (grid_size=8.0 -> 8)."""
    if isinstance(value, dict):
        return {k: _ints_where_integral(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_ints_where_integral(v) for v in value]
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        return int(value)
    return value


def read_env(start: pb.Start, base: EnvConfig | None = None) -> EnvConfig:
    """The Start's env config on ``base`` (default: the defaults), validated by the model."""
    from quicknav_core.config import ConfigError, resolve_env
    from quicknav_core.config.errors import format_items

    try:
        return resolve_env(env_fields(start), base)
    except ConfigError as e:
        raise invalid(format_items(e.items, prefix="start.config")) from None


def read_start(start: pb.Start, base: EnvConfig | None = None) -> StartRequest:
    """Every field of a Start, checked (INVALID_ARGUMENT naming the first field out of range)."""
    env = read_env(start, base)
    policy_job = start.policy.job_id if start.HasField("policy") and start.policy.job_id else None
    if policy_job is not None and base is not None and env.obs_dim != base.obs_dim:
        raise invalid(
            f"start.config: the policy of job {policy_job} reads {base.obs_dim}-long observations"
            f" (lidar_beams={base.lidar_beams}, observe_goal={base.observe_goal}); these fields make"
            f" them {env.obs_dim} long: keep lidar_beams and observe_goal"
        )
    if start.split not in SPLITS:
        raise invalid(f"start.split={start.split}: allowed values are SPLIT_TRAIN (1) and SPLIT_TEST (2)")
    if start.seed > MAX_SEED:
        raise invalid(f"start.seed={start.seed}: allowed range 0..{MAX_SEED}")
    num_envs, groups = start.num_envs or 1, start.groups or 1
    if groups > 1 and policy_job is not None:
        raise invalid("start.groups applies to stepping envs, not to policy mode; send 0")
    if groups > min(MAX_GROUPS, num_envs) or num_envs % groups:
        raise invalid(f"start.groups={groups} with num_envs={num_envs}: allowed a divisor of"
                      f" num_envs up to {min(MAX_GROUPS, num_envs)} (1 = lock-step)")  # fmt: skip
    return StartRequest(env, num_envs, SPLITS[start.split], int(start.seed), groups, policy_job,
                        bool(start.HasField("policy") and start.policy.stochastic))  # fmt: skip


def start_loc(path: str) -> list:
    """Where a config path of a Start sits in the message."""
    return ["start", path] if path == "num_envs" else ["start", "config", *path.split(".")]


def describe(item: dict[str, Any]) -> str:
    """An admission problem as a line naming its place in the Start."""
    *parent, last = [str(p) for p in item["loc"]]
    if item["msg"].startswith((f"{last}=", f"{last}:")):  # "grid_size=40 exceeds ...": it names itself
        return ".".join(parent) + "." + item["msg"]
    return ".".join(parent) + (f"[{last}]" if last.isdigit() else f".{last}") + ": " + item["msg"]


def admit_start(req: StartRequest, settings: Settings, runtime: Runtime) -> None:
    """The one admission (limits, rooms, memory), then this stream's own capacities; a Refused
    with every problem of the first check that found any."""
    problems = admit(req.rollout, server_limits(settings), runtime, start_loc)
    if problems:
        code = (grpc.StatusCode.RESOURCE_EXHAUSTED if all(p.get("capacity") for p in problems)
                else grpc.StatusCode.INVALID_ARGUMENT)  # fmt: skip
        raise Refused(code, "; ".join(describe(p) for p in problems))
    if req.policy_job is not None and req.num_envs > settings.rollout_policy_max_envs:
        raise Refused(grpc.StatusCode.RESOURCE_EXHAUSTED,
                      f"start.num_envs={req.num_envs} in policy mode; allowed range"
                      f" 1..{settings.rollout_policy_max_envs} (QUICKNAV_ROLLOUT_POLICY_MAX_ENVS)")  # fmt: skip
    message_bytes = 2 * req.num_envs * req.env.obs_dim * 4
    if message_bytes > settings.grpc_max_message_mb * 2**20:
        raise Refused(
            grpc.StatusCode.RESOURCE_EXHAUSTED,
            f"start.num_envs={req.num_envs} with obs_dim={req.env.obs_dim} needs messages of up to"
            f" {message_bytes / 2**20:.1f} MiB; this server allows {settings.grpc_max_message_mb} MiB"
            " (QUICKNAV_GRPC_MAX_MESSAGE_MB): use fewer envs or beams per stream",
        )
