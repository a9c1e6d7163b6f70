"""Admission: whether a resolved config may run here, decided by one function that every door calls
(REST, the CLI, gRPC ``Start``, the ``Policy`` stream).

    problems = admit(config, limits, runtime, loc)     # [] when it may run

The checks, in this order, each naming the request field that set the value (``loc(path)`` maps a
config path such as ``env.grid_size`` to it) and what is allowed:

- this door's limits (``Limits``: a server's QUICKNAV_MAX_* settings; none on the command line):
  grid, beams, envs, steps, episodes, trials;
- rooms: a map that cannot be read or does not fit the grid, a map a server cannot read (a file on
  the client's disk), a robot wider than every room's passages (``env.room_sources.check_rooms``);
- devices: as many as the job asks for, dividing its env batch;
- memory: the job's estimated peak (``train.memory``) within the budget.

A check that finds problems stops the later ones (a config refused for its grid is not also
carved for its rooms); every problem of one check is reported together.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from quicknav_core.config import EnvConfig, EvalConfig, SweepConfig, TrainConfig
from quicknav_core.runtime import Runtime

Items = list[dict[str, Any]]
Loc = Callable[[str], list]

# (config field, limit, smallest value the model allows): the env fields a door may cap
ENV_LIMITS = (("grid_size", "max_grid_size", 4), ("lidar_beams", "max_lidar_beams", 1))


@dataclass(frozen=True)
class RolloutRequest:
    """What a gRPC ``Start`` asks to run: ``num_envs`` envs of ``env`` (``policy``: episodes of a
    trained policy instead of envs stepped by the agent)."""

    env: EnvConfig
    num_envs: int
    split: str = "train"
    policy: bool = False


@dataclass(frozen=True)
class PolicyRequest:
    """What the ``Policy`` stream serves: the policy a train job trained with ``config``."""

    config: TrainConfig


@dataclass(frozen=True)
class Limits:
    """What a door allows; ``None`` is no cap. A server fills it from its settings
    (``quicknav_service.jobs.limits.server_limits``); the command line from the machine."""

    max_grid_size: int | None = None
    max_lidar_beams: int | None = None
    max_envs: int | None = None
    max_total_steps: int | None = None
    max_eval_episodes: int | None = None
    max_sweep_trials: int | None = None
    max_devices: int | None = None  # devices one job may span
    max_job_memory_mb: int | None = None
    # a wide robot is checked against at most this many rooms of each bank (None: every room);
    # a door that does not build the env sets it (clearance.check_fit)
    fit_rooms: int | None = None
    stored_maps_only: bool = False  # a server reads only maps uploaded to it (``map:<id>``)
    own_sweep_storage: bool = False  # a server keeps a sweep's study itself
    owner: str = "this machine's"  # whose limits, in messages
    # the setting that raises a limit, in messages: " (QUICKNAV_MAX_GRID_SIZE)"
    setting: Callable[[str], str] = field(default=lambda name: "", repr=False)


def limit_error(loc: list, msg: str, capacity: bool = False) -> dict[str, Any]:
    """An error item; ``capacity``: the request is valid but more than this door can take now
    (envs, memory), which gRPC answers RESOURCE_EXHAUSTED rather than INVALID_ARGUMENT."""
    return {"loc": list(loc), "msg": msg, "type": "limit", **({"capacity": True} if capacity else {})}


def over_limit(field_name: str, value: int, limits: Limits, name: str, low: int = 1) -> str | None:
    """The message for ``value`` of ``field_name`` above the limit ``name`` (None if within)."""
    cap = getattr(limits, name)
    if cap is None or value <= cap:
        return None
    return (f"{field_name}={value} exceeds {limits.owner} limit {name}={cap}{limits.setting(name)};"
            f" allowed range {low}..{cap}")  # fmt: skip


def admit(config: Any, limits: Limits, runtime: Runtime | None = None, loc: Loc | None = None
          ) -> Items:  # fmt: skip
    """Every reason ``config`` (a TrainConfig, SweepConfig, EvalConfig, RolloutRequest or
    PolicyRequest) may not run under ``limits``, as error items; [] when it may."""
    loc = loc or (lambda path: path.split("."))
    if isinstance(config, TrainConfig):
        return _train(config, limits, runtime, loc)
    if isinstance(config, SweepConfig):
        return _sweep(config, limits, runtime, loc)
    if isinstance(config, EvalConfig):
        return _eval(config, limits, runtime, loc)
    if isinstance(config, RolloutRequest):
        return _rollout(config, limits, runtime, loc)
    if isinstance(config, PolicyRequest):
        return _policy(config, limits, loc)
    raise TypeError(f"admit: no admission rule for {type(config).__name__}")


# --------------------------------------------------------------------------- the checks
def env_limits(env: EnvConfig, limits: Limits, loc: Loc, prefix: str = "") -> Items:
    """This door's caps on an env (grid, beams)."""
    return [limit_error(loc(prefix + f), msg) for f, name, low in ENV_LIMITS
            if (msg := over_limit(f, getattr(env, f), limits, name, low)) is not None]  # fmt: skip


