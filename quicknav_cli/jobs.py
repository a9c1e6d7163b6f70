"""`quicknav jobs`: drive a running service over HTTP with the SDK (submit, list, follow, ...)."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from quicknav_cli.common import console, fail, read_json, sets

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


@app.command("submit")
def jobs_submit(
    ctx: typer.Context,
    kind: Annotated[str, typer.Argument(help="train, sweep or eval.")],
    preset: Annotated[
        str | None,
        typer.Option(help="train: a preset (default demo). (sweep: old name of --space.)"),
    ] = None,
    space: Annotated[
        str | None, typer.Option(help="sweep: a built-in search space (ppo, lstm, ...).")
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
    split: Annotated[str, typer.Option(help="eval: room bank, test (held out) or train.")] = "test",
    deterministic: Annotated[
        bool, typer.Option("--deterministic/--stochastic", help="eval: act with the mean, or sample.")
    ] = True,
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
    if kind == "sweep" and preset is not None:
        if space is not None:
            fail("give --space only (--preset is its old name for sweeps)")
        space, preset = preset, None
    if kind == "train" and space is not None:
        fail("--space is for sweep jobs; train takes --preset or --config")
    if (preset or space) is not None and config is not None:
        fail("give either a preset/space or --config, not both")
    with service_client(ctx) as client:
        if kind == "train":
            if config is not None:
                submitted = client.train(config=read_json(config), overrides=overrides)
            else:
                submitted = client.train(preset=preset or "demo", overrides=overrides)
        elif kind == "sweep":
            if config is None and space is None:
                fail("give --space SPACE (a built-in search space) or --config SWEEP.json")
            target = read_json(config) if config is not None else space
            submitted = client.sweep(target, overrides=overrides)
        else:
            submitted = client.evaluate(job=job, policy=policy, episodes=episodes, seed=seed,
                                        env=overrides, split=split, deterministic=deterministic)  # fmt: skip
        console.print(f"submitted {submitted.kind} job {submitted.id} ({submitted.status})",
                      highlight=False)  # fmt: skip
        if follow:
            follow_job(submitted)


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


@app.command("show")
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
    if j.config:
        rows.append(("config", json.dumps(j.config)))
    rows.append(("request", json.dumps(j.request)))
    for key, value in rows:
        table.add_row(key, value)
    Console(width=max(console.width, 120)).print(table, markup=False, highlight=False)


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
    Console(width=max(console.width, 100)).print(table)


@app.command("download")
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
