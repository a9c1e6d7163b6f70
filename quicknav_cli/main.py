"""The `quicknav` command: the front door of every feature, one module per group.

    env       quicknav env demo | rooms                     (env.py)
    train     quicknav train, quicknav presets              (train.py)
    eval      quicknav eval                                 (eval.py)
    sweep     quicknav sweep                                (sweep.py)
    bench     quicknav bench [train | learning]             (bench.py)
    serve     quicknav serve | worker | rollout-server      (serve.py, needs the service extra)
    jobs      quicknav jobs submit | list | show | ...      (jobs.py, talks to a service via the SDK)
    maps      quicknav maps upload | list | show | delete   (maps.py, the same)

Every command that builds a config sends a request through ``quicknav_core.config.resolve``, the
same function the service calls, so a flag means the same thing here and in a job.
"""

from __future__ import annotations

from typing import Annotated

import typer
from typer.core import TyperGroup

from quicknav_cli import bench, env, export, jobs, maps, serve, sweep, train
from quicknav_cli import eval as eval_
from quicknav_cli.common import fail


def version() -> str:
    """QuickNav's version, from the installed package's metadata (one source)."""
    import quicknav_core

    found = getattr(quicknav_core, "__version__", None)
    if found is None:  # a quicknav_core without the attribute: ask the metadata directly
        from importlib.metadata import version as package_version

        found = package_version("quicknav")
    return found


def _print_version(value: bool) -> None:
    if value:
        print(f"quicknav {version()}")
        raise typer.Exit()


def _space_separated_set(args: list[str]) -> str | None:
    """``--set key value`` (a space where ``=`` belongs) in the command line, as a message."""
    for i, arg in enumerate(args[:-1]):
        key = args[i + 1]
        if arg == "--set" and "=" not in key and not key.startswith("-"):
            given = args[i + 2] if i + 2 < len(args) else "-"
            value = "VALUE" if given.startswith("-") else given
            return (f"--set {key}: expected key=value with no space around '=', e.g."
                    f" --set {key}={value}")  # fmt: skip
    return None


class QuickNavGroup(TyperGroup):
    """The root command: reads the whole command line before any subcommand parses it."""

    def parse_args(self, ctx, args: list[str]) -> list[str]:
        # `--set k v` would otherwise end in click's "unexpected extra argument (v)", which does
        # not say what to write instead
        message = _space_separated_set(args)
        if message:
            fail(message)
        return super().parse_args(ctx, args)


app = typer.Typer(
    name="quicknav",
    help="QuickNav: room navigation for reinforcement learning in pure JAX.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    cls=QuickNavGroup,
)


@app.callback()
def root(
    show_version: Annotated[
        bool,
        typer.Option("--version", callback=_print_version, is_eager=True,
                     help="Print QuickNav's version and exit."),
    ] = False,
) -> None:
    """QuickNav: room navigation for reinforcement learning in pure JAX."""


app.add_typer(env.app, name="env")
app.command("train")(train.train)
app.command("presets")(train.presets)
app.command("eval")(eval_.eval_cmd)
app.command("export")(export.export_cmd)
app.command("sweep")(sweep.sweep)
app.add_typer(bench.app, name="bench")
app.command("serve")(serve.serve)
app.command("worker")(serve.worker)
app.command("rollout-server")(serve.rollout_server)
app.add_typer(jobs.app, name="jobs")
app.add_typer(maps.app, name="maps")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
