"""Prometheus metrics through prometheus-client.

Two kinds:
- request metrics, counted in the process that answered (a counter and a latency histogram per
  route template, method and status); with several API processes (`quicknav serve --api-workers N`)
  they are shared through prometheus-client's multiprocess mode (PROMETHEUS_MULTIPROC_DIR, set by
  `serve`), so any process's /metrics shows the sum;
- the job system's state, read from the store at scrape time (the same in every process): jobs by
  status and kind, queue depth, busy workers, env steps/s of running jobs, seconds since each
  running job's last heartbeat, durations of finished jobs, and the announced gRPC Rollout
  servers' open streams and env steps served.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Histogram,
    generate_latest,
    multiprocess,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from quicknav_service.jobs.models import JobKind, JobStatus

__all__ = ["CONTENT_TYPE_LATEST", "observe_request", "render"]

MULTIPROC = bool(os.environ.get("PROMETHEUS_MULTIPROC_DIR"))
# in multiprocess mode the values live in files (written by every process); else in this registry
_REQUEST_REGISTRY = None if MULTIPROC else CollectorRegistry()
REQUESTS = Counter("quicknav_http_requests", "HTTP requests answered, by route template, method"
                   " and status.", ["route", "method", "status"], registry=_REQUEST_REGISTRY)  # fmt: skip
LATENCY = Histogram("quicknav_http_request_duration_seconds", "Time to answer (to the response"
                    " headers for streams), by route template and method.", ["route", "method"],
                    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0),
                    registry=_REQUEST_REGISTRY)  # fmt: skip
DURATION_BUCKETS = (1, 5, 15, 60, 300, 900, 3600, 4 * 3600, 12 * 3600, 48 * 3600)
FINISHED = (JobStatus.succeeded, JobStatus.failed, JobStatus.cancelled)


def observe_request(route: str, method: str, status: int, seconds: float) -> None:
    REQUESTS.labels(route, method, str(status)).inc()
    LATENCY.labels(route, method).observe(seconds)


class StoreCollector(Collector):
    """The job system's state, read from the store when scraped."""

    def __init__(self, store, settings, embedded_workers: int):
        self.store, self.settings, self.embedded_workers = store, settings, embedded_workers

    def collect(self) -> Iterator:
        store, now = self.store, time.time()
        counts = store.counts()
        jobs = GaugeMetricFamily("quicknav_jobs", "Jobs by status.", labels=["status"])
        for status, n in counts.items():
            jobs.add_metric([status], n)
        yield jobs
        by_kind = GaugeMetricFamily("quicknav_jobs_by_kind", "Jobs by kind and status.",
                                    labels=["kind", "status"])  # fmt: skip
        for kind, per_status in store.counts_by_kind().items():
            for status, n in per_status.items():
                by_kind.add_metric([kind, status], n)
        yield by_kind
        yield GaugeMetricFamily("quicknav_queue_depth", "Jobs waiting for a worker.",
                                value=counts.get("queued", 0))  # fmt: skip
        yield GaugeMetricFamily("quicknav_busy_workers", "Jobs being run by a worker.",
                                value=counts.get("running", 0))  # fmt: skip
        yield GaugeMetricFamily("quicknav_embedded_workers",
                                "Supervised worker processes of this API process.",
                                value=self.embedded_workers)  # fmt: skip
        running, _ = store.list(status=JobStatus.running, limit=500)
        steps = sum(float(j.metrics.get("steps_per_s", 0.0) or 0.0) for j in running)
        yield GaugeMetricFamily("quicknav_env_steps_per_second",
                                "Training throughput of running jobs, summed.", value=steps)  # fmt: skip
        beat = GaugeMetricFamily("quicknav_worker_heartbeat_age_seconds",
                                 "Seconds since the worker of a running job last renewed its lease"
                                 " (from the lease's end, taking this API's QUICKNAV_LEASE_S).",
                                 labels=["job", "worker"])  # fmt: skip
        for job in running:
            if job.lease_until is not None:
                last = job.lease_until - self.settings.lease_s
                beat.add_metric([job.id, job.worker or ""], max(0.0, now - last))
        yield beat
        hist = HistogramMetricFamily("quicknav_job_duration_seconds",
                                     "Run time of finished jobs (first start to end; the last 500"
                                     " of each status).", labels=["kind", "status"])  # fmt: skip
        for status in FINISHED:
            done, _ = store.list(status=status, limit=500)
            for kind in JobKind:
                secs = [j.finished_at - j.started_at for j in done
                        if j.kind == kind and j.started_at and j.finished_at]  # fmt: skip
                if not secs:
                    continue
                buckets = [(str(b), sum(s <= b for s in secs)) for b in DURATION_BUCKETS]
                buckets.append(("+Inf", len(secs)))
                hist.add_metric([kind.value, status.value], buckets, sum_value=sum(secs))
        yield hist
        streams = GaugeMetricFamily("quicknav_rollout_streams_open",
                                    "Open gRPC Rollout streams per announced server.",
                                    labels=["address", "worker"])  # fmt: skip
        served = CounterMetricFamily("quicknav_rollout_env_steps_served",
                                     "Env steps served over gRPC Rollout per announced server"
                                     " (since it started).", labels=["address", "worker"])  # fmt: skip
        held = GaugeMetricFamily("quicknav_rollout_memory_held_mb",
                                 "Memory the open gRPC Rollout streams hold together by their"
                                 " admission estimates, per announced server.",
                                 labels=["address", "worker"])  # fmt: skip
        budget = GaugeMetricFamily("quicknav_rollout_memory_budget_mb",
                                   "Memory the open gRPC Rollout streams may hold together"
                                   " (QUICKNAV_ROLLOUT_MEMORY_MB), per announced server.",
                                   labels=["address", "worker"])  # fmt: skip
        for e in store.endpoints():
            where = [e["address"], e["worker"]]
            streams.add_metric(where, e.get("sessions", 0))
            served.add_metric(where, e.get("env_steps_served", 0))
            if "memory_held_mb" in e:
                held.add_metric(where, e["memory_held_mb"])
            if e.get("memory_budget_mb") is not None:
                budget.add_metric(where, e["memory_budget_mb"])
        yield streams
        yield served
        yield held
        yield budget


def render(store, settings, embedded_workers: int) -> bytes:
    """The metrics page: request metrics (all API processes) and the store's state."""
    registry = CollectorRegistry()
    if MULTIPROC:
        multiprocess.MultiProcessCollector(registry)
    else:
        for collector in (REQUESTS, LATENCY):
            registry.register(collector)
    registry.register(StoreCollector(store, settings, embedded_workers))
    return generate_latest(registry)


class RequestMetrics:
    """ASGI middleware: counts each HTTP request and times it to its response headers, labelled
    with the matched route's template (``/jobs/{job_id}``, so ids do not explode the label set)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        seen = {"done": False}

        def observe(status: int) -> None:
            if not seen["done"]:
                seen["done"] = True
                route = getattr(scope.get("route"), "path", None) or "unmatched"
                observe_request(route, scope["method"], status, time.perf_counter() - t0)

        async def send_observed(message):
            if message["type"] == "http.response.start":
                observe(message["status"])
            await send(message)

        try:
            await self.app(scope, receive, send_observed)
        finally:
            observe(500)  # no response started: the app failed
