"""`quicknav sweep`: an Optuna study; trials that differ only in traced numbers train side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from quicknav_cli.common import (
    PrintConfigOpt,
    SetOpt,
    console,
    enable_compilation_cache,
    fail,
    print_config,
    read_json,
    resolved,
    sets,
    warn,
)


def sweep_request(
    space: str | None, config: Path | None, trials: int | None, parallel: int | None,
    total_steps: int | None, objective: str | None, storage: str | None, seed: int | None,
    overrides: list[str] | None, base: str | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The sweep request the flags describe (what the SDK would send to the service)."""
    from quicknav_core.config import BUILTIN_SPACES

    if (space is None) == (config is None):
        fail("give either --space NAME (a built-in search space) or --config SWEEP.json")
    changes: dict[str, Any] = {}
    for key, value in (("objective", objective), ("storage", storage), ("sampler_seed", seed)):
        if value is not None:
            changes[key] = value
    changes.update(sets(overrides))
    request: dict[str, Any] = {"overrides": changes}
    for key, value in (("trials", trials), ("parallel", parallel), ("total_steps", total_steps)):
        if value is not None:
            request[key] = value
    if config is not None:
        if base is not None:
            fail("--base goes with --space: a --config SweepConfig carries its own base")
        request["config"] = read_json(config)
    else:
        if base is not None:
            request["base"] = base
        if space not in BUILTIN_SPACES:
            fail(f"--space {space!r}: allowed values are {', '.join(BUILTIN_SPACES)}{_preset_hint(space)}")
        request["space"] = space
    return request


def _preset_hint(name: str | None) -> str:
    """For a training preset given as a space (the deprecated --preset was the space): the space
    that starts from it, or one that tunes it with --base (``resolve.preset_as_space``)."""
    from quicknav_core.config.resolve import preset_as_space

    found = preset_as_space(name) if name else None
    if found is None:
        return ""
    space, base = found
    if base is None:
        return f" ({name!r} is a training preset: --space {space} starts from it)"
    return f" ({name!r} is a training preset: --space {space} --base {base} tunes it)"


def sweep(
    space: Annotated[
        str | None,
        typer.Option(help="Built-in search space: ppo sac td3 mlp lstm gtrxl (the paper's)."),
    ] = None,
    base: Annotated[
        str | None,
        typer.Option(help="With --space: the training preset its trials start from, such as"
                     " building (default: the space's paper preset; quicknav presets lists them)."),
    ] = None,
    preset: Annotated[
        str | None, typer.Option(hidden=True, help="Deprecated name of --space.")
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="SweepConfig JSON file.")] = None,
    trials: Annotated[
        int | None, typer.Option(min=1, help="Finished trials wanted in the study (default 20).")
    ] = None,
    parallel: Annotated[
        int | None,
        typer.Option(
            min=1, max=1024, help="Trials asked at once; same-shape trials train batched."
        ),
    ] = None,
    objective: Annotated[
        str | None, typer.Option(help="success_rate, spl, steps_to_goal, return, collisions or"
                                    " collision_free_success (reached without touching anything).")
    ] = None,
    storage: Annotated[
        str | None,
        typer.Option(
            help="Optuna storage: default SQLite in --out; redis://host:port/db for a shared journal."
        ),
    ] = None,
    total_steps: Annotated[
        int | None, typer.Option(help="Env steps per trial (built-in spaces default to 2,000,000).")
    ] = None,
    seed: Annotated[int | None, typer.Option(min=0, help="Sampler seed (default 0).")] = None,
    set_: SetOpt = None,
    out: Annotated[Path, typer.Option(help="Sweep folder (resumable: rerun to continue).")] = Path(
        "sweeps/quicknav"
    ),
    print_only: PrintConfigOpt = False,
) -> None:
    """Hyperparameter sweep with Optuna; same-shape trials train side by side in one program.

    --set takes SweepConfig fields (trials, eval_episodes, ...) and fields of the base training
    config (env.grid_size, algorithm.num_epochs, ...) alike.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from quicknav_core.config import resolve_sweep

    if preset is not None:
        if space is not None:
            fail("give --space only (--preset is its deprecated name)")
        warn(f"--preset is deprecated for sweeps: write --space {preset}")
        space = preset
    request = sweep_request(space, config, trials, parallel, total_steps, objective, storage, seed,
                            set_, base)  # fmt: skip
    cfg = resolved(resolve_sweep, request)
    if print_only:
        print_config(cfg)
        return
    from quicknav_core.sweep import run_sweep

    enable_compilation_cache()
    console.print(f"sweep {cfg.study_name}: {cfg.trials} trials, {cfg.parallel} at a time, "
                  f"objective {cfg.objective} ({cfg.resolved_direction}) -> {out}")  # fmt: skip
    cols = (TextColumn("trials"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
            TimeElapsedColumn(), TextColumn("{task.fields[info]}"))  # fmt: skip
    with Progress(*cols, console=console) as progress:
        task = progress.add_task("sweep", total=cfg.trials, info="")

        def on_progress(p):
            best = "n/a" if p["best_value"] is None else f"{p['best_value']:.4g}"
            progress.update(task, completed=p["finished"], info=f"best {cfg.objective} {best}")

        summary = run_sweep(cfg, out, progress=on_progress)
    console.print(f"best {cfg.objective}: {summary['best_value']} with {summary['best_params']}")
    batched = sum(t["seconds"] for t in summary["timings"])
    console.print(f"{len(summary['timings'])} training groups in {batched:.0f} s; wrote {out}/"
                  " (best_params.json, best_config.json, trials.csv, *.png, study.db)")  # fmt: skip
