"""The base of every config model: strict, immutable, JSON-serialisable."""

from __future__ import annotations

from typing import Literal

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
