"""The job queue when it is large and watched: the API over a Redis store holding many jobs.

For one code tree (default: this checkout; `--tree DIR` another, e.g. a `git worktree` of an older
commit, run with this checkout's environment), on Redis DB 11 (flushed before and after):

1. fills the store with `--jobs` jobs through the tree's own `RedisJobStore.submit` (train, eval
   and sweep jobs; 2 % of them run and finished);
2. starts the tree's API (`quicknav serve --no-worker --no-grpc`, one process) and measures
   `GET /jobs` (a page of 50, `?limit=1`, a status-and-kind filter) p50/p99, a `/metrics`
   scrape, `/healthz` p50/p99 while four clients list jobs without pause and an eval of a train
   job with a 448 MiB checkpoint is submitted (its hash is checked then), and the API process's
   CPU (% of one core, from /proc) while 500 SSE viewers follow one running job and nothing
   happens, the viewers held by a separate process;
3. reports the API's resident memory at the end.

    uv run python benchmarks/queue_scale.py [--jobs 100000] [--tree DIR] [--label after]

Prints the figures and merges them under `--label` into benchmarks/results/queue.json, which
holds a before and an after taken in one sitting (run it for both trees, back to back).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
import redis  # noqa: E402

REDIS_URL = os.environ.get("QUICKNAV_BENCH_REDIS", "redis://127.0.0.1:6379/11")

FILL = """
import sys, time
from quicknav_service.jobs.redis_store import RedisJobStore
n, url = int(sys.argv[1]), sys.argv[2]
store = RedisJobStore(url)
t0 = time.time()
kinds = ["train"] * 12 + ["eval"] * 7 + ["sweep"]
for i in range(n):
    job, _ = store.submit(kinds[i % len(kinds)], {"i": i}, {"n": i})
    if i % 50 == 0:
        taken = store.claim("filler", 3600)
        if taken is not None:
            store.publish(taken.id, {"type": "progress", "progress": 1.0})
            store.finish(taken.id, "filler", "succeeded", result={})
print(round(time.time() - t0, 1))
"""

TRAINED = """
import hashlib, json, os, sys, time
from pathlib import Path
from quicknav_core.config import get_preset
from quicknav_core.train.run import CHECKPOINT_DIR, META_FILE, STATE_FILE
from quicknav_service.jobs.models import JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
url, data, mb = sys.argv[1], Path(sys.argv[2]), int(sys.argv[3])
store = RedisJobStore(url)
cfg = get_preset("demo").model_dump(mode="json")
job, _ = store.submit("train", {"preset": "demo"}, cfg)
def done(j, pipe):
    j.status = JobStatus.succeeded
    j.finished_at = time.time()
store._update(job.id, done)
folder = data / "artifacts" / job.id / CHECKPOINT_DIR
folder.mkdir(parents=True)
h, size = hashlib.sha256(), 0
with open(folder / STATE_FILE, "wb") as f:
    for _ in range(mb):
        block = os.urandom(2**20)
        h.update(block)
        f.write(block)
        size += len(block)
(folder / META_FILE).write_text(json.dumps({"chunk": 1, "env_steps": 1, "state_bytes": size,
                                            "state_sha256": h.hexdigest()}))
print(job.id)
"""

LISTERS = """
import sys, threading, httpx
url, n = sys.argv[1], int(sys.argv[2])
def lister():
    with httpx.Client(base_url=url, timeout=300) as c:
        while True:
            c.get("/jobs?limit=50")
threads = [threading.Thread(target=lister, daemon=True) for _ in range(n)]
for t in threads:
    t.start()
threading.Event().wait()
"""

VIEWERS = """
import asyncio, sys, httpx
url, job, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
async def view(client):
    async with client.stream("GET", f"{url}/jobs/{job}/events") as r:
        async for _ in r.aiter_lines():
            pass
async def main():
    limits = httpx.Limits(max_connections=n + 10, max_keepalive_connections=n + 10)
    async with httpx.AsyncClient(timeout=None, limits=limits) as client:
        tasks = [asyncio.create_task(view(client)) for _ in range(n)]
        await asyncio.sleep(1e9)
