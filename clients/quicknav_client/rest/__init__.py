"""REST client of the QuickNav job service: submit train/sweep/eval jobs, follow them, fetch results.

    from quicknav_client import QuickNavClient

    with QuickNavClient("http://127.0.0.1:8000") as qn:
        job = qn.train(preset="demo", overrides={"env.grid_size": 8}, total_steps=200_000)
        job.wait(progress=True)
        print(job.status, job.result, job.config)
        job.download("learning_curve.png", "curve.png")

    core.py   the sans-IO core: request bodies, retries, event streams, downloads (no waiting)
    sync.py   QuickNavClient, Job: the core run with httpx.Client
    aio.py    AsyncQuickNavClient, AsyncJob: the core run with httpx.AsyncClient

Requests go to the service as given; the service resolves them (``quicknav_core.config.resolve``)
and a job shows both: ``job.request`` as sent, ``job.config`` as resolved.
"""

from quicknav_client.rest.aio import AsyncJob, AsyncQuickNavClient
from quicknav_client.rest.core import (
    JobList,
    SSEParser,
    eval_body,
    metrics_summary,
    raise_for_status,
    sweep_body,
    train_body,
)
from quicknav_client.rest.sync import Job, QuickNavClient

__all__ = [
    "AsyncJob",
    "AsyncQuickNavClient",
    "Job",
    "JobList",
    "QuickNavClient",
    "SSEParser",
    "eval_body",
    "metrics_summary",
    "raise_for_status",
    "sweep_body",
    "train_body",
]
