"""This server's limits (QUICKNAV_MAX_*), checked on resolved configs at submission.

Each check returns every violation as an error item (``{"loc", "msg", "type"}``) whose ``loc``
names the field of the request that set the value: an override's key (down to the field of a
section sent as an object), the field of a full config, or the preset it came from.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from quicknav_core.config import EnvConfig, EvalConfig, SweepConfig, TrainConfig
from quicknav_service.settings import Settings

Items = list[dict[str, Any]]


def limit_error(loc: list[str], msg: str) -> dict[str, Any]:
    return {"loc": list(loc), "msg": msg, "type": "limit"}


# (field, setting, smallest value the model allows): what every door checks an env against
ENV_LIMITS = (("grid_size", "max_grid_size", 4), ("lidar_beams", "max_lidar_beams", 1))


def over_limit(field: str, value: int, s: Settings, name: str, low: int = 1) -> str | None:
    """The message for ``value`` of ``field`` above the setting ``name`` (None if within)."""
    limit = getattr(s, name)
    if value <= limit:
        return None
    return (f"{field}={value} exceeds this server's limit {name}={limit}"
            f" (QUICKNAV_{name.upper()}); allowed range {low}..{limit}")  # fmt: skip


def check_env(env: EnvConfig, s: Settings, loc: Callable[[str], list[str]]) -> Items:
    """This server's limits on an env (grid, beams), the one place they are checked: train and
    sweep bodies, eval bodies and gRPC Starts alike. ``loc(field)`` names the field as sent."""
    items: Items = []
    for field, name, low in ENV_LIMITS:
        if (msg := over_limit(field, getattr(env, field), s, name, low)) is not None:
            items.append(limit_error(loc(field), msg))
    if env.rooms == "maps" and env.maps is not None:
        from quicknav_service.maps import install_resolver

        install_resolver(s)  # uploaded maps (map:<id>) are read from this server's artifact store
        items += check_maps(env, loc)
    return items


def check_maps(env: EnvConfig, loc: Callable[[str], list[str]]) -> Items:
    """A service reads only the maps uploaded to it (``map:<id>``), and each must fit the env's
    grid: refused here, naming the entry, rather than when a worker builds the rooms."""
    from quicknav_core.env.maps import MAP_ID_PREFIX, MapError, is_map_id
    from quicknav_core.env.room_sources import map_rooms

    items: Items = []
    for split in ("train", "test"):
        for i, name in enumerate(getattr(env.maps, split) or []):
            if not is_map_id(name):
                items.append(limit_error([*loc(f"maps.{split}"), i], (
                    f"{name!r} is a file on your disk, which this service's workers cannot read:"
                    f" upload it (POST /maps, `quicknav maps upload`) and name it {MAP_ID_PREFIX}<id>")))
    if items:
        return items
    for split in ("train", "test") if env.maps.test else ("train",):
        try:
            map_rooms(env, split)
        except MapError as e:
            items.append(limit_error(loc(f"maps.{split}"), str(e)))
    return items


class Origin:
    """Where a field of the resolved config came from in the request body."""

    def __init__(self, body: dict[str, Any], config_key: str = "config", fallback: str = "preset",
                 shorthands: tuple[str, ...] = (), prefix: str = ""):  # fmt: skip
        self.body = body
        self.config_key = config_key
        self.fallback = fallback
        self.shorthands = shorthands  # top-level request fields that set a config field
        self.prefix = prefix  # path of the config inside the resolved one (sweep: "base.")

    def loc(self, path: str) -> list[str]:
        overrides = self.body.get("overrides") or {}
        for key in (path, path.removeprefix(self.prefix)):
            if key in overrides:
                return ["overrides", key]
            # a section sent as an object ({"env": {"grid_size": 100}}): down to the field
            sections = [k for k in overrides if key.startswith(k + ".")]
            if sections:
                section = max(sections, key=len)
                return ["overrides", section, *key[len(section) + 1 :].split(".")]
        short = path.removeprefix(self.prefix)
        if short in self.shorthands and self.body.get(short) is not None:
            return [short]
        if self.body.get(self.config_key) is not None:
            return [self.config_key, *path.split(".")]
        return [self.fallback]


def check_memory(estimate, s: Settings, loc: list[str]) -> Items:
    """Refuse a job whose estimated peak memory exceeds the server's budget."""
    from quicknav_core.train.memory import megabytes

    need = megabytes(estimate.total)
    if need <= s.max_job_memory_mb:
        return []
    return [limit_error(
            loc,
            f"{estimate.field or 'this job'}: the job needs about {need:,} MB ({estimate.describe()}),"
            f" more than this server's budget max_job_memory_mb={s.max_job_memory_mb:,}"
            " (QUICKNAV_MAX_JOB_MEMORY_MB)",
        )]


