"""The base of every config model: strict, immutable, JSON-serialisable."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict

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


def json_safe(value: Any) -> Any:
    """JSON without NaN/Infinity (browsers' JSON.parse rejects them): non-finite floats -> null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value
