"""`quicknav jobs`: drive a running service over HTTP with the SDK (submit, list, follow, ...)."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from quicknav_cli.common import console, env_sets, err_console, fail, read_json, sets, warn

app = typer.Typer(
    help="Jobs on a QuickNav service (quicknav serve): submit, list, follow, cancel, download.",
    no_args_is_help=True,
)

JobSetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="train: a config field (--set env.grid_size=8 --set total_steps=200000); sweep: a"
        " SweepConfig or base config field (--set trials=4 --set env.grid_size=8); eval: an env"
        " field of the evaluated policy's env.",
    ),
]


@app.callback()
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
    try:
        from quicknav_client import QuickNavClient, QuickNavError
    except ImportError:
        fail("the QuickNav SDK is not installed: pip install 'quicknav[service]' (or ./clients)")
    try:
        with QuickNavClient(ctx.obj["url"], token=ctx.obj["token"]) as client:
            yield client
    except QuickNavError as e:
        fail(str(e), code=1)


def metrics_summary(metrics: dict) -> str:
    """The few numbers worth a glance: success, return, throughput, a sweep's best value."""
    from quicknav_client.rest import metrics_summary as summary

    return summary(metrics, sep="  ")


def _when(t: float | None) -> str:
    import time

    return "" if t is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))


def _elapsed(seconds: float) -> str:
    seconds = max(0, int(seconds))
    return f"{seconds} s" if seconds < 120 else f"{seconds // 60} min {seconds % 60:02d} s"


class JobProgress:
    """A job's progress bar, fed by its events; readable at 80 columns.

    While the job compiles (metrics ``phase == "compiling"``) the bar pulses and says
    ``compiling 12 s`` (time since ``phase_since``, ticking) instead of a percentage that has not
    started; the latest metrics go on a second line, so they never squeeze the bar.
    """

    def __init__(self, job, console: Console, clock=None):
        import time

        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
        from rich.table import Column

        self.clock = clock or time.time
        self.name = f"{job.kind} {job.id[:8]}"
        self.status = job.status
        self.phase: str | None = None
        self.phase_since: float | None = None
        cols = (TextColumn("{task.description}", table_column=Column(no_wrap=True)),
                BarColumn(bar_width=24), TextColumn("{task.fields[done]}", justify="right"),
                TimeElapsedColumn())  # fmt: skip
        self.progress = Progress(*cols, console=console)
        self.task = self.progress.add_task(self.name, total=1.0, completed=job.progress, done="",
                                           info="")  # fmt: skip
        self.update({"status": job.status, "progress": job.progress, "metrics": job.metrics})

    def update(self, event: dict) -> None:
        """Take one event (status, progress, metrics) into the bar."""
        if isinstance(event.get("status"), str):
            self.status = event["status"]
        elif event.get("type") in ("started", "succeeded", "failed", "cancelled", "queued"):
            self.status = "running" if event["type"] == "started" else event["type"]
        metrics = event.get("metrics") or {}
        if isinstance(metrics.get("phase"), str):
            if metrics["phase"] != self.phase:
                self.phase_since = None
            self.phase = metrics["phase"]
            since = metrics.get("phase_since")
            if isinstance(since, int | float):
                self.phase_since = float(since)
            elif self.phase_since is None:
                self.phase_since = self.clock()
        update: dict = {}
        if isinstance(event.get("progress"), int | float):
            update["completed"] = event["progress"]
        info = metrics_summary(metrics)
        if info:
            update["info"] = info
        self.progress.update(self.task, **update)
        self.refresh()

    @property
    def compiling(self) -> bool:
        """The job runs but has not finished compiling its first chunk (or batch)."""
        return self.status == "running" and self.phase == "compiling"

    def refresh(self) -> None:
        """Re-label the bar (called on every event and before each render, so time ticks)."""
        task = self.progress.tasks[0]
        if self.compiling:
            since = self.phase_since if self.phase_since is not None else self.clock()
            label, done, total = f"compiling {_elapsed(self.clock() - since)}", "", None
        else:
            label, done, total = self.status, f"{task.completed:.0%}", 1.0
        self.progress.update(self.task, description=f"{self.name} {label}", done=done,
                             total=total)  # fmt: skip

    def renderable(self):
        """What the terminal shows now: the bar line, then the metrics line."""
        from rich.console import Group
        from rich.text import Text

        self.refresh()
        info = self.progress.tasks[0].fields.get("info") or ""
        lines = [self.progress.make_tasks_table(self.progress.tasks)]
        # the metrics on a line of their own below the bar: an 80-column terminal keeps its bar
        if info:
            lines.append(Text(f"  {info}", no_wrap=True, overflow="ellipsis", style="dim"))
        return Group(*lines)