def check_train(cfg: TrainConfig, s: Settings, origin: Origin, prefix: str = "") -> Items:
    """This server's limits on a training config (a sweep's base with ``prefix="base."``)."""
    items: Items = []
    for path, name in (("num_envs", "max_envs"), ("total_steps", "max_total_steps")):
        if (msg := over_limit(path, getattr(cfg, path), s, name)) is not None:
            items.append(limit_error(origin.loc(prefix + path), msg))
    items += check_env(cfg.env, s, lambda field: origin.loc(f"{prefix}env.{field}"))
    devices = s.max_devices if cfg.devices == "all" else cfg.devices
    if devices > s.max_devices:
        items.append(limit_error(
            origin.loc(prefix + "devices"),
            f"devices={cfg.devices} but this server's workers have {s.max_devices} device(s) per"
            f" job; allowed: 1..{s.max_devices} or 'all' (QUICKNAV_MAX_DEVICES)",
        ))
    elif cfg.devices == "all" and cfg.num_envs % devices:
        items.append(limit_error(
            origin.loc(prefix + "devices"),
            f"devices='all' is {devices} device(s) here, which must divide num_envs={cfg.num_envs}",
        ))
    if not prefix and not items:  # a sweep's base is checked as the sweep's trials, side by side
        from quicknav_core.train.memory import train_memory

        est = train_memory(cfg)
        items += check_memory(est, s, origin.loc(est.field))
    return items


def check_sweep(cfg: SweepConfig, s: Settings, origin: Origin) -> Items:
    """This server's limits on a sweep: its own and its base's."""
    items: Items = []
    if cfg.storage is not None:
        items.append(limit_error(
            origin.loc("storage"),
            "sweep jobs keep their study in the job's folder; leave storage unset",
        ))  # fmt: skip
    if cfg.trials > s.max_sweep_trials:
        items.append(limit_error(
            origin.loc("trials"),
            f"trials={cfg.trials} exceeds this server's limit max_sweep_trials={s.max_sweep_trials}",
        ))  # fmt: skip
    items += check_train(cfg.base, s, origin, prefix="base.")
    if items:  # the memory estimate of a sweep already refused says nothing new
        return items
    from quicknav_core.train.memory import sweep_memory

    est = sweep_memory(cfg)
    return check_memory(est, s, origin.loc(est.field if est.field == "parallel" else "base." + est.field))


def check_eval(cfg: EvalConfig, s: Settings) -> Items:
    """This server's limits on an evaluation."""
    items: Items = []
    if cfg.episodes > s.max_eval_episodes:
        items.append(limit_error(
            ["episodes"],
            f"episodes={cfg.episodes} exceeds this server's limit max_eval_episodes={s.max_eval_episodes}",
        ))  # fmt: skip
    if cfg.env is not None:
        items += check_env(cfg.env, s, lambda field: ["env", *field.split(".")])
    if items:
        return items
    from quicknav_core.train.memory import eval_memory

    est = eval_memory(cfg)
    loc = ["episodes"] if est.field == "episodes" else ["env", *est.field.removeprefix("env.").split(".")]
    return check_memory(est, s, loc)
