"""`quicknav bench`: figures, never timed tests. Env throughput (JAX vs the NumPy twin), room-bank
build time, training throughput at the paper's sizes, and the paper's Tables 1 and 2 as a learning
benchmark."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from quicknav_cli.common import (
    SetOpt,
    checked_grids,
    console,
    enable_compilation_cache,
    expose_cpu_devices,
    fail,
    sets,
    warn,
)
from quicknav_core.config import ConfigError

app = typer.Typer(
    help="Benchmarks. Without a subcommand: environment throughput, JAX vs the NumPy twin.",
    invoke_without_command=True,
)


def show_with_targets(table, width: int, targets: list[dict], unit: str = "") -> None:
    """A bench's table (at least ``width`` columns wide), then each target: measured, met or not."""
    Console(width=max(console.width, width), markup=False, emoji=False).print(table)
    for t in targets:
        mark = "[green]met[/]" if t["met"] else "[red]NOT met[/]"
        console.print(f"target: {t['target']}: measured {t['measured']:,}{unit} -> {mark}",
                      markup=True)


def given_here(ctx: typer.Context) -> None:
    """Exit when an option of the env benchmark (``quicknav bench``'s own) was given before a
    subcommand: it would be ignored (``quicknav bench --grid 300 rooms`` ran rooms' default grids)."""
    sub = ctx.invoked_subcommand
    command = ctx.command.get_command(ctx, sub)
    theirs = {opt for p in (command.params if command else []) for opt in p.opts}
    for param in ctx.command.params:  # (by name: typer may carry its own copy of click's enum)
        if getattr(ctx.get_parameter_source(param.name), "name", None) == "COMMANDLINE":
            flag = max(param.opts, key=len)
            where = (f"put it after the command: quicknav bench {sub} {flag} ..." if flag in theirs
                     else f"`{sub}` has no {flag} (`quicknav bench {sub} --help` lists its"
                     f" options); the env benchmark takes it alone: quicknav bench {flag} ...")  # fmt: skip
            fail(f"{flag} is an option of `quicknav bench` (the env benchmark), given before"
                 f" `{sub}`, which would ignore it; {where}")


@app.callback()
def bench_env(
    ctx: typer.Context,
    grid: Annotated[
        list[int] | None, typer.Option("--grid", help="Grid sizes (default 4 8 16).")
    ] = None,
    batch: Annotated[
        list[int] | None,
        typer.Option("--batch", help="vmap batch sizes (default 64 1024 4096 16384)."),
    ] = None,
    beams: Annotated[int, typer.Option(min=1, max=1024, help="Lidar beams.")] = 16,
    steps: Annotated[
        int, typer.Option(min=100, max=100_000_000, help="Steps per timed run.")
    ] = 100_000,
    repeats: Annotated[int, typer.Option(min=3, max=100, help="Timed repeats (median).")] = 3,
    budget: Annotated[
        float, typer.Option("--budget-s", min=10, help="Time budget of the Python-driven loops, s.")
    ] = 240.0,
    final_obs: Annotated[
        bool, typer.Option(help="Also compute info['final_obs'] (a second lidar cast).")
    ] = False,
    cpu_devices: Annotated[
        int,
        typer.Option(
            min=0,
            max=64,
            help="CPU cores exposed to JAX as devices, batches sharded over them (0: all cores, max 8).",
        ),
    ] = 0,
    lidar_method: Annotated[
        str,
        typer.Option(help="Lidar caster: auto, crossings or dda (see EnvConfig.lidar_method)."),
    ] = "auto",
    out: Annotated[Path, typer.Option(help="Folder for bench.json and the PNGs.")] = Path("bench"),
) -> None:
    """Environment throughput: NumPy twin vs JAX (1 env, scan, vmapped batches) per grid size."""
    if ctx.invoked_subcommand is not None:
        given_here(ctx)
        return
    expose_cpu_devices(cpu_devices or min(os.cpu_count() or 1, 8))
    from rich.table import Table

    from quicknav_core.bench.env import (
        DEFAULT_BATCHES,
        DEFAULT_GRIDS,
        GPU_EXTRA_BATCHES,
        BenchConfig,
        format_table,
        run_bench,
        write_outputs,
    )

    grids = checked_grids(grid, DEFAULT_GRIDS)
    if batch and min(batch) < 1:
        fail(f"--batch {min(batch)}: allowed range >= 1")
    from quicknav_core.env.lidar import LIDAR_METHODS

    if lidar_method not in ("auto", *LIDAR_METHODS):
        fail(f"--lidar-method {lidar_method}: allowed " + ", ".join(("auto", *LIDAR_METHODS)))
    import jax

    batches = batch or list(DEFAULT_BATCHES)
    if batch is None and jax.default_backend() == "gpu":
        batches += list(GPU_EXTRA_BATCHES)
    cfg = BenchConfig(
        grids=grids, batches=batches, beams=beams, steps=steps, repeats=repeats, budget_s=budget,
        final_obs=final_obs, lidar_method=lidar_method,
    )  # fmt: skip
    with console.status("benchmarking...") as status:
        report = run_bench(cfg, progress=lambda msg: status.update(msg))
    table = Table(
        title=f"QuickNav env throughput ({report.machine['cpu']}, {report.machine['jax_backend']})"
    )
    for col in (
        "grid",
        "impl",
        "envs",
        "steps/s",
        f"s per {steps:,}",
        "compile s",
        "mem MiB",
        "dev",
        "note",
    ):
        table.add_column(col, justify="right" if col not in ("impl", "note") else "left")
    for row in format_table(report):
        table.add_row(*row)
    show_with_targets(table, 120, report.targets)
    paths = write_outputs(report, out, warn=warn)
    console.print("wrote " + ", ".join(str(p) for p in paths.values()))