def follow_job(job) -> None:
    """Show a progress bar until the job finishes; exit 0 if it succeeded, 1 otherwise."""
    from rich.live import Live

    bar = JobProgress(job, console)
    # the bar is re-rendered on each refresh, so "compiling 12 s" ticks between events
    with Live(console=console, refresh_per_second=4, get_renderable=bar.renderable) as live:
        job.wait(on_event=lambda event: (bar.update(event), live.refresh()))
    if not console.is_terminal:
        console.line()  # a pipe or a log gets the bar's last frame without its line end
    report_finished(job)


def report_finished(job) -> None:
    """The finished job's status line, its warnings and error (on stderr); exit 1 unless it
    succeeded."""
    colour = "green" if job.succeeded else "red"
    console.print(f"job {job.id}: [{colour}]{job.status}[/]", highlight=False, markup=True)
    print_warnings(job)
    if job.error:
        err_console.print(f"error: {job.error}", highlight=False, markup=False, soft_wrap=True)
    if not job.succeeded:
        raise typer.Exit(1)


def print_warnings(job) -> None:
    """Each of the job's warnings (an artifact that failed to render) on stderr."""
    for warning in job.warnings:
        err_console.print(f"warning: {warning}", highlight=False, markup=False, soft_wrap=True)


@app.command("submit")
def jobs_submit(
    ctx: typer.Context,
    kind: Annotated[str, typer.Argument(help="train, sweep or eval.")],
    preset: Annotated[
        str | None,
        typer.Option(help="train: a preset (default demo). (sweep: deprecated name of --space.)"),
    ] = None,
    space: Annotated[
        str | None, typer.Option(help="sweep: a built-in search space (ppo, lstm, ...).")
    ] = None,
    base: Annotated[
        str | None, typer.Option(help="sweep: with --space, the preset its trials start from"
                                 " (default: the space's paper preset).")
    ] = None,
    config: Annotated[
        Path | None, typer.Option("--config", help="TrainConfig or SweepConfig JSON file.")
    ] = None,
    set_: JobSetOpt = None,
    trials: Annotated[
        int | None, typer.Option(min=1, help="sweep: finished trials wanted.")
    ] = None,
    parallel: Annotated[
        int | None, typer.Option(min=1, max=1024, help="sweep: trials asked at once.")
    ] = None,
    total_steps: Annotated[
        int | None, typer.Option(min=1, help="train: env steps; sweep: env steps per trial.")
    ] = None,
    job: Annotated[
        str | None, typer.Option("--job", help="eval: the train job whose checkpoint to evaluate.")
    ] = None,
    policy: Annotated[
        str | None, typer.Option(help="eval: a baseline instead of a job, random, oracle or dwa.")
    ] = None,
    episodes: Annotated[int, typer.Option(min=1, help="eval: episodes.")] = 100,
    seed: Annotated[int, typer.Option(min=0, help="eval: episode seed.")] = 0,
    split: Annotated[str, typer.Option(help="eval: room bank, test (held out) or train.")] = "test",
    deterministic: Annotated[
        bool,
        typer.Option("--deterministic/--no-deterministic",
                     help="eval: act with the policy's mean (default), or sample its actions."),
    ] = True,
    stochastic: Annotated[
        bool, typer.Option("--stochastic", hidden=True, help="Deprecated: --no-deterministic.")
    ] = False,
    robustness: Annotated[
        bool,
        typer.Option("--robustness", help="eval: also run the episodes at fixed levels of lidar"
                     " noise, dropout, bias, latency and wheel asymmetry (robustness.png)."),
    ] = False,
    shield: Annotated[
        bool,
        typer.Option("--shield", help="eval: put the safety layer between the policy and the"
                     " wheels (a command that would bring the robot within 1 cm of a lidar return"
                     " is slowed, down to turning in place)."),
    ] = False,
    map: Annotated[
        str | None,
        typer.Option("--map", metavar="map:<id>", help="eval: drive a map uploaded to the server"
                     " (quicknav maps list) at the policy's cell size; the grid and the step"
                     " limit follow the map."),
    ] = None,
    follow: Annotated[
        bool, typer.Option("--follow", help="Wait with a progress bar until the job finishes.")
    ] = False,
) -> None:
    """Submit a job; prints its id (and with --follow, exits 0 only if it succeeds).

    The request goes to the service as given; the service resolves it to the config it stores
    (`quicknav jobs show ID` prints it), exactly as `quicknav train --print-config` would locally.
    """
    overrides = sets(set_)
    if kind not in ("train", "sweep", "eval"):
        fail(f"KIND {kind!r}: allowed values are train, sweep and eval")
    if kind != "eval" and (job or policy):
        fail("--job and --policy are for eval jobs")
    if kind == "eval" and (preset or config or space):
        fail("--preset, --space and --config are for train and sweep jobs; eval takes --job or --policy")
    if kind != "sweep" and (trials or parallel or base):
        fail("--trials, --parallel and --base are for sweep jobs")
    if kind == "eval" and total_steps:
        fail("--total-steps is for train and sweep jobs")
    if kind != "eval" and robustness:
        fail("--robustness is for eval jobs")
    if kind != "eval" and map is not None:
        fail("--map is for eval jobs (a train job names its maps: --set env.rooms=maps --set"
             " 'env.maps.train=[\"map:<id>\"]')")
    if map is not None and not map.startswith("map:") and Path(map).is_file():
        fail(f"--map {map}: a file on this machine, which the server cannot read; upload it first"
             f" (quicknav maps upload {map}) and pass the map:<id> it prints")  # fmt: skip
    if kind != "eval" and shield:
        fail("--shield is for eval jobs")
    if stochastic:
        warn("--stochastic is deprecated: write --no-deterministic (the API's field is"
             " `deterministic`)")  # fmt: skip
        deterministic = False
    if kind == "sweep" and preset is not None:
        if space is not None:
            fail("give --space only (--preset is its deprecated name for sweeps)")
        warn(f"--preset is deprecated for sweeps: write --space {preset}")
        space, preset = preset, None
    if kind == "train" and space is not None:
        fail("--space is for sweep jobs; train takes --preset or --config")
    if (preset or space) is not None and config is not None:
        fail("give either a preset/space or --config, not both")
    with service_client(ctx) as client:
        if kind == "train":
            if total_steps is not None:
                overrides["total_steps"] = total_steps
            if config is not None:
                submitted = client.train(config=read_json(config), overrides=overrides)
            else:
                submitted = client.train(preset=preset or "demo", overrides=overrides)
        elif kind == "sweep":
            if config is None and space is None:
                fail("give --space SPACE (a built-in search space) or --config SWEEP.json")
            submitted = client.sweep(
                space=space, base=base, config=read_json(config) if config is not None else None,
                trials=trials, parallel=parallel, total_steps=total_steps, overrides=overrides,
            )  # fmt: skip
        else:
            submitted = client.evaluate(job=job, policy=policy, episodes=episodes, seed=seed,
                                        env=env_sets(set_), split=split, deterministic=deterministic,
                                        robustness=robustness, shield=shield, map=map)  # fmt: skip
        console.print(f"submitted {submitted.kind} job {submitted.id} ({submitted.status})",
                      highlight=False)  # fmt: skip
        if follow:
            follow_job(submitted)


