"""The `quicknav` command: the front door of every feature."""

from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from pydantic import ValidationError
from rich.console import Console

from quicknav_core.config import EnvConfig, TrainConfig, apply_overrides, format_validation_error

app = typer.Typer(
    name="quicknav",
    help="QuickNav: room navigation for reinforcement learning in pure JAX.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
env_app = typer.Typer(
    help="Look at the environment: demo episodes and generated rooms.", no_args_is_help=True
)
app.add_typer(env_app, name="env")
bench_app = typer.Typer(
    help="Benchmarks. Without a subcommand: environment throughput, JAX vs the NumPy twin.",
    invoke_without_command=True,
)
app.add_typer(bench_app, name="bench")

console = Console()

ConfigOpt = Annotated[
    Path | None,
    typer.Option("--config", help="EnvConfig JSON file (fields not given keep defaults)."),
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set", help="Override a config field: --set grid_size=8 --set reward.goal_reward=20"
    ),
]
TrainSetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override a training config field: --set env.grid_size=8 "
        "--set env.reward.goal_reward=20 --set algorithm.learning_rate=1e-3",
    ),
]


def fail(message: str, code: int = 2) -> None:
    """Print an error a person can act on and exit."""
    console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def load_env_config(config: Path | None, overrides: list[str] | None) -> EnvConfig:
    """EnvConfig from an optional JSON file plus --set overrides; exits with a clear message if bad."""
    try:
        data = json.loads(config.read_text()) if config else {}
        return apply_overrides(EnvConfig.model_validate(data), overrides or [])
    except FileNotFoundError:
        fail(f"--config {config}: no such file")
    except json.JSONDecodeError as e:
        fail(f"--config {config}: not valid JSON ({e})")
    except ValidationError as e:
        fail(format_validation_error(e))
    except ValueError as e:
        fail(str(e))
    raise AssertionError("unreachable")


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
    """Turn on JAX's persistent compilation cache (CLI processes only; library code never does)."""
    import jax

    cache = os.environ.get("QUICKNAV_JAX_CACHE", str(Path.home() / ".cache" / "quicknav" / "jax"))
    if cache:
        jax.config.update("jax_compilation_cache_dir", cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


@env_app.command("demo")
def env_demo(
    out: Annotated[Path, typer.Option(help="Folder for demo.png and demo.gif.")] = Path("demo"),
    policy: Annotated[
        str, typer.Option(help="'scripted' (BFS path follower) or 'random'.")
    ] = "scripted",
    seed: Annotated[int, typer.Option(help="Seed of the episode.")] = 0,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Run one episode and write a PNG of its trajectory and a GIF with lidar rays."""
    from quicknav_core.demo import run_demo

    cfg = load_env_config(config, set_)
    if policy not in ("scripted", "random"):
        fail(f"--policy {policy!r}: allowed values are 'scripted' and 'random'")
    enable_compilation_cache()
    with console.status("running one episode and drawing it..."):
        result = run_demo(cfg, out, policy=policy, seed=seed)
    outcome = "reached the goal" if result.goal_reached else "timed out"
    console.print(
        f"{policy} policy {outcome} after {result.steps} steps, return {result.episode_return:.1f},"
        f" {result.collisions} wall collisions"
    )
    console.print(f"wrote {result.png}\nwrote {result.gif}")


@env_app.command("rooms")
def env_rooms(
    out: Annotated[Path, typer.Option(help="PNG file to write.")] = Path("rooms.png"),
    grid: Annotated[
        list[int] | None, typer.Option("--grid", help="Grid sizes (default 4 8 16).")
    ] = None,
    per_row: Annotated[int, typer.Option(min=1, max=12, help="Rooms per grid size.")] = 5,
    seed: Annotated[int, typer.Option(min=0, help="Room seed.")] = 0,
) -> None:
    """Draw generated rooms for several grid sizes (the paper's room-generation figure)."""
    from quicknav_core.demo import draw_rooms

    grids = grid or [4, 8, 16]
    bad = [g for g in grids if not 4 <= g <= 128]
    if bad:
        fail(f"--grid {bad[0]}: allowed range 4..128")
    path = draw_rooms(out, tuple(grids), per_row=per_row, seed=seed)
    console.print(f"wrote {path}")


@bench_app.callback()
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
    out: Annotated[Path, typer.Option(help="Folder for bench.json and the PNGs.")] = Path("bench"),
) -> None:
    """Environment throughput: NumPy twin vs JAX (1 env, scan, vmapped batches) per grid size."""
    if ctx.invoked_subcommand is not None:
        return
    expose_cpu_devices(cpu_devices or min(os.cpu_count() or 1, 8))
    from rich.table import Table

    from quicknav_core.bench import (
        DEFAULT_BATCHES,
        DEFAULT_GRIDS,
        GPU_EXTRA_BATCHES,
        BenchConfig,
        format_table,
        run_bench,
        write_outputs,
    )

    grids = grid or list(DEFAULT_GRIDS)
    bad = [g for g in grids if not 4 <= g <= 128]
    if bad:
        fail(f"--grid {bad[0]}: allowed range 4..128")
    if batch and min(batch) < 1:
        fail(f"--batch {min(batch)}: allowed range >= 1")
    import jax

    batches = batch or list(DEFAULT_BATCHES)
    if batch is None and jax.default_backend() == "gpu":
        batches += list(GPU_EXTRA_BATCHES)
    cfg = BenchConfig(
        grids=grids, batches=batches, beams=beams, steps=steps, repeats=repeats, budget_s=budget,
        final_obs=final_obs,
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
    Console(width=max(console.width, 120)).print(table)
    for t in report.targets:
        mark = "[green]met[/]" if t["met"] else "[red]NOT met[/]"
        console.print(f"target: {t['target']}: measured {t['measured']:,} -> {mark}")
    paths = write_outputs(report, out)
    console.print("wrote " + ", ".join(str(p) for p in paths.values()))


@bench_app.command("train")
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

    from quicknav_core.bench_train import ROWS, run_train_bench, write_report

    known = [r[0] for r in ROWS]
    bad = [r for r in row or [] if r not in known]
    if bad:
        fail(f"--row {bad[0]!r}: allowed values are {', '.join(known)}")
    enable_compilation_cache()
    with console.status("benchmarking training...") as status:
        try:
            report = run_train_bench(row, chunks, set_ or [], progress=lambda m: status.update(m))
        except ValidationError as e:
            fail(format_validation_error(e))
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
    Console(width=max(console.width, 110)).print(table)
    console.print(f"wrote {write_report(report, out)}")


@bench_app.command("learning")
def bench_learning(
    row: Annotated[
        list[str] | None,
        typer.Option(
            "--row",
            help="Presets to train now (default all): paper-ppo paper-sac paper-td3 paper-mlp paper-lstm paper-gtrxl.",
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
) -> None:
    """The paper's Tables 1 and 2: train with several seeds, evaluate on held-out rooms, report."""
    from quicknav_core.bench_learning import ROWS, run_learning_bench

    known = [r.preset for r in ROWS]
    bad = [r for r in row or [] if r not in known]
    if bad:
        fail(f"--row {bad[0]!r}: allowed values are {', '.join(known)}")
    enable_compilation_cache()
    markdown, _ = run_learning_bench(
        out, runs, row, seeds, scale, say=lambda m: console.print(m, highlight=False)
    )
    console.print(markdown, highlight=False, markup=False, soft_wrap=True)
    console.print(f"wrote {out}/report.md and report.json")


NETWORK_DEFAULTS = {
    "mlp": {"kind": "mlp"},
    "mlp-memory": {"kind": "mlp", "memory_size": 32},
    "lstm": {"kind": "lstm"},
    "gtrxl": {"kind": "gtrxl"},
}


def build_train_config(
    preset: str | None,
    config: Path | None,
    algo: str | None,
    network: str | None,
    total_steps: int | None,
    num_envs: int | None,
    seed: int | None,
    overrides: list[str] | None,
):
    """TrainConfig from a preset or JSON file plus options; exits with a clear message if bad."""
    from quicknav_core.config import TrainConfig
    from quicknav_core.train.presets import get_preset

    try:
        if config is not None:
            cfg = TrainConfig.model_validate_json(config.read_text())
        else:
            cfg = get_preset(preset or "demo")
        data = cfg.model_dump(mode="json")
        if algo is not None:
            if algo not in ("ppo", "sac", "td3"):
                fail(f"--algo {algo!r}: allowed values are ppo, sac, td3")
            data["algorithm"] = {"name": algo}
        if network is not None:
            if network not in NETWORK_DEFAULTS:
                fail(f"--network {network!r}: allowed values are {', '.join(NETWORK_DEFAULTS)}")
            data["network"] = dict(NETWORK_DEFAULTS[network])
        for key, value in (("total_steps", total_steps), ("num_envs", num_envs), ("seed", seed)):
            if value is not None:
                data[key] = value
        return apply_overrides(TrainConfig.model_validate(data), overrides or [])
    except FileNotFoundError:
        fail(f"--config {config}: no such file")
    except ValidationError as e:
        fail(format_validation_error(e))
    except ValueError as e:
        fail(str(e))
    raise AssertionError("unreachable")


@app.command("train")
def train(
    preset: Annotated[
        str | None, typer.Option(help="Preset name (quicknav presets lists them).")
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="TrainConfig JSON file.")] = None,
    algo: Annotated[
        str | None, typer.Option(help="ppo, sac or td3 (its default hyperparameters).")
    ] = None,
    network: Annotated[str | None, typer.Option(help="mlp, mlp-memory, lstm or gtrxl.")] = None,
    total_steps: Annotated[int | None, typer.Option(help="Env steps to train.")] = None,
    num_envs: Annotated[int | None, typer.Option(help="Parallel envs.")] = None,
    seed: Annotated[int | None, typer.Option(help="Training seed.")] = None,
    set_: TrainSetOpt = None,
    out: Annotated[
        Path | None, typer.Option(help="Run folder (default runs/<preset>-s<seed>).")
    ] = None,
    resume: Annotated[Path | None, typer.Option(help="Continue the run in this folder.")] = None,
    checkpoint_every: Annotated[int, typer.Option(min=1, help="Checkpoint every N chunks.")] = 1,
) -> None:
    """Train an agent; writes config.json, metrics.jsonl, a checkpoint and learning_curve.png."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from quicknav_core.train.run import train_run

    if resume is not None:
        if not (resume / "config.json").exists():
            fail(f"--resume {resume}: not a run folder (no config.json)")
        from quicknav_core.config import TrainConfig

        cfg = TrainConfig.model_validate_json((resume / "config.json").read_text())
        run_dir = resume
    else:
        cfg = build_train_config(preset, config, algo, network, total_steps, num_envs, seed, set_)
        run_dir = (
            out or Path("runs") / f"{preset or (config.stem if config else 'demo')}-s{cfg.seed}"
        )
    enable_compilation_cache()
    console.print(
        f"training {cfg.trainer_kind} ({cfg.network.kind}) for {cfg.total_steps:,} env steps,"
        f" {cfg.num_envs} envs, grid {cfg.env.grid_size} -> {run_dir}"
    )
    columns = (
        TextColumn("[progress.description]{task.description}"), BarColumn(),
        TextColumn("{task.completed:,.0f}/{task.total:,.0f} steps"), TimeElapsedColumn(),
        TimeRemainingColumn(), TextColumn("{task.fields[info]}"),
    )  # fmt: skip
    with Progress(*columns, console=console) as progress:
        task = progress.add_task("compiling", total=cfg.total_steps, info="")

        def on_chunk(r) -> bool:
            m = r.metrics
            info = (
                f"return {m.get('mean_return', float('nan')):.1f}  success"
                f" {m.get('success_rate', float('nan')):.0%}  len {m.get('mean_length', float('nan')):.0f}"
                f"  {r.steps_per_s:,.0f} steps/s"
            )
            progress.update(task, completed=r.env_steps, total=r.total_steps, info=info,
                            description="training")  # fmt: skip
            return False

        summary = train_run(cfg, run_dir, callback=on_chunk, resume=resume is not None,
                            checkpoint_every=checkpoint_every)  # fmt: skip
    final = summary["final"]
    console.print(
        f"done: {summary['env_steps']:,} env steps; last chunk: return {final.get('mean_return', 0):.1f},"
        f" success {final.get('success_rate', 0):.0%}"
    )
    console.print(
        f"run folder: {run_dir} (config.json, metrics.jsonl, checkpoint/, learning_curve.png)"
    )


@app.command("eval")
def eval_cmd(
    run: Annotated[
        Path | None,
        typer.Argument(help="Run folder (or its checkpoint folder) from quicknav train."),
    ] = None,
    policy: Annotated[
        str | None, typer.Option(help="Baseline instead of a run: random or oracle.")
    ] = None,
    episodes: Annotated[
        int, typer.Option(min=1, max=100_000, help="Episodes (fixed seeds).")
    ] = 100,
    seed: Annotated[int, typer.Option(min=0, help="Episode seed: same seed, same episodes.")] = 0,
    stochastic: Annotated[bool, typer.Option(help="Sample actions instead of the mean.")] = False,
    split: Annotated[str, typer.Option(help="Room bank: test (held out) or train.")] = "test",
    config: ConfigOpt = None,
    set_: SetOpt = None,
    out: Annotated[
        Path | None, typer.Option(help="Folder for eval.json and pictures (default RUN/eval).")
    ] = None,
) -> None:
    """Evaluate a trained run or a baseline on held-out rooms: success, SPL, steps, collisions."""
    from quicknav_core.evaluate import EvalConfig, agent_for, agent_from_run, evaluate

    if (run is None) == (policy is None):
        fail("give either a run folder or --policy random|oracle")
    if split not in ("test", "train"):
        fail(f"--split {split!r}: allowed values are test and train")
    enable_compilation_cache()
    if run is not None:
        try:
            agent, env_cfg, _ = agent_from_run(run)
        except FileNotFoundError as e:
            fail(str(e))
        if config or set_:
            env_cfg = apply_overrides(env_cfg, set_ or [])
        out_dir = out or (run / "eval")
    else:
        env_cfg = load_env_config(config, set_)
        try:
            agent = agent_for(policy, env_cfg)
        except ValueError as e:
            fail(str(e))
        out_dir = out or Path("eval") / policy
    cfg = EvalConfig(episodes=episodes, seed=seed, deterministic=not stochastic, split=split)
    with console.status(f"evaluating {agent.name} on {episodes} episodes..."):
        try:
            result, _ = evaluate(env_cfg, agent, cfg, out_dir)
        except ValueError as e:
            fail(str(e))
    print_eval(result)
    console.print(f"wrote {out_dir}/eval.json, trajectories.png, episodes.gif")


def print_eval(result) -> None:
    from rich.table import Table

    m = result["metrics"]
    t = Table(title=f"{result['agent']}: {m['episodes']} held-out episodes")
    t.add_column("metric")
    t.add_column("value", justify="right")
    lo, hi = m["success_ci95"]
    t.add_row("success rate (95% CI)", f"{m['success_rate']:.1%} ({lo:.1%} - {hi:.1%})")
    t.add_row("SPL", f"{m['spl']:.3f}")
    s = m["steps_to_goal_successes"]
    t.add_row("steps to goal (successes)", f"{s['mean']:.1f} ± {s['std']:.1f}")
    s = m["steps_to_goal_failures_as_limit"]
    t.add_row("steps (failures = limit)", f"{s['mean']:.1f} ± {s['std']:.1f}")
    t.add_row("steps lower bound (oracle path)", f"{m['steps_lower_bound']['mean']:.1f}")
    t.add_row("return", f"{m['return']['mean']:.2f} ± {m['return']['std']:.2f}")
    t.add_row("collisions per episode", f"{m['collisions_per_episode']:.2f}")
    t.add_row("timeout rate", f"{m['timeout_rate']:.1%}")
    p = m["path_length_successes"]
    t.add_row("path length, m (successes)", f"{p['mean']:.2f} ± {p['std']:.2f}")
    console.print(t)


@app.command("sweep")
def sweep(
    preset: Annotated[
        str | None,
        typer.Option(help="Built-in search space: ppo sac td3 mlp lstm gtrxl (the paper's)."),
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="SweepConfig JSON file.")] = None,
    trials: Annotated[
        int | None, typer.Option(min=1, help="Finished trials wanted in the study.")
    ] = None,
    parallel: Annotated[
        int | None,
        typer.Option(
            min=1, max=1024, help="Trials asked at once; same-shape trials train batched."
        ),
    ] = None,
    objective: Annotated[
        str | None, typer.Option(help="success_rate, spl, steps_to_goal, return or collisions.")
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
    seed: Annotated[int, typer.Option(min=0, help="Sampler seed.")] = 0,
    set_: TrainSetOpt = None,
    out: Annotated[Path, typer.Option(help="Sweep folder (resumable: rerun to continue).")] = Path(
        "sweeps/quicknav"
    ),
) -> None:
    """Hyperparameter sweep with Optuna; same-shape trials train side by side in one program."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from quicknav_core.sweep import BUILTIN_SPACES, SweepConfig, builtin_sweep, run_sweep

    if (preset is None) == (config is None):
        fail("give either --preset NAME (a built-in space) or --config SWEEP.json")
    try:
        if config is not None:
            cfg = SweepConfig.model_validate_json(config.read_text())
        else:
            if preset not in BUILTIN_SPACES:
                fail(f"--preset {preset!r}: allowed values are {', '.join(BUILTIN_SPACES)}")
            cfg = builtin_sweep(preset, study_name=preset)
            cfg = cfg.model_copy(
                update={"base": cfg.base.model_copy(update={"total_steps": 2_000_000})}
            )
        data = cfg.model_dump(mode="json")
        for key, value in (("trials", trials), ("parallel", parallel), ("objective", objective),
                           ("storage", storage)):  # fmt: skip
            if value is not None:
                data[key] = value
        data["sampler_seed"] = seed
        if total_steps is not None:
            data["base"]["total_steps"] = total_steps
        base = apply_overrides(TrainConfig.model_validate(data["base"]), set_ or [])
        data["base"] = base.model_dump(mode="json")
        cfg = SweepConfig.model_validate(data)
    except FileNotFoundError:
        fail(f"--config {config}: no such file")
    except ValidationError as e:
        fail(format_validation_error(e))
    except ValueError as e:
        fail(str(e))
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
                  "(best_params.json, best_config.json, trials.csv, *.png, study.db)")  # fmt: skip


def _service_settings(**overrides):
    """Service settings from QUICKNAV_* variables plus CLI options; exits on a bad value."""
    from service.settings import Settings

    try:
        return Settings(**{k: v for k, v in overrides.items() if v is not None})
    except ValidationError as e:
        fail("invalid service settings (QUICKNAV_* variables / options):\n  " + "\n  ".join(
            f"QUICKNAV_{'_'.join(map(str, err['loc'])).upper()}: {err['msg']}" for err in e.errors()))  # fmt: skip
    raise AssertionError("unreachable")


@app.command("serve")
def serve(
    host: Annotated[
        str | None, typer.Option(help="Bind address (QUICKNAV_HOST, default 127.0.0.1).")
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="HTTP port (QUICKNAV_PORT, default 8000).")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="In-process workers (QUICKNAV_MAX_CONCURRENT_JOBS).")
    ] = None,
    no_worker: Annotated[
        bool, typer.Option("--no-worker", help="API only; run `quicknav worker` elsewhere.")
    ] = False,
    api_workers: Annotated[
        int,
        typer.Option(
            min=1,
            max=64,
            help="API processes (each with its own in-process workers unless --no-worker).",
        ),
    ] = 1,
    grpc_port: Annotated[
        int | None, typer.Option(help="gRPC Rollout port (QUICKNAV_GRPC_PORT, default 50051).")
    ] = None,
    no_grpc: Annotated[
        bool, typer.Option("--no-grpc", help="Do not start the gRPC Rollout server.")
    ] = False,
) -> None:
    """Start the HTTP API, the gRPC Rollout server and, by default, an in-process worker."""
    import uvicorn

    from service.api.app import create_app

    settings = _service_settings(host=host, port=port, max_concurrent_jobs=workers,
                                 embedded_worker=False if no_worker else None,
                                 grpc_port=grpc_port, grpc_enabled=False if no_grpc else None)  # fmt: skip
    if settings.host not in ("127.0.0.1", "localhost", "::1") and not settings.api_token:
        console.print(f"[yellow]warning:[/] binding {settings.host} without QUICKNAV_API_TOKEN: anyone who can"
                      " reach this port can submit jobs", soft_wrap=True)  # fmt: skip
    store = (
        "redis " + settings.redis_url
        if settings.redis_url
        else f"sqlite {settings.data_dir / 'jobs.db'}"
    )
    console.print(f"QuickNav API on http://{settings.host}:{settings.port} (docs at /docs), store: {store},"
                  f" in-process workers: {settings.max_concurrent_jobs if settings.embedded_worker else 0}",
                  soft_wrap=True)  # fmt: skip
    rollout = None
    if settings.grpc_enabled:
        from service.rollout.server import BackgroundServer

        rollout = BackgroundServer(settings).start()
        console.print(f"gRPC Rollout on {settings.host}:{rollout.port}", soft_wrap=True)
    if api_workers > 1:
        # several processes: each builds its app from the same QUICKNAV_* settings
        os.environ["QUICKNAV_EMBEDDED_WORKER"] = "false" if not settings.embedded_worker else "true"
        uvicorn.run("service.api.app:create_app", factory=True, host=settings.host, port=settings.port,
                    workers=api_workers, log_level="warning")  # fmt: skip
    else:
        uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")


@app.command("rollout-server")
def rollout_server(
    host: Annotated[
        str | None, typer.Option(help="Bind address (QUICKNAV_HOST, default 127.0.0.1).")
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="gRPC port (QUICKNAV_GRPC_PORT, default 50051).")
    ] = None,
    cpu_devices: Annotated[
        int,
        typer.Option(
            min=1,
            max=64,
            help="CPU devices XLA exposes; batches of at least 256 envs per device are split"
            " across them (on 2 cores one device was faster: gRPC needs the other core)."
            " Several GPUs are always used.",
        ),
    ] = 1,
) -> None:
    """Only the gRPC Rollout server: remote agents step batches of envs over one stream each."""
    if cpu_devices > 1:
        expose_cpu_devices(cpu_devices)
    enable_compilation_cache()
    from service.rollout.server import serve_forever

    settings = _service_settings(host=host, grpc_port=port)
    if settings.host not in ("127.0.0.1", "localhost", "::1") and not settings.api_token:
        console.print(f"[yellow]warning:[/] binding {settings.host} without QUICKNAV_API_TOKEN",
                      soft_wrap=True)  # fmt: skip
    try:
        serve_forever(settings)
    except OSError as e:
        fail(str(e))
    except KeyboardInterrupt:
        pass


