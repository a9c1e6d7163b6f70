"""THE path from a request to a config: every door (CLI, REST, SDK) sends a request, ``resolve`` makes it
a validated config, and that config is what runs and what a job stores.

    resolve_train(TrainRequest(preset="demo", overrides={"env.grid_size": 8}))  -> TrainConfig
    resolve_sweep(SweepRequest(space="ppo", trials=8))                        -> SweepConfig
    resolve_eval(EvalRequest(policy="oracle", env={"grid_size": 8}))          -> EvalConfig

A request that cannot become a config raises ``ConfigError`` whose items name the request field
(``["overrides", "env.grid_size"]``, ``["config", "num_envs"]``, ``["preset"]``) and what is allowed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Literal, TypeVar, get_args

from pydantic import (
    AliasChoices,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from quicknav_core.config.base import Flag, Split, StrictModel, exactly_one_of
from quicknav_core.config.env import EnvConfig, MapsConfig
from quicknav_core.config.errors import ConfigError, error_items, unknown_field_msg, unknown_msg
from quicknav_core.config.eval import EvalConfig
from quicknav_core.config.overrides import OverrideError, _models, override_data
from quicknav_core.config.presets import PRESETS, get_preset
from quicknav_core.config.sweep import (
    BUILTIN_SPACES,
    BUILTIN_TOTAL_STEPS,
    SPACE_BASE_PRESET,
    SweepConfig,
    untaken,
)
from quicknav_core.config.train import TrainConfig, unhonoured_fields, with_trainer_defaults

M = TypeVar("M", bound=BaseModel)
SpaceName = Literal["ppo", "sac", "td3", "mlp", "lstm", "gtrxl"]
# the tag values that pydantic puts into error locations of tagged unions
_TAG_VALUES = {"ppo", "sac", "td3", "mlp", "lstm", "gtrxl"}


# --------------------------------------------------------------------------- requests
def _settings_hint(key: str, config: type[BaseModel], what: str) -> str | None:
    head = key.split(".", 1)[0]
    if head not in config.model_fields:
        return None
    return f'{what} go in overrides: {{"overrides": {{"{key}": ...}}}}'


class TrainRequest(StrictModel):
    """A training request: a preset or a full config, plus dotted-key overrides applied on top."""

    model_config = exactly_one_of("preset", "config")

    preset: str | None = Field(None, description="a training preset name (GET /presets lists them)",
                               examples=["demo"], json_schema_extra={"enum": [*PRESETS, None]})  # fmt: skip
    config: TrainConfig | None = Field(None, description="a full TrainConfig")
    overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="dotted keys of TrainConfig with JSON values",
        examples=[{"total_steps": 200000, "env.grid_size": 8}],
    )

    @classmethod
    def unknown_field_hint(cls, key: str) -> str | None:
        """Where a top-level key that is not a request field belongs, if it is a config field."""
        return _settings_hint(key, TrainConfig, "training settings")

    @model_validator(mode="after")
    def _one(self) -> TrainRequest:
        if (self.config is None) == (self.preset is None):
            raise ValueError("give exactly one of 'config' (a TrainConfig) or 'preset' (a preset name)")
        return self


class SweepRequest(StrictModel):
    """A sweep request: a built-in search space or a full SweepConfig, plus overrides.

    ``overrides`` keys are SweepConfig fields (``trials``, ``objective``, ...) or fields of the base
    TrainConfig (``env.grid_size``, ``base.total_steps`` and ``total_steps`` alike); ``trials``,
    ``parallel`` and ``total_steps`` are shorthands for the same.
    """

    model_config = exactly_one_of("space", "config")

    space: SpaceName | None = Field(None, description="a built-in search space (the paper's)")
    base: str | None = Field(
        None, description="with a space: the training preset its trials start from (default: the"
        " space's paper preset, paper-ppo for ppo); its algorithm and network must take the"
        " space's parameters", examples=["building"],
        json_schema_extra={"enum": [*PRESETS, None]},
    )  # fmt: skip
    config: SweepConfig | None = Field(None, description="a full SweepConfig")
    trials: int | None = Field(None, ge=1, le=100_000, description="finished trials wanted")
    parallel: int | None = Field(None, ge=1, le=1024, description="trials asked at once")
    total_steps: int | None = Field(None, ge=1, description="env steps per trial")
    overrides: dict[str, Any] = Field(default_factory=dict, examples=[{"env.grid_size": 8}])

    @classmethod
    def unknown_field_hint(cls, key: str) -> str | None:
        """Where a top-level key that is not a request field belongs, if it is a config field."""
        return _settings_hint(key, SweepConfig, "sweep settings") or _settings_hint(
            key, TrainConfig, "settings of the trials' base config"
        )

    @field_validator("space", mode="before")
    @classmethod
    def _not_a_preset(cls, value: Any) -> Any:
        """A training preset sent as the space: say which space starts from it or tunes it."""
        found = preset_as_space(value) if isinstance(value, str) else None
        if found is not None:
            space, base = found
            how = (f'"space": "{space}" starts from it' if base is None else
                   f'"space": "{space}", "base": "{base}" tunes it')  # fmt: skip
            raise ValueError(f"{value!r} is a training preset, not a search space (allowed:"
                             f" {', '.join(get_args(SpaceName))}); {how}")  # fmt: skip
        return value

    @model_validator(mode="after")
    def _one(self) -> SweepRequest:
        if (self.config is None) == (self.space is None):
            raise ValueError("give exactly one of 'config' (a SweepConfig) or 'space' (a built-in space)")
        if self.base is not None and self.config is not None:
            raise ValueError("'base' goes with 'space': a full SweepConfig carries its own base")
        return self


def not_both_ways(schema: dict[str, Any]) -> None:
    """EvalFields' rule in its JSON schema: ``stochastic`` (deprecated) and ``deterministic`` may
    both be sent only if they agree (one is the other's opposite)."""
    schema["not"] = {"anyOf": [
        {"required": ["stochastic", "deterministic"],
         "properties": {"stochastic": {"const": value}, "deterministic": {"const": value}}}
        for value in (True, False)
    ]}  # fmt: skip


class EvalFields(StrictModel):
    """What every evaluation request holds besides the name of a trained policy: one model that
    the library's ``EvalRequest`` and the service's eval job body both extend."""

    model_config = ConfigDict(json_schema_extra=not_both_ways)

    policy: Literal["random", "oracle", "dwa"] | None = Field(None, description="a baseline policy")
    map: str | None = Field(
        None, min_length=1, max_length=500,
        description="drive this map: a map uploaded to the service ('map:<id>', GET /maps), or a"
        " map_server YAML file for the library; the map is laid on the grid at the policy's own"
        " cell size, and the step limit follows its longest path (twice the time to drive it at"
        " full speed) unless 'env' sets max_steps",
        examples=["map:3f2a9c1d5e7b8a60"],
    )  # fmt: skip
    env: dict[str, Any] = Field(
        default_factory=dict,
        description="EnvConfig fields (dotted keys or sections) set on the policy's env: the "
        "trained policy's own, the defaults for a baseline",
        examples=[{"max_steps": 200}],
    )
    episodes: int = Field(100, ge=1, le=100_000)
    seed: int = Field(0, ge=0, le=2**31 - 1, description="episode seed: same seed, same episodes")
    split: Split = Field("test", description="room bank: test (held out) or train")
    deterministic: Flag = Field(True, description="act with the policy's mean, not a sample")
    robustness: Flag = Field(
        False,
        description="also run the episodes at fixed levels of lidar noise, beam dropout, range bias,"
        " action latency and wheel asymmetry: success and SPL per level in eval.json's"
        " 'robustness', drawn in robustness.png",
    )
    shield: Flag = Field(
        False,
        description="put the safety layer between the policy and the wheels: a command that would"
        " bring the robot within 1 cm of a lidar return is slowed, down to turning in place"
        " (agent '<policy>+shield')",
    )
    stochastic: Flag | None = Field(
        None, deprecated=True,
        description="deprecated: the opposite of 'deterministic'; send 'deterministic' instead",
    )  # fmt: skip

    @property
    def _stochastic(self) -> bool | None:
        """The deprecated field as sent, read without pydantic's warning (that is for callers)."""
        return self.__dict__.get("stochastic")

    @model_validator(mode="after")
    def _not_both_ways(self) -> EvalFields:
        stochastic = self._stochastic
        if (
            stochastic is not None
            and "deterministic" in self.model_fields_set
            and stochastic == self.deterministic
        ):
            raise ValueError(
                f"stochastic={stochastic} contradicts deterministic={self.deterministic};"
                " send only 'deterministic' (stochastic is its deprecated opposite)"
            )
        return self

    @property
    def acts_deterministically(self) -> bool:
        if "deterministic" not in self.model_fields_set and self._stochastic is not None:
            return not self._stochastic
        return self.deterministic


class EvalRequest(EvalFields):
    """An evaluation request: a trained policy or a baseline.

    ``source`` names the trained policy and each door looks it up its own way: the service takes a
    train job's id (also accepted as ``job_id``), the CLI a run folder (also accepted as ``run``).
    """

    source: str | None = Field(
        None,
        validation_alias=AliasChoices("source", "job_id", "run"),
        description="the trained policy: a train job's id (service; alias job_id) or a run folder"
        " (CLI; alias run)",
    )

    @model_validator(mode="before")
    @classmethod
    def _one_source(cls, data: Any) -> Any:
        if isinstance(data, dict):
            named = [k for k in ("source", "job_id", "run") if data.get(k) is not None]
            if len(named) > 1:
                raise ValueError(f"give the trained policy once: {' and '.join(named)} are the same field")
        return data

    @model_validator(mode="after")
    def _one(self) -> EvalRequest:
        if (self.source is None) == (self.policy is None):
            raise ValueError(
                "give exactly one of 'job_id' (a train job; 'source' or 'run' for a run folder)"
                " or 'policy' (random, oracle or dwa)"
            )
        return self


# --------------------------------------------------------------------------- resolving
def _model_at(model: type[BaseModel], loc: list[str]) -> type[BaseModel] | None:
    """The model that holds the field at ``loc`` (pydantic's error location inside ``model``)."""
    parts = list(loc)
    while parts:
        part = parts.pop(0)
        field = model.model_fields.get(part)
        members = _models(field.annotation) if field is not None else []
        if not members:
            return None
        if len(members) > 1:  # a tagged union: pydantic names the variant next in the location
            tag = parts.pop(0) if parts else None
            members = [m for m in members if tag in
                       (m.model_fields[t].default for t in ("kind", "name") if t in m.model_fields)]  # fmt: skip
            if len(members) != 1:
                return None
        model = members[0]
    return model


def explain_unknown_fields(model: type[BaseModel], items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``items`` with pydantic's "Extra inputs are not permitted" turned into a message that says
    what was meant: the closest known name, or (a config field sent beside the request's own) that
    it belongs in ``overrides``."""
    out = []
    for item in items:
        if item.get("type") != "extra_forbidden" or not item["loc"]:
            out.append(item)
            continue
        *parent_loc, key = item["loc"]
        parent = _model_at(model, parent_loc)
        if parent is None:
            out.append(item)
            continue
        hint_of = getattr(parent, "unknown_field_hint", None)
        hint = hint_of(key) if hint_of is not None and not parent_loc else None
        where = ".".join(p for p in parent_loc if p not in _TAG_VALUES) or parent.__name__
        msg = (f"unknown field {key!r}: {hint}" if hint
               else unknown_field_msg(key, where, parent.model_fields))  # fmt: skip
        out.append({**item, "msg": msg, "type": "unknown_field"})
    return out


def _request(cls: type[BaseModel], request: BaseModel | Mapping[str, Any]) -> Any:
    if isinstance(request, cls):
        return request
    if isinstance(request, BaseModel):
        request = request.model_dump(exclude_unset=True)
    try:
        return cls.model_validate(request)
    except ValidationError as e:
        raise ConfigError(explain_unknown_fields(cls, error_items(e)), title=cls.__name__) from None


class _Where:
    """Maps a location inside the resolved config back to the request field that set it."""

    def __init__(self, fallback: list[str], config_root: list[str] | None = None):
        self.fallback = fallback
        self.config_root = config_root
        self.sources: list[tuple[list[str], list[str]]] = []  # (config path, request loc)

    def add(self, config_path: str, request_loc: list[str]) -> None:
        self.sources.append((config_path.split("."), request_loc))

    def locate(self, loc: list[str], msg: str = "") -> list[str]:
        path = [p for p in loc if p not in _TAG_VALUES]
        best: tuple[int, list[str]] | None = None
        for cfg_path, req_loc in self.sources:
            n = len(cfg_path)
            if path[:n] == cfg_path and (best is None or n > best[0]):
                best = (n, req_loc)
        if best is not None:
            # a section sent as an object ({"env": {"grid_size": 1000}}): down to the field
            return [*best[1], *path[best[0]:]]
        # an error of a whole section (a check across fields): the request field inside it that
        # the message names, e.g. "total_steps=1 is less than one update" -> the total_steps sent
        inside = [(p, r) for p, r in self.sources if p[: len(path)] == path]
        named = [r for p, r in inside if f"{p[-1]}=" in msg or f".{p[-1]}" in msg]
        if len(named) == 1 or (len(inside) == 1 and not named):
            return named[0] if named else inside[0][1]
        if self.config_root is not None:
            return [*self.config_root, *loc]
        return self.fallback

    def items(self, e: ValidationError) -> list[dict[str, Any]]:
        return [{**item, "loc": self.locate(item["loc"], item["msg"]), "field": ".".join(item["loc"])}
                for item in error_items(e)]  # fmt: skip


def _apply(schema: type[BaseModel], data: dict, changes, where: _Where) -> list[dict[str, Any]]:
    """Set each ``(config path, value, request loc)`` in ``data``; the unknown keys' errors (all of
    them: the rest are still applied, so their bad values are reported in the same answer)."""
    problems = []
    for path, value, loc in changes:
        try:
            override_data(schema, {path: value}, data=data)
        except OverrideError as e:
            problems.append({"loc": list(loc), "msg": e.message, "type": "unknown_field"})
            continue
        where.add(path, loc)
    return problems


def _validate(schema: type[M], data: dict, where: _Where, problems: list[dict[str, Any]]) -> M:
    """``data`` as a ``schema``; every problem of the request in one ConfigError."""
    try:
        config = schema.model_validate(data)
    except ValidationError as e:
        raise ConfigError([*problems, *where.items(e)], title=e.title) from None
    if problems:
        raise ConfigError(problems, title=schema.__name__)
    return config


def resolve_train(request: TrainRequest | Mapping[str, Any]) -> TrainConfig:
    """The TrainConfig a training request asks for (preset or config, then the overrides)."""
    req: TrainRequest = _request(TrainRequest, request)
    if req.preset is not None:
        try:
            base = get_preset(req.preset)
        except ValueError:
            raise ConfigError.single(
                ["preset"], unknown_msg("preset", req.preset, PRESETS)
            ) from None
        where = _Where(fallback=["preset"])
    else:
        base = req.config
        where = _Where(fallback=["config"], config_root=["config"])
    data = base.model_dump(mode="json")
    changes = [(key, value, ["overrides", key]) for key, value in req.overrides.items()]
    problems = _apply(TrainConfig, data, changes, where)
    return _honoured(_validate(TrainConfig, data, where, problems), where)


def _honoured(config: TrainConfig, where: _Where, inside: tuple[str, ...] = ()) -> TrainConfig:
    """``config`` with what it leaves to its trainer written in; refused, every field named, if
    its trainer cannot do what a field says (what a config names is what runs)."""
    problems = [{"loc": where.locate([*inside, *path.split(".")], msg), "msg": msg,
                 "type": "not_honoured", "field": ".".join([*inside, path])}
                for path, msg in unhonoured_fields(config)]  # fmt: skip
    if problems:
        raise ConfigError(problems, title="TrainConfig")
    return with_trainer_defaults(config)


def _sweep_key(key: str) -> str:
    """A sweep override key as a SweepConfig path: base fields may be given without ``base.``."""
    head = key.split(".", 1)[0]
    return key if head in SweepConfig.model_fields else f"base.{key}"


def resolve_sweep(request: SweepRequest | Mapping[str, Any]) -> SweepConfig:
    """The SweepConfig a sweep request asks for (space or config, then the overrides)."""
    req: SweepRequest = _request(SweepRequest, request)
    if req.space is not None:
        base = _space_base(req.space, req.base).model_dump(mode="json")
        base["total_steps"] = BUILTIN_TOTAL_STEPS
        name = req.space if req.base is None else f"{req.space}-{req.base}"
        data = {"base": base, "space": BUILTIN_SPACES[req.space], "study_name": name}
        where = _Where(fallback=["space"])
    else:
        data = req.config.model_dump(mode="json")
        where = _Where(fallback=["config"], config_root=["config"])
    shorthands = (
        ("trials", "trials", req.trials),
        ("parallel", "parallel", req.parallel),
        ("total_steps", "base.total_steps", req.total_steps),
    )
    changes = [(path, value, [name]) for name, path, value in shorthands if value is not None]
    changes += [(_sweep_key(k), v, ["overrides", k]) for k, v in req.overrides.items()]
    problems = _apply(SweepConfig, data, changes, where)
    config = _validate(SweepConfig, data, where, problems)
    return config.model_copy(update={"base": _honoured(config.base, where, ("base",))})


def _space_base(space: str, preset: str | None) -> TrainConfig:
    """The TrainConfig a built-in space's trials start from: ``preset`` (the request's ``base``)
    or the space's paper preset; refused, naming ``base``, unless it takes every parameter of the
    space (space ppo tunes a PPO preset, lstm an LSTM one, ...)."""
    if preset is None:
        return get_preset(SPACE_BASE_PRESET[space])
    if preset not in PRESETS:
        raise ConfigError.single(["base"], unknown_msg("preset", preset, PRESETS))
    config = get_preset(preset)
    missing = list(untaken(config, BUILTIN_SPACES[space]))
    if missing:
        takes = spaces_for(preset)
        hint = f"; spaces it takes: {', '.join(takes)}" if takes else ""
        raise ConfigError.single(["base"], f"preset {preset!r} (algorithm {config.algorithm.name},"
                                 f" network {config.network.kind}) has no {', '.join(missing)}"
                                 f" for space {space!r} to tune{hint}")  # fmt: skip
    return config  # the rest (no curriculum, ...) SweepConfig checks of every base


def preset_as_space(name: str) -> tuple[str, str | None] | None:
    """For a training preset named where a space goes: (the space whose trials start from it,
    None), or (a space that tunes it, the preset as its ``base``); None for a name that is a space,
    is no preset, or is a preset no space can tune."""
    if name in get_args(SpaceName) or name not in PRESETS:
        return None
    own = [space for space, base in SPACE_BASE_PRESET.items() if base == name]
    if own:
        return own[0], None
    takes = spaces_for(name)
    return (takes[0], name) if takes else None


def spaces_for(preset: str) -> list[str]:
    """The built-in spaces that can tune a preset (``SweepRequest.base``): those whose every
    parameter the preset has."""
    config = get_preset(preset)
    return [space for space in BUILTIN_SPACES if not untaken(config, BUILTIN_SPACES[space])]


TrainedEnv = Callable[[str], EnvConfig]
# how a door lays a named map on the grid for an env: (env, map, how the map is read: the fields
# of env.maps but its lists) -> env on the map
MapEnv = Callable[[EnvConfig, str, dict[str, Any]], EnvConfig]


def resolve_env(fields: Mapping[str, Any], base: EnvConfig | None = None) -> EnvConfig:
    """An EnvConfig from fields (sections or dotted keys) set on ``base`` (default: the defaults).

    The env of a baseline evaluation, of ``quicknav env demo`` and of a gRPC Rollout ``Start``;
    errors name the field as sent (``loc`` = its key).
    """
    base = base or EnvConfig()
    where = _Where(fallback=[])
    data = base.model_dump(mode="json")
    problems = _apply(EnvConfig, data, [(key, value, [key]) for key, value in fields.items()], where)
    return _validate(EnvConfig, data, where, problems)


def _map_keys(req: EvalFields) -> set[str]:
    """The request's env keys that say how its map is read (``maps.<field>``)."""
    return {k for k in req.env if k.startswith("maps.")} if req.map is not None else set()


def _env_fields(req: EvalFields) -> dict[str, Any]:
    """The request's env fields but those of its map (``_map_keys``); a whole ``maps`` section (a
    config file's) keeps how it reads maps, and its map lists become the request's map."""
    fields = {k: v for k, v in req.env.items() if k not in _map_keys(req)}
    if req.map is not None and isinstance(fields.get("maps"), Mapping):
        fields["maps"] = {**fields["maps"], "train": [str(req.map)], "test": None}
    return fields


def _map_reading(req: EvalFields, env: EnvConfig) -> dict[str, Any]:
    """How the request's map is read: the policy's own ``env.maps`` fields (its maps' scale,
    thresholds, unknown pixels), then the request's ``env.maps.<field>`` keys (a plain image's
    ``resolution``). The maps themselves are the request's ``map`` alone."""
    reading = env.maps.reading() if env.maps is not None else {}
    for key in sorted(_map_keys(req)):
        field = key.removeprefix("maps.")
        if field in ("train", "test"):
            raise ConfigError.single(["env", key], "the map evaluated on is the request's map"
                                     " (--map): leave maps.train and maps.test unset")  # fmt: skip
        reading[field] = req.env[key]
    try:
        MapsConfig.model_validate({**reading, "train": [str(req.map)]})
    except ValidationError as e:
        raise ConfigError([{"loc": ["env", ".".join(["maps", *map(str, i["loc"])])], "msg": i["msg"],
                            "type": i["type"]} for i in e.errors()], title="EvalRequest") from None  # fmt: skip
    return reading


def _on_map(req: EvalFields, env: EnvConfig, map_env: MapEnv | None) -> EnvConfig:
    """``env`` on the request's map (``map_env``: the door's fitting, ``eval.map_fit.env_on_map``),
    read as ``_map_reading`` says; the request's own ``env.max_steps`` wins over the map's step
    limit."""
    if map_env is None:
        raise ConfigError.single(["map"], "this door cannot lay maps on the grid; set the env's"
                                 " rooms, grid and step limit instead (quicknav eval --map does)")  # fmt: skip
    reading = _map_reading(req, env)
    try:
        on_map = map_env(env, str(req.map), reading)
        if "max_steps" in req.env:
            on_map = resolve_env({"max_steps": req.env["max_steps"]}, on_map)
    except (ConfigError, ValueError, OSError) as e:  # a MapError is a ValueError
        why = "; ".join(i["msg"] for i in e.items) if isinstance(e, ConfigError) else str(e)
        raise ConfigError.single(["map"], why) from None
    return on_map


def resolve_eval(
    request: EvalRequest | Mapping[str, Any], trained_env: TrainedEnv | None = None,
    map_env: MapEnv | None = None,
) -> EvalConfig:  # fmt: skip
    """The EvalConfig an eval request asks for, its env resolved.

    ``trained_env(source)`` gives the env a trained policy was trained in (the CLI reads the run
    folder, the service the train job's stored config); it raises ``ConfigError`` for an unknown
    source. ``env`` overrides apply on top; they may not change the observation's length.
    ``map_env(env, map, reading)`` lays the request's ``map`` on the grid at that env's cell size,
    read as ``reading`` says (``_map_reading``: env keys ``maps.<field>`` such as a plain image's
    ``maps.resolution`` apply to the map, on the policy's own; a door
    passes ``quicknav_core.eval.map_fit.env_on_map`` with how it reads maps; without it a request
    that names a map is refused).
    """
    req: EvalRequest = _request(EvalRequest, request)
    source = req.source
    if source is not None:
        if trained_env is None:
            raise ConfigError.single(["source"], "this door cannot look up trained policies")
        base_env = trained_env(source)
    else:
        base_env = EnvConfig()
    try:  # with a map, how it is read applies when it is laid (_map_reading)
        env = resolve_env(_env_fields(req), base_env)
    except ConfigError as e:
        raise ConfigError([{**i, "loc": ["env", *i["loc"]]} for i in e.items], e.title) from None
    if req.map is not None:
        env = _on_map(req, env, map_env)
    if source is not None and env.obs_dim != base_env.obs_dim:
        raise ConfigError.single(
            ["env"],
            f"the policy was trained on {base_env.obs_dim}-long observations (lidar_beams="
            f"{base_env.lidar_beams}, observe_goal={base_env.observe_goal}); these env overrides"
            f" make them {env.obs_dim} long: keep lidar_beams and observe_goal",
        )
    return EvalConfig(
        policy="trained" if source is not None else req.policy,
        source=source,
        env=env,
        episodes=req.episodes,
        seed=req.seed,
        split=req.split,
        deterministic=req.acts_deterministically,
        robustness=req.robustness,
        shield=req.shield,
    )