asyncio.run(main())
"""


def pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q / 100 * len(xs)))]


def timed(client: httpx.Client, path: str, n: int) -> dict:
    lat = []
    for _ in range(n):
        t = time.perf_counter()
        r = client.get(path)
        lat.append(time.perf_counter() - t)
        r.raise_for_status()
    return {"n": n, "p50_ms": round(1000 * pct(lat, 50), 2), "p99_ms": round(1000 * pct(lat, 99), 2),
            "max_ms": round(1000 * max(lat), 2)}  # fmt: skip


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=100_000)
    ap.add_argument("--tree", type=Path, default=ROOT)
    ap.add_argument("--label", default="after")
    ap.add_argument("--samples", type=int, default=30)
    ap.add_argument("--viewers", type=int, default=500)
    ap.add_argument("--port", type=int, default=8791)
    ap.add_argument("--checkpoint-mb", type=int, default=448,
                    help="size of the trained job's checkpoint an eval is submitted for")
    ap.add_argument("--lister-nice", type=int, default=0,
                    help="niceness of the listing clients' process (they share the 2 cores)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "queue.json")
    args = ap.parse_args()
    tree = args.tree.resolve()
    env = {**os.environ, "PYTHONPATH": str(tree), "QUICKNAV_REDIS_URL": REDIS_URL,
           "QUICKNAV_SSE_MAX_TOTAL": str(args.viewers + 50),
           "QUICKNAV_SSE_MAX_PER_CLIENT": str(args.viewers + 50)}  # fmt: skip
    db = redis.Redis.from_url(REDIS_URL)
    db.flushdb()
    out: dict = {"jobs": args.jobs, "tree": str(tree),
                 "commit": subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
                                          capture_output=True, text=True).stdout.strip()}  # fmt: skip
    fill = subprocess.run([sys.executable, "-c", FILL, str(args.jobs), REDIS_URL], env=env,
                          capture_output=True, text=True, check=True)  # fmt: skip
    out["fill_s"] = float(fill.stdout.strip())
    print(f"[{args.label}] filled {args.jobs:,} jobs in {out['fill_s']} s", flush=True)
    data = tempfile.mkdtemp(prefix="quicknav-queue-bench-")
    api = subprocess.Popen(
        [sys.executable, "-c", "from quicknav_cli.main import app; app()", "serve", "--no-worker",
         "--no-grpc", "--port", str(args.port)],
        env={**env, "QUICKNAV_DATA_DIR": data}, cwd=data,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    url = f"http://127.0.0.1:{args.port}"
    viewers = None
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        client = httpx.Client(base_url=url, timeout=120)
        client.get("/jobs?limit=1").raise_for_status()  # first request: imports, connections
        slow = max(3, args.samples // 3)
        out["list_page_50"] = timed(client, "/jobs?limit=50", args.samples)
        out["list_limit_1"] = timed(client, "/jobs?limit=1", args.samples)
        out["list_status_kind"] = timed(client, "/jobs?status=succeeded&kind=eval&limit=50", args.samples)
        out["metrics_scrape"] = timed(client, "/metrics", slow)
        print(f"[{args.label}] list {out['list_page_50']}, metrics {out['metrics_scrape']}", flush=True)

        # /healthz while four clients (another process) list without pause, and an eval of a
        # train job with a large checkpoint (its hash checked at submission) is submitted
        trained = subprocess.run([sys.executable, "-c", TRAINED, REDIS_URL, data,
                                  str(args.checkpoint_mb)], env=env, capture_output=True, text=True,
                                 check=True).stdout.strip()  # fmt: skip
        listers = subprocess.Popen(["nice", "-n", str(args.lister_nice), sys.executable, "-c", LISTERS, url, "4"], env=env,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        time.sleep(1.0)
        health, end, submitted = [], time.time() + 10, {}

        def submit_eval():
            time.sleep(3)
            t0 = time.perf_counter()
            r = httpx.post(f"{url}/jobs/eval", json={"job_id": trained, "episodes": 1}, timeout=120)
            submitted.update(status=r.status_code, seconds=round(time.perf_counter() - t0, 3))

        submitter = threading.Thread(target=submit_eval)
        submitter.start()
        while time.time() < end:
            t0 = time.perf_counter()
            client.get("/healthz").raise_for_status()
            health.append(time.perf_counter() - t0)
            time.sleep(0.02)
        submitter.join()
        listers.kill()
        listers.wait()
        out["healthz_under_listing"] = {"n": len(health), "p50_ms": round(1000 * pct(health, 50), 2),
                                        "p99_ms": round(1000 * pct(health, 99), 2),
                                        "max_ms": round(1000 * max(health), 2),
                                        "eval_submission": {"checkpoint_mb": args.checkpoint_mb,
                                                            **submitted}}  # fmt: skip
        print(f"[{args.label}] healthz with 4 listers {out['healthz_under_listing']}", flush=True)

        # idle SSE viewers of one running job
        job = client.post("/jobs/eval", json={"policy": "random", "episodes": 1}).json()["id"]
        db2 = redis.Redis.from_url(REDIS_URL)
        viewers = subprocess.Popen([sys.executable, "-c", VIEWERS, url, job, str(args.viewers)],
                                   env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        time.sleep(8)  # connect them all
        c0, t0 = cpu_seconds(api.pid), time.time()
        time.sleep(20)
        share = (cpu_seconds(api.pid) - c0) / (time.time() - t0)
        out["sse_idle_viewers"] = {"viewers": args.viewers, "api_cpu_percent_of_core": round(100 * share, 1)}
        out["api_rss_mb"] = round(rss_mb(api.pid), 1)
        del db2
        print(f"[{args.label}] {args.viewers} idle viewers: {out['sse_idle_viewers']}, RSS"
              f" {out['api_rss_mb']} MB", flush=True)  # fmt: skip
    finally:
        if viewers is not None:
            viewers.kill()
        api.terminate()
        api.wait(30)
        db.flushdb()
    from quicknav_core.bench.machine import machine_line

    out["machine"] = machine_line()
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    results[args.label] = out
    args.out.write_text(json.dumps(results, indent=1))
    print(json.dumps(out, indent=1))
    print(f"wrote {args.out} [{args.label}]")


if __name__ == "__main__":
    main()