@app.command("worker")
def worker(
    burst: Annotated[
        bool,
        typer.Option(
            help="Run queued jobs (and jobs orphaned by a dead worker), exit when none is queued or running."
        ),
    ] = False,
) -> None:
    """A worker process: claims jobs from the store (Redis for several machines), runs them."""
    import signal

    from service.settings import make_store
    from service.worker import Worker

    settings = _service_settings()
    w = Worker(make_store(settings), settings)

    def on_term(signum, frame):
        console.print("stopping at the next chunk boundary (checkpoint kept, job handed back)")
        w.shutdown.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    console.print(f"worker {w.id} on {'redis' if settings.redis_url else settings.data_dir / 'jobs.db'}",
                  soft_wrap=True)  # fmt: skip
    if burst:
        ran = w.run_burst()
        console.print(f"burst done: {ran} job(s) run, none queued or running")
    else:
        w.run_forever()


@app.command("presets")
def presets() -> None:
    """List the training presets."""
    from quicknav_core.train.presets import PRESETS

    for name, p in PRESETS.items():
        console.print(f"[bold]{name}[/]: {p['description']}")


# --------------------------------------------------------------------------- jobs on a service
jobs_app = typer.Typer(
    help="Jobs on a QuickNav service (quicknav serve): submit, list, follow, cancel, download.",
    no_args_is_help=True,
)
app.add_typer(jobs_app, name="jobs")

JobSetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="train/sweep: a config field (--set env.grid_size=8 --set total_steps=200000);"
        " sweep with a built-in space: trials, parallel or total_steps; eval --policy: an env field.",
    ),
]


@jobs_app.callback()
def jobs_main(
    ctx: typer.Context,
    url: Annotated[
        str, typer.Option(envvar="QUICKNAV_URL", help="The service's base URL.")
    ] = "http://127.0.0.1:8000",
    token: Annotated[
        str | None,
        typer.Option(envvar="QUICKNAV_API_TOKEN", help="Bearer token, if the service wants one."),
    ] = None,
) -> None:
    """Talk to a running QuickNav service over HTTP."""
    ctx.obj = {"url": url, "token": token}


@contextmanager
def service_client(ctx: typer.Context):
    """A QuickNavClient for --url/--token; a failed request prints the server's message, exits 1."""
    from quicknav_client import QuickNavClient, QuickNavError

    try:
        with QuickNavClient(ctx.obj["url"], token=ctx.obj["token"]) as client:
            yield client
    except QuickNavError as e:
        fail(str(e), code=1)


def parse_sets(items: list[str] | None) -> dict:
    """--set key=value items as a dict; values are JSON where they parse, else strings."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            fail(f"--set {item!r}: expected key=value, e.g. env.grid_size=8")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return out


def load_json_file(path: Path) -> dict:
    """A JSON object from a file; exits with a clear message if missing or malformed."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        fail(f"--config {path}: no such file")
    except json.JSONDecodeError as e:
        fail(f"--config {path}: not valid JSON ({e})")
    if not isinstance(data, dict):
        fail(f"--config {path}: expected a JSON object")
    return data