def progress_cell(job) -> str:
    """The list's progress column: a percentage while it means something, a word otherwise."""
    if job.status == "failed" or job.status == "cancelled":
        return "–"  # how far it got is in the error; a full bar would read as done
    if job.status == "running" and job.phase == "compiling":
        return "compiling"
    return f"{job.progress:.0%}"


def latest_cell(job):
    """The list's last column: why a failed job failed, why a queued one waits (when no live
    worker can run it), else its latest numbers."""
    from rich.text import Text

    if job.error:
        reason = job.error.strip().splitlines()[-1] if job.error.strip() else job.error
        return Text(reason, style="red")
    if job.waiting:  # queued, and no live worker can run it
        return Text(job.waiting, style="yellow")
    text = Text(metrics_summary(job.metrics))
    if job.warnings:
        text.append(f"  ({len(job.warnings)} warning{'s' if len(job.warnings) > 1 else ''})",
                    style="yellow")  # fmt: skip
    return text


@app.command("list")
def jobs_list(
    ctx: typer.Context,
    status: Annotated[
        str | None, typer.Option(help="queued, running, succeeded, failed or cancelled.")
    ] = None,
    kind: Annotated[str | None, typer.Option(help="train, sweep or eval.")] = None,
    limit: Annotated[int, typer.Option(min=1, max=500, help="Jobs to show.")] = 20,
    offset: Annotated[int, typer.Option(min=0, help="Skip this many (newest first).")] = 0,
) -> None:
    """List jobs, newest first (a failed job shows why it failed)."""
    from rich.table import Table

    with service_client(ctx) as client:
        page = client.jobs(status=status, kind=kind, limit=limit, offset=offset)
    table = Table(
        title=f"{len(page)} of {page.count} jobs" + (f" from #{offset + 1}" if offset else "")
    )
    table.add_column("id", no_wrap=True)
    for col in ("kind", "status", "progress", "tries", "created"):
        table.add_column(col, justify="right" if col in ("progress", "tries") else "left")
    table.add_column("latest / reason", overflow="fold")
    for j in page:
        table.add_row(j.id, j.kind, j.status, progress_cell(j), str(j.attempts),
                      _when(j.created_at), latest_cell(j))  # fmt: skip
    Console(width=max(console.width, 140), markup=False, emoji=False).print(table)