@app.command("rooms")
def bench_rooms(
    grid: Annotated[
        list[int] | None, typer.Option("--grid", help="Grid sizes (default 8 16 32 64 128).")
    ] = None,
    carver: Annotated[
        str, typer.Option(help="Carver: auto, paper, centre or carved (see EnvConfig.carver).")
    ] = "auto",
    out: Annotated[Path, typer.Option(help="Folder for bench_rooms.json.")] = Path("bench"),
) -> None:
    """Seconds to build the train and test room banks per grid size (first call, compile included)."""
    from rich.table import Table

    from quicknav_core.bench.rooms import (
        DEFAULT_GRIDS,
        RoomsBenchConfig,
        format_table,
        run_rooms_bench,
        write_report,
    )
    from quicknav_core.env.carving import CARVERS

    grids = checked_grids(grid, DEFAULT_GRIDS)
    if carver not in ("auto", *CARVERS):
        fail(f"--carver {carver}: allowed " + ", ".join(("auto", *CARVERS)))
    cfg = RoomsBenchConfig(grids=grids, carver=carver)
    with console.status("carving room banks...") as status:
        try:
            report = run_rooms_bench(cfg, progress=lambda msg: status.update(msg))
        except (ConfigError, ValueError) as e:
            fail(str(e))
    table = Table(
        title=f"Room bank build ({report.machine['cpu']}, {report.machine['cores']} cores,"
        f" {report.machine['jax_backend']})"
    )
    for col in ("grid", "carver", "rooms", "free cells", "train s", "test s", "total s"):
        table.add_column(col, justify="left" if col in ("grid", "carver") else "right")
    for row in format_table(report):
        table.add_row(*row)
    show_with_targets(table, 100, report.targets, unit=" s")
    console.print(f"wrote {write_report(report, out)}")


@app.command("train")
def bench_train(
    row: Annotated[
        list[str] | None,
        typer.Option(
            "--row",
            help="Rows to run (ppo-mlp sac-mlp td3-mlp rppo-mlp-memory rppo-lstm rppo-gtrxl).",
        ),
    ] = None,
    chunks: Annotated[int, typer.Option(min=1, max=100, help="Timed chunks per row (median).")] = 3,
    set_: SetOpt = None,
    out: Annotated[Path, typer.Option(help="Folder for bench_train.json.")] = Path("bench"),
) -> None:
    """End-to-end training throughput at the paper's network sizes (env steps/s, compile excluded)."""
    from rich.table import Table

    from quicknav_core.bench.train import ROWS, run_train_bench, write_report

    known = [r[0] for r in ROWS]
    bad = [r for r in row or [] if r not in known]
    if bad:
        fail(f"--row {bad[0]!r}: allowed values are {', '.join(known)}")
    enable_compilation_cache()
    with console.status("benchmarking training...") as status:
        try:
            report = run_train_bench(row, chunks, sets(set_), progress=lambda m: status.update(m))
        except ConfigError as e:
            fail(str(e))
    table = Table(
        title=f"Training throughput ({report['machine']['cpu']}, {report['machine']['jax_backend']})"
    )
    for col in ("row", "trainer", "network", "envs", "env steps/s", "first chunk s", "target"):
        table.add_column(col)
    for r in report["rows"]:
        target = (
            ""
            if r["target"] is None
            else (
                f"{r['target']:,.0f} "
                + ("met" if r["env_steps_per_s"] >= r["target"] else "NOT met")
            )
        )
        table.add_row(r["name"], r["trainer"], r["network"], str(r["num_envs"]),
                      f"{r['env_steps_per_s']:,.0f}", f"{r['compile_and_first_chunk_s']:.1f}", target)  # fmt: skip
    Console(width=max(console.width, 110), markup=False, emoji=False).print(table)
    console.print(f"wrote {write_report(report, out)}")


