"""Service benchmark against the Redis store on this machine (run: uv run python benchmarks/service.py).

1. Job submissions accepted per second with concurrent HTTP clients (target >= 1,000/s), and the p99
   latency of GET /jobs/{id} under that load (target < 20 ms). The API runs as `quicknav serve
   --no-worker --api-workers 2` (QUICKNAV_BENCH_API_WORKERS); the load comes from `wrk` (C, one
   thread: 16 connections POSTing, 1 connection GETting) when it is installed (`apt-get install
   wrk`), else from an httpx client in this process, which needs a core of its own. Clients and
   server share the same 2 cores. Every accepted submission is checked to exist in Redis.
2. Progress-event latency, worker -> SSE client: a worker publishes timestamped events into the
   store, a client follows /jobs/{id}/events (target p50 < 50 ms).
3. Time to first progress of a repeated train job on a warm worker vs a cold one (target >= 5x).
Writes benchmarks/results/service.json. Uses Redis DB 12 (flushed before and after).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

# this file is named like the `service` package: keep its folder off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import httpx  # noqa: E402
import redis  # noqa: E402

REDIS_URL = os.environ.get("QUICKNAV_BENCH_REDIS", "redis://127.0.0.1:6379/12")
PORT = 8765
URL = f"http://127.0.0.1:{PORT}"


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q / 100 * len(xs)))]


async def submissions(n_requests: int, concurrency: int) -> dict:
    body = {"policy": "random", "episodes": 1}
    lat_get: list[float] = []
    ids: list[str] = []
    done = 0

    async with httpx.AsyncClient(
        base_url=URL, timeout=30, limits=httpx.Limits(max_connections=concurrency * 2)
    ) as c:
        first = (await c.post("/jobs/eval", json=body)).json()["id"]

        async def submitter():
            nonlocal done
            while done < n_requests:
                done += 1
                r = await c.post("/jobs/eval", json=body)
                assert r.status_code == 202, r.text
                ids.append(r.json()["id"])

        async def getter(stop: asyncio.Event):
            while not stop.is_set():
                t0 = time.perf_counter()
                r = await c.get(f"/jobs/{first}")
                lat_get.append(time.perf_counter() - t0)
                assert r.status_code == 200

        stop = asyncio.Event()
        getters = [asyncio.create_task(getter(stop)) for _ in range(2)]
        t0 = time.perf_counter()
        await asyncio.gather(*[submitter() for _ in range(concurrency)])
        wall = time.perf_counter() - t0
        stop.set()
        await asyncio.gather(*getters)
    return {
        "requests": len(ids), "concurrency": concurrency, "wall_s": round(wall, 3),
        "submissions_per_s": round(len(ids) / wall, 1),
        "get_p50_ms": round(1000 * pct(lat_get, 50), 2), "get_p99_ms": round(1000 * pct(lat_get, 99), 2),
        "gets_measured": len(lat_get),
    }  # fmt: skip


def _wrk_latency_ms(text: str, q: str) -> float:
    """A percentile from wrk's --latency table, in ms."""
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0] == q:
            v = parts[1]
            for unit, f in (("us", 1e-3), ("ms", 1.0), ("s", 1e3)):
                if v.endswith(unit):
                    return round(float(v[: -len(unit)]) * f, 3)
    raise ValueError(f"no {q} line in wrk output:\n{text}")


def _wrk_rate(text: str) -> float:
    return float(next(x for x in text.splitlines() if x.startswith("Requests/sec:")).split()[1])


def submissions_wrk(seconds: int, concurrency: int) -> dict:
    """wrk POSTs eval jobs on `concurrency` connections while a second wrk times GET /jobs/{id}."""
    first = httpx.post(f"{URL}/jobs/eval", json={"policy": "random", "episodes": 1}).json()["id"]
    lua = Path(tempfile.mkdtemp()) / "post.lua"
    lua.write_text('wrk.method = "POST"\nwrk.body = \'{"policy": "random", "episodes": 1}\'\n'
                   'wrk.headers["Content-Type"] = "application/json"\n')  # fmt: skip
    post = subprocess.Popen(["wrk", "-t1", f"-c{concurrency}", f"-d{seconds}s", "-s", str(lua),
                             f"{URL}/jobs/eval"], stdout=subprocess.PIPE, text=True)  # fmt: skip
    time.sleep(0.5)
    get = subprocess.run(["wrk", "-t1", "-c1", f"-d{seconds - 1}s", "--latency", f"{URL}/jobs/{first}"],
                         capture_output=True, text=True, check=True)  # fmt: skip
    post_out = post.communicate()[0]
    if "Non-2xx" in post_out or "Non-2xx" in get.stdout:
        raise RuntimeError(f"wrk saw error responses:\n{post_out}\n{get.stdout}")
    return {
        "load_generator": f"wrk, 1 thread, {concurrency} POST connections + 1 GET connection",
        "concurrency": concurrency, "seconds": seconds,
        "submissions_per_s": round(_wrk_rate(post_out), 1),
        "get_per_s": round(_wrk_rate(get.stdout), 1),
        "get_p50_ms": _wrk_latency_ms(get.stdout, "50%"),
        "get_p99_ms": _wrk_latency_ms(get.stdout, "99%"),
    }  # fmt: skip