@app.command("show")
def jobs_show(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(help="The job's id.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the server's JSON.")] = False,
) -> None:
    """Show one job: status, progress, latest metrics, result or error, warnings, request."""
    import time

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
    if j.status == "running" and j.phase == "compiling":
        since = j.metrics.get("phase_since")
        rows.append(("phase", "compiling" + (f" for {_elapsed(time.time() - since)}"
                                             if isinstance(since, int | float) else "")))  # fmt: skip
    if j.error:
        rows.append(("error", j.error))
    for warning in j.warnings:
        rows.append(("warning", warning))
    if j.metrics:
        rows.append(("metrics", json.dumps(j.metrics)))
    if j.result is not None:
        rows.append(("result", json.dumps(j.result)))
    if j.config:
        rows.append(("config", json.dumps(j.config)))
    rows.append(("request", json.dumps(j.request)))
    for key, value in rows:
        table.add_row(key, value)
    Console(width=max(console.width, 120), markup=False, emoji=False).print(table, markup=False, highlight=False)


@app.command("follow")
def jobs_follow(
    ctx: typer.Context, job_id: Annotated[str, typer.Argument(help="The job's id.")]
) -> None:
    """Progress bar until the job finishes; exit code 0 if it succeeded, 1 if failed or cancelled."""
    with service_client(ctx) as client:
        follow_job(client.job(job_id))


@app.command("cancel")
def jobs_cancel(
    ctx: typer.Context, job_id: Annotated[str, typer.Argument(help="The job's id.")]
) -> None:
    """Cancel a job: a queued one at once, a running one at its next chunk boundary."""
    with service_client(ctx) as client:
        j = client.job(job_id).cancel()
    note = " (stops at the next chunk boundary)" if j.cancel_requested and not j.done else ""
    console.print(f"job {j.id}: {j.status}{note}", highlight=False)


@app.command("artifacts")
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
    Console(width=max(console.width, 100), markup=False, emoji=False).print(table)


@app.command("download")
def jobs_download(
    ctx: typer.Context,
    job_id: Annotated[str, typer.Argument(help="The job's id.")],
    name: Annotated[str, typer.Argument(help="Artifact name, e.g. checkpoint/state.msgpack.")],
    out: Annotated[
        Path | None, typer.Option("--out", help="File or folder (default: the name's basename).")
    ] = None,
) -> None:
    """Download one of a job's artifacts (the SDK's `download(job_id, name, out)`)."""
    with service_client(ctx) as client:
        path = client.download(job_id, name, out=out)
    console.print(f"wrote {path} ({path.stat().st_size:,} bytes)", highlight=False)
