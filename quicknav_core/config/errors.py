"""Errors a person can act on: every message names the field and what is allowed."""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Any

from pydantic import ValidationError


def error_items(error: ValidationError) -> list[dict[str, Any]]:
    """A pydantic error as ``[{"loc": [...], "msg": ..., "type": ..., "input": ...}]``."""
    items = []
    for e in error.errors():
        item = {
            "loc": [str(p) for p in e["loc"]],
            "msg": e["msg"].removeprefix("Value error, "),
            "type": e["type"],
        }
        if "input" in e and not isinstance(e["input"], dict):
            item["input"] = e["input"]
        items.append(item)
    return items


def did_you_mean(name: str, known: Iterable[str]) -> str | None:
    """The known name closest to ``name`` (a likely typo), or None."""
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return close[0] if close else None


def unknown_msg(what: str, name: str, known: Iterable[str], where: str = "",
                instead: str | None = None) -> str:  # fmt: skip
    """``unknown preset 'buildin'; did you mean 'building'? known: ...`` (the guess only for a
    likely typo, or ``instead``: the name meant, when it is known otherwise)."""
    known = list(known)
    close = instead or did_you_mean(name, known)
    guess = f"; did you mean {close!r}?" if close else ""
    place = f" in {where}" if where else ""
    return f"unknown {what} {name!r}{place}{guess}{' known' if close else '; known'}: {', '.join(known)}"


def unknown_field_msg(name: str, where: str, known: Iterable[str], instead: str | None = None) -> str:
    """``unknown field 'gird_size' in env; did you mean 'grid_size'? known: ...``; ``instead``: the
    path meant, where the name is a field one level down (``env.lidar_fov_deg`` for
    ``lidar_fov_deg`` set on a TrainConfig)."""
    return unknown_msg("field", name, known, where, instead)


def format_items(items: list[dict[str, Any]], title: str = "", prefix: str = "") -> str:
    """One line per bad field: ``field.path: message (got value)``; ``prefix`` goes before paths."""
    lines = []
    for item in items:
        loc = ".".join(item["loc"])
        loc = f"{prefix}.{loc}" if prefix and loc else (loc or prefix or title)
        got = f" (got {_short(item['input'])})" if "input" in item else ""
        lines.append(f"{loc}: {item['msg']}{got}")
    return "invalid configuration:\n  " + "\n  ".join(lines)


def format_validation_error(error: ValidationError, prefix: str = "") -> str:
    """One line per bad field of a pydantic error (``prefix`` goes before the paths)."""
    return format_items(error_items(error), title=error.title, prefix=prefix)


def _short(value: Any, limit: int = 200) -> str:
    """A value as repr, cut to ``limit`` characters: bad input is echoed, never at length."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 20]}... ({len(text):,} characters)"


class ConfigError(ValueError):
    """A request that cannot become a config.

    ``items`` hold ``{"loc", "msg", "type"}`` with ``loc`` relative to the request (e.g.
    ``["overrides", "env.grid_size"]`` or ``["config", "num_envs"]``): the API answers them as a
    422's ``detail``; the CLI prints ``str(error)``, one line per field.
    """

    def __init__(self, items: list[dict[str, Any]], title: str = "request"):
        self.items = items
        self.title = title
        super().__init__(format_items(items, title=title))

    @classmethod
    def single(cls, loc: list[str], msg: str, kind: str = "value_error") -> ConfigError:
        return cls([{"loc": list(loc), "msg": msg, "type": kind}])
