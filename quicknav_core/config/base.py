"""The base of every config model: strict, immutable, JSON-serialisable."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict

Split = Literal["train", "test"]

# ``json_schema_extra`` of a field whose value ends up as a traced number (vmappable, no recompile):
# fields marked this way may differ between trials that train side by side in one compiled program
# (``quicknav_core.train.batched``); every other field fixes a shape or a code path.
TRACED = {"traced": True}


class StrictModel(BaseModel):
    """Unknown fields are errors, NaN and infinities are refused, models are immutable and JSON-serialisable."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False
    )


def traced_fields(model: type[BaseModel]) -> frozenset[str]:
    """Names of the fields of ``model`` marked as traced numbers."""
    return frozenset(
        name
        for name, field in model.model_fields.items()
        if isinstance(field.json_schema_extra, dict) and field.json_schema_extra.get("traced")
    )


def json_safe(value: Any) -> Any:
    """JSON without NaN/Infinity (browsers' JSON.parse rejects them): non-finite floats -> null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