def rooms(env: EnvConfig, limits: Limits, runtime: Runtime | None, loc: Loc, prefix: str = "") -> Items:
    """Rooms that cannot be had: maps a server cannot read or that do not fit, a robot that fits
    in no room."""
    from quicknav_core.env.clearance import check_fit
    from quicknav_core.env.maps import MAP_ID_PREFIX, MapError, is_map_id
    from quicknav_core.env.room_sources import MapRooms, room_source

    source = room_source(env, runtime)
    items: Items = []
    if isinstance(source, MapRooms):
        splits = ("train", "test") if env.maps.test else ("train",)
        if limits.stored_maps_only:
            for split in ("train", "test"):
                for i, name in enumerate(getattr(env.maps, split) or []):
                    if not is_map_id(name):
                        items.append(limit_error([*loc(f"{prefix}maps.{split}"), i], (
                            f"{name!r} is a file on your disk, which this service's workers cannot"
                            f" read: upload it (POST /maps, `quicknav maps upload`) and name it"
                            f" {MAP_ID_PREFIX}<id>")))  # fmt: skip
            if items:
                return items
        for split in splits:
            try:
                source.rooms(split)
            except MapError as e:
                items.append(limit_error(loc(f"{prefix}maps.{split}"), str(e)))
        if items:
            return items
    try:
        check_fit(env, source, at_most=limits.fit_rooms)
    except ValueError as e:
        named = str(e).split(":", 1)[0]
        where = named if named in ("robot_radius", "randomize.robot_radius_m") else "robot_radius"
        items.append(limit_error(loc(prefix + where), str(e)))
    return items


def devices(cfg: TrainConfig, limits: Limits, loc: Loc, prefix: str = "") -> Items:
    """As many devices as the job asks for, and a count that divides its env batch."""
    cap = limits.max_devices
    if cap is None:
        return []
    asked = cap if cfg.devices == "all" else cfg.devices
    if asked > cap:
        return [limit_error(loc(prefix + "devices"), (
            f"devices={cfg.devices} but {limits.owner} jobs get {cap} device(s) each;"
            f" allowed: 1..{cap} or 'all'{limits.setting('max_devices')}"))]  # fmt: skip
    if cfg.num_envs % asked:
        return [limit_error(loc(prefix + "devices"), (
            f"devices={cfg.devices!r} is {asked} device(s) here, which must divide"
            f" num_envs={cfg.num_envs}"))]  # fmt: skip
    return []


def memory(estimate, limits: Limits, loc: list) -> Items:
    """A job whose estimated peak memory exceeds the budget."""
    from quicknav_core.train.memory import megabytes

    need = megabytes(estimate.total)
    if limits.max_job_memory_mb is None or need <= limits.max_job_memory_mb:
        return []
    return [limit_error(loc, (
        f"{estimate.field or 'this job'}: the job needs about {need:,} MB ({estimate.describe()}),"
        f" more than {limits.owner} budget max_job_memory_mb={limits.max_job_memory_mb:,}"
        f"{limits.setting('max_job_memory_mb')}"), capacity=True)]  # fmt: skip