@app.command("learning")
def bench_learning(
    row: Annotated[
        list[str] | None,
        typer.Option(
            "--row",
            help="Rows to train now (default all): a paper preset (paper-ppo paper-sac paper-td3"
            " paper-mlp paper-lstm paper-gtrxl) for the paper's reward, the preset plus '-shaped'"
            " (paper-td3-shaped, ...) for potential-based shaping, or a tuned or variant row"
            " (tuned-gtrxl, ...; an unknown key lists them all).",
        ),
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, max=10, help="Training seeds per row.")] = 3,
    scale: Annotated[
        float,
        typer.Option(min=0.0001, max=10.0, help="Scale of step and time budgets (smoke runs)."),
    ] = 1.0,
    out: Annotated[Path, typer.Option(help="Folder for report.md and report.json.")] = Path(
        "benchmarks/results/learning"
    ),
    runs: Annotated[
        Path, typer.Option(help="Folder for the training runs (large; not for git).")
    ] = Path("runs/learning"),
    rerun_scoreless: Annotated[
        bool,
        typer.Option(
            help="Also retrain the chosen rows' seeds recorded before the report kept"
            " per-episode scores (they have no IQM or bootstrap interval); each stays in the"
            " report until its new run is evaluated.",
        ),
    ] = False,
    rerun_before: Annotated[
        str | None,
        typer.Option(
            metavar="VERSION",
            help="Also retrain the chosen rows' seeds trained by a QuickNav older than VERSION"
            " (e.g. 0.2.0: SAC trained 64x64 before it); each stays in the report until its new"
            " run is evaluated.",
        ),
    ] = None,
) -> None:
    """The paper's Tables 1 and 2: train with several seeds, evaluate on held-out rooms, report."""
    from quicknav_core.bench.learning import ROW_KEYS, run_learning_bench

    known = list(ROW_KEYS)
    bad = [r for r in row or [] if r not in known]
    if bad:
        fail(f"--row {bad[0]!r}: allowed values are {', '.join(known)}")
    enable_compilation_cache()
    markdown, _ = run_learning_bench(
        out, runs, row, seeds, scale, say=lambda m: console.print(m, highlight=False),
        rerun_scoreless=rerun_scoreless, rerun_before=rerun_before,
    )  # fmt: skip
    console.print(markdown, highlight=False, markup=False, soft_wrap=True)
    console.print(f"wrote {out}/report.md, report.json and profiles.png")


@app.command("time-to-target")
def bench_time_to_target(
    row: Annotated[
        list[str] | None,
        typer.Option("--row", help="Rows to run (default all): ppo ppo-fast sac td3 mlp-memory lstm gtrxl."),
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, max=10, help="Warm runs (seeds) per row.")] = 3,
    scale: Annotated[
        float, typer.Option(min=0.001, max=10.0, help="Scale of the time caps (smoke runs).")
    ] = 1.0,
    out: Annotated[Path, typer.Option(help="Folder for time_to_target.json.")] = Path(
        "benchmarks/results"
    ),
    report_only: Annotated[
        bool, typer.Option("--report", help="Only print the table of what is recorded (and the peers').")
    ] = False,
    write_to: Annotated[
        list[Path] | None,
        typer.Option("--write-to", help="Also put the table between the time-to-target markers of"
                     " these Markdown pages (README.md, docs/performance.md)."),
    ] = None,
) -> None:
    """Wall-clock time until held-out success reaches 90 %, compile included, cold and warm cache."""
    from quicknav_core.bench import time_to_target as ttt

    bad = [r for r in row or [] if r not in ttt.ROW_KEYS]
    if bad:
        fail(f"--row {bad[0]!r}: allowed values are {', '.join(ttt.ROW_KEYS)}")
    if not report_only:
        ttt.run_bench(row, seeds, out, scale, say=lambda m: console.print(m, highlight=False))
    table = ttt.report(out / "time_to_target.json", out / "time_to_target_peers.json")
    console.print(table, highlight=False, markup=False, soft_wrap=True)
    for page in write_to or []:
        try:
            ttt.write_between_markers(page, table)
        except (OSError, ValueError) as e:
            fail(f"--write-to: {e}")
        console.print(f"wrote the table into {page}")
