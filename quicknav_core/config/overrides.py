"""One override mechanism for every door: dotted keys with typed values, applied to a config model.

    apply_overrides(TrainConfig(), {"env.grid_size": 8, "algorithm.learning_rate": 1e-3})

Keys walk the model's fields (an unknown one is named together with the fields that exist); values
are JSON values (numbers, strings, booleans, lists, objects; an object merges into a section); the
result is validated as a whole. Setting a discriminator (``algorithm.name``, ``network.kind``) to
another variant starts that section from the new variant's defaults. For an MLP,
``network.hidden_layers`` and ``network.hidden_size`` set ``hidden_sizes`` (the sweep spaces use
them). The CLI's ``--set key=value`` strings become such a dict through ``parse_assignments``.
"""

from __future__ import annotations

import json
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Annotated, Any, TypeVar

from pydantic import BaseModel

from quicknav_core.config.errors import unknown_field_msg

M = TypeVar("M", bound=BaseModel)

# Tag fields of the discriminated unions (algorithm.name, network.kind).
_TAGS = ("kind", "name")
# Parameters of an MLP that are not fields: they set ``hidden_sizes`` (layers x size).
_MLP_SHAPE = ("hidden_layers", "hidden_size")


class OverrideError(ValueError):
    """An override that names no field, or walks into a field that has no sub-fields."""

    def __init__(self, key: str, message: str):
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


def parse_value(text: str) -> Any:
    """A ``--set`` value: JSON where it parses (numbers, true/false, null, lists), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_assignments(items: Iterable[str]) -> dict[str, Any]:
    """``["env.grid_size=8", ...]`` as ``{"env.grid_size": 8, ...}`` (later keys win)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise OverrideError(item, "expected key=value, e.g. env.grid_size=8")
        out[key.strip()] = parse_value(value)
    return out


def as_dict(overrides: Mapping[str, Any] | Iterable[str] | None) -> dict[str, Any]:
    """Overrides given as a mapping or as ``key=value`` strings, as a dict."""
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        return dict(overrides)
    return parse_assignments(overrides)


def _section_with(model: type[BaseModel], name: str) -> str | None:
    """The section of ``model`` (a field holding a model) that has a field ``name``, if one does:
    where a field set one level too high belongs."""
    for section, field in model.model_fields.items():
        if any(name in m.model_fields for m in _models(field.annotation)):
            return section
    return None


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The model classes a field can hold: itself, or the model members of a union/Optional."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _models(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(annotation) for m in _models(a)]
    return []  # a plain value, or a container (dict, list) that pydantic checks at the end


def _model_of(annotation: Any, data: Any) -> type[BaseModel] | None:
    """The model a field holds given its current data: the only one, or the variant of a tagged
    union that ``data``'s tag selects."""
    members = _models(annotation)
    if len(members) == 1:
        return members[0]
    for member in members:
        tags = [t for t in _TAGS if t in member.model_fields]
        if tags and isinstance(data, dict) and all(
            member.model_fields[t].default == data.get(t) for t in tags
        ):
            return member
    return None


def _union_tag(annotation: Any) -> str | None:
    """The tag field of a union of models (None if the field is not one)."""
    members = _models(annotation)
    if len(members) < 2:
        return None
    return next((t for t in _TAGS if all(t in m.model_fields for m in members)), None)


def _is_variant(model: type[BaseModel]) -> bool:
    """Whether ``model`` is one variant of a tagged union (its tag field has a fixed default)."""
    return any(t in model.model_fields for t in _TAGS)


def _set(data: dict, schema: type[BaseModel], key: str, parts: list[str], value: Any,
         pending: list) -> None:  # fmt: skip
    """Set one dotted key in the JSON data of a ``schema`` model."""
    node, model = data, schema
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if model is None:  # inside a free-form value (a dict field): pydantic checks it at the end
            if last:
                node[part] = value
                return
            if not isinstance(node.get(part), dict):
                node[part] = {}
            node = node[part]
            continue
        fields = model.model_fields
        if part in _MLP_SHAPE and "hidden_sizes" in fields:
            if not last:
                raise OverrideError(key, f"{part!r} has no sub-fields")
            pending.append((node, part, value))
            return
        if part not in fields:
            where = ".".join(parts[:i]) or schema.__name__
            section = _section_with(model, part)  # the exact name one level down beats a likeness
            instead = ".".join([*parts[:i], section, *parts[i:]]) if section else None
            raise OverrideError(key, unknown_field_msg(part, where, fields, instead))
        annotation = fields[part].annotation
        if last and isinstance(value, dict) and _models(annotation):
            # a section given as an object: its keys one by one, the variant's tag first
            tag = _union_tag(annotation)
            if not isinstance(node.get(part), dict):
                node[part] = {}
            for sub, sub_value in sorted(value.items(), key=lambda kv: kv[0] != tag):
                _set(node, model, f"{key}.{sub}", [part, sub], sub_value, pending)
            return
        if last:
            if part in _TAGS and _is_variant(model) and node.get(part) != value:
                node.clear()  # another algorithm or network: its own defaults, not these
            node[part] = value
            return
        if not _models(annotation):
            raise OverrideError(key, f"{part!r} has no sub-fields")
        if not isinstance(node.get(part), dict):
            node[part] = {}
        node = node[part]
        model = _model_of(annotation, node)


def _apply_mlp_shape(pending: list) -> None:
    """``hidden_layers``/``hidden_size`` of an MLP as ``hidden_sizes`` (layers x size)."""
    by_node: dict[int, tuple[dict, dict[str, Any]]] = {}
    for node, part, value in pending:
        by_node.setdefault(id(node), (node, {}))[1][part] = value
    for node, shape in by_node.values():
        sizes = list(node.get("hidden_sizes") or [128, 128])
        layers = int(shape.get("hidden_layers", len(sizes)))
        size = int(shape.get("hidden_size", sizes[0]))
        node["hidden_sizes"] = [size] * layers


def override_data(model: BaseModel | type[BaseModel], overrides: Mapping[str, Any] | Iterable[str],
                  data: dict | None = None) -> dict:  # fmt: skip
    """The JSON data of ``model`` (an instance, or a class for its defaults) with overrides set."""
    schema = model if isinstance(model, type) else type(model)
    if data is None:
        data = {} if isinstance(model, type) else model.model_dump(mode="json")
    pending: list = []
    for key, value in as_dict(overrides).items():
        parts = key.strip().split(".")
        if not all(parts):
            raise OverrideError(key, "empty part in the dotted key; e.g. env.grid_size")
        _set(data, schema, key, parts, value, pending)
    if pending:
        _apply_mlp_shape(pending)
    return data


def apply_overrides(model: M, overrides: Mapping[str, Any] | Iterable[str] | None) -> M:
    """A copy of ``model`` with dotted-key overrides set and the whole re-validated.

    Unknown keys raise ``OverrideError`` (a ValueError) naming the key and the known fields; bad
    values raise pydantic's ``ValidationError`` naming the field and the allowed range.
    """
    return type(model).model_validate(override_data(model, overrides or {}))
