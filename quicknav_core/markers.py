"""What a config field is to compiled code, declared once on the field and read from there.

Config models mark their fields (pydantic's ``json_schema_extra``); the env, the trainers and the
batched trials read the marks with the functions here. This module imports nothing of QuickNav, so
both the config package and the env use it without depending on each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, get_args

if TYPE_CHECKING:  # pragma: no cover
    from pydantic import BaseModel

# What a field is to compiled code, declared once on the field (``json_schema_extra``), as rejax
# declares it on its struct fields:
# TRACED: its value ends up as a traced number (``EnvParams``, an algorithm's hyperparameters):
#   vmappable, never recompiles; trials that differ only in traced fields train side by side in one
#   compiled program (``quicknav_core.train.batched``). ``param`` names the pytree field when it
#   differs from the config's; a choice (a Literal) travels as its index.
# STATIC: its value fixes shapes or code paths: part of the env's compile key.
# Neither: what the room banks hold (where rooms come from, their seed and number).
TRACED = {"traced": True}
STATIC = {"static": True}


def traced(param: str) -> dict[str, Any]:
    """TRACED, for a field whose pytree field is called ``param``."""
    return {"traced": True, "param": param}


def _marked(model: type[BaseModel], mark: str) -> dict[str, dict[str, Any]]:
    return {name: field.json_schema_extra for name, field in model.model_fields.items()
            if isinstance(field.json_schema_extra, dict) and field.json_schema_extra.get(mark)}  # fmt: skip


def traced_fields(model: type[BaseModel]) -> frozenset[str]:
    """Names of the fields of ``model`` marked as traced numbers."""
    return frozenset(_marked(model, "traced"))


def static_fields(model: type[BaseModel]) -> tuple[str, ...]:
    """Names of the fields of ``model`` that fix compiled code, in declaration order."""
    return tuple(_marked(model, "static"))


def traced_values(config: BaseModel) -> dict[str, float | int]:
    """Every traced number of ``config`` (not of its sections) under its pytree name: numbers as
    they are, a choice among literals as its index."""
    out: dict[str, float | int] = {}
    for name, extra in _marked(type(config), "traced").items():
        value = getattr(config, name)
        if isinstance(value, str):  # a Literal choice: its index among the allowed values
            value = get_args(type(config).model_fields[name].annotation).index(value)
        if isinstance(value, int | float) and not isinstance(value, bool):
            out[extra.get("param", name)] = value
    return out
