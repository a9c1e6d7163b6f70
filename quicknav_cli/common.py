"""What every command group shares: the console, errors that exit, options, and process setup."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.console import Console

# markup and emoji off: a path, a map's name or an id such as "map:abcd:" is printed as written,
# never read as rich's [tags] or :emoji: (a map named "a[/]b" crashed `maps list`); the few
# styled lines ask for markup themselves
console = Console(markup=False, emoji=False)
# errors and warnings go to stderr, so a script reading stdout gets only the results
err_console = Console(stderr=True, markup=False, emoji=False)

SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override a config field (dotted key, JSON value): --set env.grid_size=8"
        " --set env.reward.goal_reward=20 --set algorithm.learning_rate=1e-3",
    ),
]
EnvSetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set", help="Override an env field: --set grid_size=8 --set reward.goal_reward=20"
        " (env.grid_size=8 works too)"
    ),
]
PrintConfigOpt = Annotated[
    bool,
    typer.Option(
        "--print-config",
        help="Print the resolved config as JSON (what a job would store) and exit without running.",
    ),
]


def fail(message: str, code: int = 2) -> NoReturn:
    """Print an error a person can act on and exit (the message is never read as rich markup)."""
    err_console.print("[bold red]error:[/] ", end="", highlight=False, markup=True)
    err_console.print(message, highlight=False, soft_wrap=True, markup=False)
    raise typer.Exit(code)


def warn(message: str) -> None:
    """A warning on stderr (deprecated options, ...); the command goes on."""
    err_console.print("[yellow]warning:[/] ", end="", highlight=False, markup=True)
    err_console.print(message, highlight=False, soft_wrap=True, markup=False)


def sets(items: list[str] | None) -> dict[str, Any]:
    """``--set key=value`` items as a dict of dotted keys with JSON values; exits if malformed."""
    from quicknav_core.config import parse_assignments
    from quicknav_core.config.overrides import OverrideError

    try:
        return parse_assignments(items or [])
    except OverrideError as e:
        fail(f"--set {e}")


def env_sets(items: list[str] | None) -> dict[str, Any]:
    """An eval's ``--set`` items, env fields: ``grid_size=8`` and ``env.grid_size=8`` (the spelling
    of train jobs and of what ``quicknav maps upload`` prints) mean the same field."""
    return {key.removeprefix("env."): value for key, value in sets(items).items()}


def read_json(path: Path, what: str = "--config") -> dict[str, Any]:
    """A JSON object from a file; exits with a clear message if missing or malformed."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        fail(f"{what} {path}: no such file")
    except json.JSONDecodeError as e:
        fail(f"{what} {path}: not valid JSON ({e})")
    if not isinstance(data, dict):
        fail(f"{what} {path}: expected a JSON object")
    return data


def resolved(resolve, request: dict[str, Any], flags: dict[str, str] | None = None, **kw):
    """``resolve(request)``, or exit with one line per bad field (config paths, as --set names them;
    ``flags``: a request field by the option that set it, ``{"map": "--map"}``)."""
    from quicknav_core.config import ConfigError

    try:
        return resolve(request, **kw)
    except ConfigError as e:
        lines = []
        for item in e.items:
            loc = item["loc"]
            where = (
                f"--set {loc[1]}" if loc[:1] == ["overrides"] and len(loc) > 1
                else (flags or {}).get(".".join(loc)) or item.get("field") or ".".join(loc) or e.title
            )  # fmt: skip
            got = f" (got {item['input']!r})" if "input" in item else ""
            lines.append(f"{where}: {item['msg']}{got}")
        fail("invalid configuration:\n  " + "\n  ".join(lines))


def admitted(config, runtime) -> None:
    """Run the admission every door runs (``quicknav_core.admission.admit``) with this machine's
    limits (its devices; no server caps): exit naming every problem, before anything compiles."""
    import jax

    from quicknav_core.admission import Limits, admit

    problems = admit(config, Limits(max_devices=jax.local_device_count()), runtime)
    if problems:
        fail("\n  ".join(["this run cannot start here:"] + [
            f"{'.'.join(map(str, p['loc']))}: {p['msg']}" for p in problems]))  # fmt: skip


def print_config(config) -> None:
    """A resolved config as JSON on stdout (nothing else printed)."""
    print(config.model_dump_json(indent=2))


def expose_cpu_devices(count: int) -> None:
    """Let XLA's CPU backend present ``count`` devices, one per core, so work can be sharded.

    Only effective before JAX initialises its backends; GPU/TPU devices are not affected.
    """
    if "jax" in sys.modules and count > 1:
        import jax

        if jax.local_device_count() == count:
            return
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()


def enable_compilation_cache() -> None:
    """Turn on JAX's persistent compilation cache for this command: QUICKNAV_JAX_CACHE (empty:
    none), default ~/.cache/quicknav/jax (``quicknav_core.compile_cache``)."""
    from quicknav_core.compile_cache import enable_compilation_cache as enable

    enable(os.environ.get("QUICKNAV_JAX_CACHE", str(Path.home() / ".cache" / "quicknav" / "jax")))


def service_settings(**overrides):
    """Service settings from QUICKNAV_* variables plus CLI options; exits on a bad value."""
    from pydantic import ValidationError

    try:
        from quicknav_service.settings import Settings
    except ImportError as e:
        fail(
            f"the job service is not installed ({e.name} is missing): pip install 'quicknav[service]'"
        )
    try:
        settings = Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as e:
        # the message names the variable, never its value (a URL may hold a password)
        fail("invalid service settings (QUICKNAV_* variables / options):\n  " + "\n  ".join(
            f"QUICKNAV_{'_'.join(map(str, err['loc'])).upper()}: {err['msg']}" for err in e.errors()))  # fmt: skip
    from quicknav_service import redact

    redact.install(settings)  # before any log handler takes hold of stdout or stderr
    return settings


def checked_grids(grid: list[int] | None, default) -> list[int]:
    """The --grid values (or the default), each within EnvConfig.grid_size's range."""
    from quicknav_core.config.env import GRID_SIZE_RANGE

    lo, hi = GRID_SIZE_RANGE
    grids = grid or list(default)
    bad = [g for g in grids if not lo <= g <= hi]
    if bad:
        fail(f"--grid {bad[0]}: allowed range {lo}..{hi} (EnvConfig.grid_size)")
    return grids
