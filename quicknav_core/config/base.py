"""The base of every config model: strict, immutable, JSON-serialisable."""

from __future__ import annotations

import math
import types
from typing import Annotated, Any, ClassVar, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Strict, model_validator

from quicknav_core.markers import (  # noqa: F401 (the config package's names for them)
    STATIC,
    TRACED,
    static_fields,
    traced,
    traced_fields,
    traced_values,
)

Split = Literal["train", "test"]


class StrictModel(BaseModel):
    """Unknown fields are errors, NaN and infinities are refused, models are immutable and JSON-serialisable."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False
    )

    # the fields that take a number only, found once per model class (a frozenset, never changed)
    __numeric_fields__: ClassVar[frozenset[str]] = frozenset()

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        cls.__numeric_fields__ = _numeric_fields(cls)

    @model_validator(mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, data: Any) -> Any:
        # pydantic reads true as 1 where a number is expected; the documents say "integer" or
        # "number", and a JSON boolean is neither
        if isinstance(data, dict):
            for name in cls.__numeric_fields__:
                if isinstance(data.get(name), bool):
                    raise ValueError(f"{name}: {str(data[name]).lower()} is a boolean; a number is expected")
        return data


def _numeric_fields(model: type[BaseModel]) -> frozenset[str]:
    """The fields of ``model`` that take a number (int or float, or either or None) only."""

    def numeric(kind: Any) -> bool:
        if get_origin(kind) is Annotated:
            return numeric(get_args(kind)[0])
        if get_origin(kind) in (Union, types.UnionType):
            kinds = [k for k in get_args(kind) if k is not type(None)]
            return bool(kinds) and all(numeric(k) for k in kinds)
        return kind in (int, float)

    return frozenset(name for name, field in model.model_fields.items() if numeric(field.annotation))


# a JSON boolean, not 0, 1 or "yes": what the documents say a boolean field takes is what it takes
Flag = Annotated[bool, Strict()]


def tag_required(tag: str) -> ConfigDict:
    """The config of one member of a tagged union (``algorithm.name``, ``network.kind``): the tag
    keeps its default in Python (``PPOConfig()`` is PPO), but the JSON schema marks it required,
    because the union cannot tell its members apart without it (the API refuses a body that
    leaves it out, and its document must say so)."""

    def mark(schema: dict[str, Any]) -> None:
        schema["required"] = [tag, *(f for f in schema.get("required", ()) if f != tag)]

    return ConfigDict(json_schema_extra=mark)


EXACTLY_ONE_OF = "x-exactly-one-of"


def exactly_one_of(first: str, second: str, also=None) -> ConfigDict:
    """The config of a request that takes exactly one of two fields (a preset or a config, a job or
    a baseline). Its JSON schema names the pair (``x-exactly-one-of``); the service's OpenAPI
    document turns that into one variant per field (``quicknav_service.api.openapi``), so that
    what the document calls valid is what the model accepts."""

    def mark(schema: dict[str, Any]) -> None:
        schema[EXACTLY_ONE_OF] = [first, second]
        if also is not None:  # the model's own schema rule (a parent's json_schema_extra)
            also(schema)

    return ConfigDict(json_schema_extra=mark)


def json_safe(value: Any) -> Any:
    """JSON without NaN/Infinity (browsers' JSON.parse rejects them): non-finite floats -> null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
