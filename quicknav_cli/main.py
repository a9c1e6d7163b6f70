"""The `quicknav` command: the front door of every feature, one module per group.

    env       quicknav env demo | rooms                     (env.py)
    train     quicknav train, quicknav presets              (train.py)
    eval      quicknav eval                                 (eval.py)
    sweep     quicknav sweep                                (sweep.py)
    bench     quicknav bench [train | learning]             (bench.py)
    serve     quicknav serve | worker | rollout-server      (serve.py, needs the service extra)
    jobs      quicknav jobs submit | list | show | ...      (jobs.py, talks to a service via the SDK)

Every command that builds a config sends a request through ``quicknav_core.config.resolve``, the
same function the service calls, so a flag means the same thing here and in a job.
"""

from __future__ import annotations

import typer

from quicknav_cli import bench, env, jobs, serve, sweep, train
from quicknav_cli import eval as eval_

app = typer.Typer(
    name="quicknav",
    help="QuickNav: room navigation for reinforcement learning in pure JAX.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
app.add_typer(env.app, name="env")
app.command("train")(train.train)
app.command("presets")(train.presets)
app.command("eval")(eval_.eval_cmd)
app.command("sweep")(sweep.sweep)
app.add_typer(bench.app, name="bench")
app.command("serve")(serve.serve)
app.command("worker")(serve.worker)
app.command("rollout-server")(serve.rollout_server)
app.add_typer(jobs.app, name="jobs")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