def _caps(cfg: Any, limits: Limits, loc: Loc, caps: tuple[tuple[str, str], ...], prefix: str = ""
          ) -> Items:  # fmt: skip
    return [limit_error(loc(prefix + path), msg) for path, name in caps
            if (msg := over_limit(path, getattr(cfg, path), limits, name)) is not None]  # fmt: skip


def _train(cfg: TrainConfig, limits: Limits, runtime, loc: Loc, prefix: str = "",
           trials: int = 1) -> Items:  # fmt: skip
    items = _caps(cfg, limits, loc, (("num_envs", "max_envs"), ("total_steps", "max_total_steps")),
                  prefix)  # fmt: skip
    items += env_limits(cfg.env, limits, loc, prefix + "env.")
    items += devices(cfg, limits, loc, prefix)
    if items:
        return items
    if items := rooms(cfg.env, limits, runtime, loc, prefix + "env."):
        return items
    if prefix:  # a sweep's base: its memory is the sweep's (trials side by side)
        return []
    from quicknav_core.train.memory import train_memory

    est = train_memory(cfg, trials)
    return memory(est, limits, loc(est.field))


def _sweep(cfg: SweepConfig, limits: Limits, runtime, loc: Loc) -> Items:
    items = _caps(cfg, limits, loc, (("trials", "max_sweep_trials"),))
    if limits.own_sweep_storage and cfg.storage is not None:
        items.append(limit_error(loc("storage"),
                                 "sweep jobs keep their study in the job's folder; leave storage unset"))  # fmt: skip
    items += _train(cfg.base, limits, runtime, loc, prefix="base.")
    if items:  # the memory estimate of a sweep already refused says nothing new
        return items
    from quicknav_core.train.memory import sweep_memory

    est = sweep_memory(cfg)
    return memory(est, limits, loc(est.field if est.field == "parallel" else "base." + est.field))


def _eval(cfg: EvalConfig, limits: Limits, runtime, loc: Loc) -> Items:
    items = _caps(cfg, limits, loc, (("episodes", "max_eval_episodes"),))
    if cfg.env is not None:
        items += env_limits(cfg.env, limits, loc, "env.")
    if items:
        return items
    if cfg.env is not None and (items := rooms(cfg.env, limits, runtime, loc, "env.")):
        return items
    from quicknav_core.train.memory import eval_memory

    est = eval_memory(cfg)
    return memory(est, limits, loc(est.field))


def _rollout(req: RolloutRequest, limits: Limits, runtime, loc: Loc) -> Items:
    items = env_limits(req.env, limits, loc)
    if (msg := over_limit("num_envs", req.num_envs, limits, "max_envs")) is not None:
        items.append(limit_error(loc("num_envs"), msg, capacity=True))
    if items:
        return items
    if items := rooms(req.env, limits, runtime, loc):
        return items
    est, where = stream_estimate(req)
    return memory(est, limits, loc(where))


def stream_estimate(req: RolloutRequest | PolicyRequest):
    """A gRPC stream's estimated peak memory (``train.memory.Estimate``) and the request field
    that its largest part after the process's runtime follows (the runtime is no field's doing):
    what admission holds one stream to, and what a server's open streams add up to
    (``quicknav_service.rollout.common.StreamMemory``)."""
    from quicknav_core.train.memory import eval_memory, policy_memory, rollout_memory

    if isinstance(req, PolicyRequest):
        est = policy_memory(req.config)
    elif req.policy:
        est = eval_memory(EvalConfig(env=req.env, episodes=req.num_envs, split=req.split,
                                     gif_episodes=req.num_envs))  # fmt: skip
    else:
        est = rollout_memory(req.env, req.num_envs, req.split)
    own = {name: size for name, size in est.parts.items() if name != "runtime"}
    field = est.fields.get(max(own, key=own.get), "") if own else ""
    if isinstance(req, PolicyRequest):
        return est, field or "network"
    # a policy-mode stream's estimate is an evaluation's: its episodes are the stream's envs,
    # its env the Start's config
    return est, "num_envs" if field in ("", "episodes", "trajectories") else field.removeprefix("env.")


def _policy(req: PolicyRequest, limits: Limits, loc: Loc) -> Items:
    if items := env_limits(req.config.env, limits, loc, "env."):
        return items
    est, where = stream_estimate(req)
    return memory(est, limits, loc(where))
