"""`quicknav train` and `quicknav presets`: train an agent into a run folder, list the presets."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.progress import Progress, ProgressColumn
from rich.text import Text

from quicknav_cli.common import (
    PrintConfigOpt,
    SetOpt,
    admitted,
    console,
    enable_compilation_cache,
    fail,
    print_config,
    read_json,
    resolved,
    sets,
    warn,
)

# --network NAME: the network section it sets (other fields keep the preset's values)
NETWORKS: dict[str, dict[str, Any]] = {
    "mlp": {"network.kind": "mlp", "network.memory_size": 0},
    "mlp-memory": {"network.kind": "mlp", "network.memory_size": 32},
    "lstm": {"network.kind": "lstm"},
    "gtrxl": {"network.kind": "gtrxl"},
}
ALGORITHMS = ("ppo", "sac", "td3")


def train_request(
    preset: str | None,
    config: Path | None,
    algo: str | None = None,
    network: str | None = None,
    total_steps: int | None = None,
    num_envs: int | None = None,
    seed: int | None = None,
    overrides: list[str] | None = None,
) -> dict[str, Any]:
    """The training request the flags describe (what the SDK would send to the service)."""
    if preset is not None and config is not None:
        fail("give either --preset or --config, not both")
    changes: dict[str, Any] = {}
    if algo is not None:
        if algo not in ALGORITHMS:
            fail(f"--algo {algo!r}: allowed values are {', '.join(ALGORITHMS)}")
        changes["algorithm.name"] = algo
    if network is not None:
        if network not in NETWORKS:
            fail(f"--network {network!r}: allowed values are {', '.join(NETWORKS)}")
        changes.update(NETWORKS[network])
    for key, value in (("total_steps", total_steps), ("num_envs", num_envs), ("seed", seed)):
        if value is not None:
            changes[key] = value
    changes.update(sets(overrides))
    if config is not None:
        return {"config": read_json(config), "overrides": changes}
    return {"preset": preset or "demo", "overrides": changes}


def holds_run(folder: Path) -> bool:
    """Whether a folder holds a run already (its config or a checkpoint)."""
    from quicknav_core.layout import RunFolder

    run = RunFolder(folder)
    return run.config.exists() or run.checkpoint_folder.exists()


def free_folder(default: Path, claim: str | None = None) -> Path:
    """The default run folder, or, where an earlier run holds it, the first of NAME-2, NAME-3, ...
    that holds none: a second `quicknav train --preset demo` never trains over the first.

    ``claim`` (the run's config as JSON): the folder is taken for this run at once, its config.json
    created exclusively (``train_run`` writes the same), so that a second command started in the
    same instant, which found the same folder free, takes the next name instead of training into
    it too."""
    folder, n = default, 1
    while holds_run(folder) or (claim is not None and not _claimed(folder, claim)):
        n += 1
        folder = default.with_name(f"{default.name}-{n}")
    return folder


def _claimed(folder: Path, config_json: str) -> bool:
    """Whether this process created ``folder``'s config.json (False: another one did first)."""
    from quicknav_core.layout import RunFolder

    folder.mkdir(parents=True, exist_ok=True)
    try:
        with open(RunFolder(folder).config, "x") as f:
            f.write(config_json)
    except FileExistsError:
        return False
    return True


def train(
    preset: Annotated[
        str | None, typer.Option(help="Preset name (quicknav presets lists them; default demo).")
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="TrainConfig JSON file.")] = None,
    algo: Annotated[
        str | None, typer.Option(help="ppo, sac or td3 (its default hyperparameters).")
    ] = None,
    network: Annotated[str | None, typer.Option(help="mlp, mlp-memory, lstm or gtrxl.")] = None,
    total_steps: Annotated[int | None, typer.Option(help="Env steps to train.")] = None,
    num_envs: Annotated[int | None, typer.Option(help="Parallel envs.")] = None,
    seed: Annotated[int | None, typer.Option(help="Training seed.")] = None,
    set_: SetOpt = None,
    out: Annotated[
        Path | None, typer.Option(help="Run folder (default runs/<preset>-s<seed>, or -2, -3, ..."
                                  " where an earlier run holds it); one that holds a run is"
                                  " refused: --resume it, or name another.")
    ] = None,
    resume: Annotated[
        Path | None,
        typer.Option(help="Continue the run in this folder, as its config.json says (no other"
                     " config options)."),
    ] = None,
    checkpoint_every: Annotated[int, typer.Option(min=1, help="Checkpoint every N chunks.")] = 1,
    print_only: PrintConfigOpt = False,
) -> None:
    """Train an agent; writes config.json, metrics.jsonl, a checkpoint and learning_curve.png."""
    from rich.progress import BarColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from quicknav_core.config import resolve_train
    from quicknav_core.layout import RunFolder
    from quicknav_core.train.run import read_config, train_run

    if resume is not None:
        changes = [flag for flag, value in (
            ("--preset", preset), ("--config", config), ("--algo", algo), ("--network", network),
            ("--total-steps", total_steps), ("--num-envs", num_envs), ("--seed", seed),
            ("--set", set_), ("--out", out),
        ) if value is not None]  # fmt: skip
        if changes:
            fail(f"--resume {resume} continues the run as its config.json says, in its folder;"
                 f" {', '.join(changes)} would change it. To train otherwise, start a new run"
                 f" (quicknav train --config {RunFolder(resume).config} ... --out NEW)")  # fmt: skip
        try:
            cfg = read_config(resume)
        except FileNotFoundError:
            fail(f"--resume {resume}: not a run folder (no config.json)")
        run_dir = resume
    else:
        request = train_request(preset, config, algo, network, total_steps, num_envs, seed, set_)
        cfg = resolved(resolve_train, request)
        claim = None if print_only or out is not None else cfg.model_dump_json(indent=2)
        run_dir = out or free_folder(
            Path("runs") / f"{preset or (config.stem if config else 'demo')}-s{cfg.seed}", claim
        )
        if out is not None and holds_run(out) and not print_only:
            # training over it would leave its evaluations and exports beside another policy
            fail(f"--out {out} holds a run already (config.json, checkpoint/): continue it with"
                 f" --resume {out}, or train into another folder")  # fmt: skip
    if print_only:
        print_config(cfg)
        return
    from quicknav_core.runtime import Runtime
    from quicknav_core.train.trainers import local_devices

    runtime = Runtime()  # this command's banks and compiled programs
    # every door's admission: a map that cannot be used, a robot wider than every room's
    # passages, more devices than this machine has: refused before anything compiles
    try:
        admitted(cfg, runtime)
        devices = local_devices(cfg.devices)
    except BaseException:
        if resume is None and out is None:  # the default folder claimed above: give it back
            RunFolder(run_dir).config.unlink(missing_ok=True)
            try:
                run_dir.rmdir()  # made for this run, nothing else in it
            except OSError:
                pass
        raise
    enable_compilation_cache()
    console.print(
        f"training {cfg.trainer_kind} ({cfg.network.kind}) for {cfg.total_steps:,} env steps,"
        f" {cfg.num_envs} envs, grid {cfg.env.grid_size}"
        f"{f', {len(devices)} devices' if len(devices) > 1 else ''} -> {run_dir}"
    )
    # fits 80 columns: the bar line, then the latest metrics on a line of their own
    columns = (
        TextColumn("[progress.description]{task.description}"), BarColumn(bar_width=24),
        StepsColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
    )  # fmt: skip
    with MetricsProgress(*columns, console=console) as progress:
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

        before = RunFolder(run_dir).meta() if resume is not None else None
        if resume is not None and before is None:  # stopped before its first checkpoint
            console.print(f"{run_dir} has no complete checkpoint yet: training it from the start,"
                          " as its config.json says", highlight=False, soft_wrap=True)  # fmt: skip
        summary = train_run(cfg, run_dir, callback=on_chunk, resume=before is not None,
                            checkpoint_every=checkpoint_every, runtime=runtime)  # fmt: skip
    if before is not None and summary["chunks_done"] == before.chunk:
        console.print(f"nothing left to train: {run_dir} has trained all of its"
                      f" {summary['env_steps']:,} env steps. To train longer, start a new run:"
                      f" quicknav train --config {RunFolder(run_dir).config} --total-steps N"
                      " --out NEW", highlight=False, soft_wrap=True)  # fmt: skip
        return
    final = summary["final"]
    console.print(
        f"done: {summary['env_steps']:,} env steps; last chunk: return {final.get('mean_return', 0):.1f},"
        f" success {final.get('success_rate', 0):.0%}"
    )
    if summary["env_steps"] != cfg.total_steps:
        console.print(
            f"note: {summary['env_steps']:,} env steps, not {cfg.total_steps:,}: training runs in"
            " whole updates of num_envs x rollout steps"
        )
    console.print(
        f"run folder: {run_dir} (config.json, metrics.jsonl, checkpoint/, learning_curve.png)"
    )
    for message in summary.get("warnings", []):
        warn(message)


def _steps(n: float) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.0f}k" if n >= 1e4 else f"{n:.0f}"


class StepsColumn(ProgressColumn):
    """``1.50M/1.50M steps``: env steps done and planned, short enough for an 80-column bar."""

    def render(self, task) -> Text:
        return Text(f"{_steps(task.completed)}/{_steps(task.total or 0)} steps")


class MetricsProgress(Progress):
    """A rich Progress that shows its task's ``info`` field on a second line below the bar."""

    def get_renderables(self):
        yield self.make_tasks_table(self.tasks)
        info = self.tasks[0].fields.get("info") if self.tasks else ""
        if info:
            yield Text(f"  {info}", no_wrap=True, overflow="ellipsis", style="dim")


def presets() -> None:
    """List the training presets."""
    from quicknav_core.config import PRESETS

    for name, p in PRESETS.items():
        console.print(f"[bold]{name}[/]: {p['description']}", markup=True)