def metrics_summary(metrics: dict) -> str:
    """The few numbers worth a glance: success, return, throughput, a sweep's best value."""
    from quicknav_client.rest import metrics_summary as summary

    return summary(metrics, sep="  ")


def _when(t: float | None) -> str:
    import time

    return "" if t is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def follow_job(job) -> None:
    """Show a progress bar until the job finishes; exit 0 if it succeeded, 1 otherwise."""
    from rich.progress import (
        BarColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    name = f"{job.kind} {job.id[:8]}"
    cols = (TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
            TimeElapsedColumn(), TextColumn("{task.fields[info]}"))  # fmt: skip
    with Progress(*cols, console=console) as progress:
        task = progress.add_task(f"{name} {job.status}", total=1.0, completed=job.progress,
                                 info=metrics_summary(job.metrics))  # fmt: skip

        def on_event(event: dict) -> None:
            update = {}
            if isinstance(event.get("status"), str):
                update["description"] = f"{name} {event['status']}"
            if isinstance(event.get("progress"), int | float):
                update["completed"] = event["progress"]
            info = metrics_summary(event.get("metrics") or {})
            if info:
                update["info"] = info
            progress.update(task, **update)

        job.wait(on_event=on_event)
    colour = "green" if job.succeeded else "red"
    console.print(f"job {job.id}: [{colour}]{job.status}[/]", highlight=False)
    if job.error:
        console.print(f"error: {job.error}", highlight=False, markup=False, soft_wrap=True)
    if not job.succeeded:
        raise typer.Exit(1)


@jobs_app.command("submit")
def jobs_submit(
    ctx: typer.Context,
    kind: Annotated[str, typer.Argument(help="train, sweep or eval.")],
    preset: Annotated[
        str | None,
        typer.Option(
            help="train: a preset (default demo); sweep: a built-in space (ppo, lstm...)."
        ),
    ] = None,
    config: Annotated[
        Path | None, typer.Option("--config", help="TrainConfig or SweepConfig JSON file.")
    ] = None,
    set_: JobSetOpt = None,
    job: Annotated[
        str | None, typer.Option("--job", help="eval: the train job whose checkpoint to evaluate.")
    ] = None,
    policy: Annotated[
        str | None, typer.Option(help="eval: a baseline instead of a job, random or oracle.")
    ] = None,
    episodes: Annotated[int, typer.Option(min=1, help="eval: episodes.")] = 100,
    seed: Annotated[int, typer.Option(min=0, help="eval: episode seed.")] = 0,
    stochastic: Annotated[bool, typer.Option(help="eval: sample actions, not the mean.")] = False,
    follow: Annotated[
        bool, typer.Option("--follow", help="Wait with a progress bar until the job finishes.")
    ] = False,
) -> None:
    """Submit a job; prints its id (and with --follow, exits 0 only if it succeeds)."""
    sets = parse_sets(set_)
    if kind not in ("train", "sweep", "eval"):
        fail(f"KIND {kind!r}: allowed values are train, sweep and eval")
    if kind != "eval" and (job or policy):
        fail("--job and --policy are for eval jobs")
    if kind == "eval" and (preset or config):
        fail("--preset and --config are for train and sweep jobs; eval takes --job or --policy")
    if preset is not None and config is not None:
        fail("give either --preset or --config, not both")
    with service_client(ctx) as client:
        if kind == "train":
            if config is not None:
                submitted = client.train(config=load_json_file(config), overrides=sets)
            else:
                submitted = client.train(preset=preset or "demo", overrides=sets)
        elif kind == "sweep":
            if config is not None:
                submitted = client.sweep(load_json_file(config), overrides=sets)
            elif preset is not None:
                knobs = ("trials", "parallel", "total_steps")
                bad = [k for k in sets if k not in knobs]
                if bad:
                    fail(f"--set {bad[0]}: with a built-in space only {', '.join(knobs)} can be set;"
                         " for other fields write a SweepConfig and pass --config")  # fmt: skip
                submitted = client.sweep(preset, **sets)
            else:
                fail("give --preset SPACE (a built-in search space) or --config SWEEP.json")
        else:
            if job is not None and sets:
                fail("--set changes a baseline's env (--policy); a --job keeps its own env")
            submitted = client.evaluate(job=job, policy=policy, episodes=episodes, seed=seed,
                                        env=sets, stochastic=stochastic)  # fmt: skip
        console.print(f"submitted {submitted.kind} job {submitted.id} ({submitted.status})",
                      highlight=False)  # fmt: skip
        if follow:
            follow_job(submitted)


@jobs_app.command("list")
def jobs_list(
    ctx: typer.Context,
    status: Annotated[
        str | None, typer.Option(help="queued, running, succeeded, failed or cancelled.")
    ] = None,
    kind: Annotated[str | None, typer.Option(help="train, sweep or eval.")] = None,
    limit: Annotated[int, typer.Option(min=1, max=500, help="Jobs to show.")] = 20,
    offset: Annotated[int, typer.Option(min=0, help="Skip this many (newest first).")] = 0,
) -> None:
    """List jobs, newest first."""
    from rich.table import Table

    with service_client(ctx) as client:
        page = client.jobs(status=status, kind=kind, limit=limit, offset=offset)
    table = Table(
        title=f"{len(page)} of {page.count} jobs" + (f" from #{offset + 1}" if offset else "")
    )
    table.add_column("id", no_wrap=True)
    for col in ("kind", "status", "progress", "tries", "created", "latest"):
        table.add_column(col, justify="right" if col in ("progress", "tries") else "left")
    for j in page:
        latest = f"[red]{j.error}[/]" if j.error else metrics_summary(j.metrics)
        table.add_row(j.id, j.kind, j.status, f"{j.progress:.0%}", str(j.attempts),
                      _when(j.created_at), latest)  # fmt: skip
    Console(width=max(console.width, 140)).print(table)


@jobs_app.command("show")
def jobs_show(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(help="The job's id.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the server's JSON.")] = False,
) -> None:
    """Show one job: status, progress, latest metrics, result or error, request."""
    from rich.table import Table

    with service_client(ctx) as client:
        j = client.job(job_id)
    if as_json:
        print(json.dumps(j.raw, indent=2))
        return
    table = Table(title=f"{j.kind} job {j.id}", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value", overflow="fold")
    rows = [("status", j.status + (" (cancel requested)" if j.cancel_requested and not j.done else "")),
            ("progress", f"{j.progress:.1%}"), ("attempts", str(j.attempts)),
            ("created", _when(j.created_at)), ("started", _when(j.started_at)),
            ("finished", _when(j.finished_at))]  # fmt: skip
    if j.error:
        rows.append(("error", j.error))
    if j.metrics:
        rows.append(("metrics", json.dumps(j.metrics)))
    if j.result is not None:
        rows.append(("result", json.dumps(j.result)))
    rows.append(("request", json.dumps(j.request)))
    for key, value in rows:
        table.add_row(key, value)
    Console(width=max(console.width, 120)).print(table, markup=False, highlight=False)


@jobs_app.command("follow")
def jobs_follow(
    ctx: typer.Context, job_id: Annotated[str, typer.Argument(help="The job's id.")]
) -> None:
    """Progress bar until the job finishes; exit code 0 if it succeeded, 1 if failed or cancelled."""
    with service_client(ctx) as client:
        follow_job(client.job(job_id))


@jobs_app.command("cancel")
def jobs_cancel(
    ctx: typer.Context, job_id: Annotated[str, typer.Argument(help="The job's id.")]
) -> None:
    """Cancel a job: a queued one at once, a running one at its next chunk boundary."""
    with service_client(ctx) as client:
        j = client.job(job_id).cancel()
    note = " (stops at the next chunk boundary)" if j.cancel_requested and not j.done else ""
    console.print(f"job {j.id}: {j.status}{note}", highlight=False)


@jobs_app.command("artifacts")
def jobs_artifacts(
    ctx: typer.Context, job_id: Annotated[str, typer.Argument(help="The job's id.")]
) -> None:
    """List a job's files (names for `quicknav jobs download`)."""
    from rich.table import Table

    with service_client(ctx) as client:
        files = client.job(job_id).artifacts()
    table = Table(title=f"{len(files)} artifacts of job {job_id}")
    table.add_column("name", no_wrap=True)
    table.add_column("bytes", justify="right")
    for f in files:
        table.add_row(f["name"], f"{f['bytes']:,}")
    Console(width=max(console.width, 100)).print(table)


@jobs_app.command("download")
def jobs_download(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(help="The job's id.")],
    name: Annotated[str, typer.Argument(help="Artifact name, e.g. checkpoint/state.msgpack.")],
    out: Annotated[
        Path | None, typer.Option("--out", help="File or folder (default: the name's basename).")
    ] = None,
) -> None:
    """Download one of a job's artifacts."""
    with service_client(ctx) as client:
        path = client.download(job_id, name, out)
    console.print(f"wrote {path} ({path.stat().st_size:,} bytes)", highlight=False)


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