def sse_latency(store, n_events: int = 200) -> dict:
    from quicknav_core.config import resolve_eval

    request = {"policy": "random", "episodes": 1, "seed": 0}
    job, _ = store.submit("eval", request, resolve_eval(request).model_dump(mode="json"))
    received: list[float] = []
    ready = threading.Event()

    def client():
        with httpx.stream("GET", f"{URL}/jobs/{job.id}/events", timeout=60) as r:
            ready.set()
            for line in r.iter_lines():
                if line.startswith("data: "):
                    ev = json.loads(line[6:])
                    if "sent" in ev:
                        received.append(time.time() - ev["sent"])
                    if ev.get("type") == "done-bench":
                        return

    t = threading.Thread(target=client, daemon=True)
    t.start()
    ready.wait(10)
    time.sleep(0.3)
    for i in range(n_events):
        store.publish(job.id, {"type": "progress", "i": i, "sent": time.time()})
        time.sleep(0.01)
    store.publish(job.id, {"type": "done-bench", "sent": time.time()})
    t.join(30)
    return {"events": len(received), "p50_ms": round(1000 * statistics.median(received), 2),
            "p99_ms": round(1000 * pct(received, 99), 2)}  # fmt: skip


def warm_vs_cold(data_dir: Path) -> dict:
    """Time from claim to first progress for the same train job, twice, in one worker."""
    from quicknav_core.config import resolve_train
    from quicknav_service.jobs.sqlite_store import SQLiteJobStore
    from quicknav_service.settings import Settings
    from quicknav_service.worker import Worker

    settings = Settings(data_dir=data_dir, embedded_worker=False)
    store = SQLiteJobStore(data_dir / "jobs.db")
    worker = Worker(store, settings, worker_id="bench")
    from quicknav_service.worker import _enable_jax_cache

    _enable_jax_cache(settings)
    request = {"preset": "demo", "overrides": {"total_steps": 65536, "chunk_steps": 32768}}
    cfg = resolve_train(request)
    times = []
    for _ in range(2):
        job, _ = store.submit("train", request, cfg.model_dump(mode="json"))
        assert worker.run_once()
        events = store.events(job.id)
        started = next(e["time"] for _, e in events if e["type"] == "started")
        first = next(e["time"] for _, e in events if e["type"] == "progress")
        times.append(first - started)
        assert store.get(job.id).status.value == "succeeded"
    return {
        "cold_s": round(times[0], 3),
        "warm_s": round(times[1], 3),
        "speedup": round(times[0] / times[1], 1),
    }


def main() -> None:
    from quicknav_service.jobs.redis_store import RedisJobStore

    r = redis.Redis.from_url(REDIS_URL)
    r.flushdb()
    tmp = Path(tempfile.mkdtemp(prefix="quicknav-bench-"))
    env = {**os.environ, "QUICKNAV_REDIS_URL": REDIS_URL, "QUICKNAV_DATA_DIR": str(tmp / "api"),
           "QUICKNAV_PORT": str(PORT)}  # fmt: skip
    api_workers = os.environ.get("QUICKNAV_BENCH_API_WORKERS", "2")
    server = subprocess.Popen([sys.executable, "-m", "quicknav_cli", "serve", "--no-worker", "--no-grpc",
                               "--api-workers", api_workers], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    results: dict = {}
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                if httpx.get(f"{URL}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        asyncio.run(submissions(200, 16))  # warm-up
        if shutil.which("wrk"):
            results["submissions"] = submissions_wrk(10, 16)
        else:
            print("wrk not found: the load comes from httpx in this process", flush=True)
            results["submissions"] = asyncio.run(submissions(3000, 32))
            results["submissions"]["load_generator"] = (
                "httpx.AsyncClient, 32 submitters + 2 getters"
            )
        results["submissions"]["api_workers"] = int(api_workers)
        # every accepted submission is a job record and a queue entry
        stored = r.zcard("quicknav:jobs")
        results["submissions"]["jobs_in_redis"] = stored
        print("submissions:", results["submissions"], flush=True)
        results["sse_latency"] = sse_latency(RedisJobStore(REDIS_URL))
        print("sse latency:", results["sse_latency"], flush=True)
    finally:
        server.terminate()
        server.wait(30)
        r.flushdb()
    results["warm_vs_cold"] = warm_vs_cold(tmp / "worker")
    print("warm vs cold:", results["warm_vs_cold"], flush=True)
    from quicknav_core.bench.machine import machine_info

    results["machine"] = machine_info()
    results["targets"] = {
        "submissions_per_s >= 1000": results["submissions"]["submissions_per_s"] >= 1000,
        "GET p99 < 20 ms": results["submissions"]["get_p99_ms"] < 20,
        "SSE p50 < 50 ms": results["sse_latency"]["p50_ms"] < 50,
        "warm >= 5x faster to first progress": results["warm_vs_cold"]["speedup"] >= 5,
    }
    path = Path(__file__).parent / "results" / "service.json"
    path.write_text(json.dumps(results, indent=2))
    print(json.dumps(results["targets"], indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
