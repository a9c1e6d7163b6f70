"""Chaos benchmark: does every accepted job end while workers and Redis are killed under it?

    uv run python benchmarks/chaos.py [--jobs 30] [--workers 3] [--chaos-s 120] [--seed 0]

Starts its own redis-server (append-only file, fsync always) on a free port, the API as
`quicknav serve --no-worker` on the Redis store and several `quicknav worker` processes. It submits
small train and eval jobs through the REST API while a fault loop, for --chaos-s seconds, either
SIGKILLs a random worker (restarted a second later, as a process supervisor would) or kill -9s the
Redis server and restarts it after a few seconds; some jobs are cancelled on the way. A submission
that meets the outage (503 or no answer) is retried with the same Idempotency-Key. Then the faults
stop and every accepted job gets --settle-s seconds to end.

Printed and written to benchmarks/results/chaos.json: jobs accepted, faults by kind, outcomes,
lost (accepted but no record), stuck (not ended by the deadline), duplicated (a retried submission
that made two jobs), train runs whose metrics log is not chunks 1..n exactly once, workers that
exited on their own, and recovery times (Redis back -> API answers again; worker killed -> its job
running again elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this folder holds service.py, named like the `service` package: keep it off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402

from tests.service.faults import RedisServer, free_port  # noqa: E402

TINY = {"env.grid_size": 8, "env.train_rooms": 32, "env.test_rooms": 16, "env.max_steps": 60,
        "num_envs": 16, "algorithm.num_steps": 32, "algorithm.num_minibatches": 4,
        "chunk_steps": 512}  # fmt: skip
TERMINAL = {"succeeded", "failed", "cancelled"}


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


class Cluster:
    def __init__(self, folder: Path, n_workers: int):
        self.folder = folder
        self.redis = RedisServer(folder / "redis")
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {
            **os.environ,
            "QUICKNAV_REDIS_URL": "",  # set in start(), once the port is known
            "QUICKNAV_DATA_DIR": str(folder / "data"),
            "QUICKNAV_LEASE_S": "6", "QUICKNAV_HEARTBEAT_S": "1",
            "QUICKNAV_MAX_ATTEMPTS": "20",  # a job may be killed many times here; count losses, not give-ups
            "QUICKNAV_MAX_CHUNK_S": "2",
            "PYTHONUNBUFFERED": "1",
        }  # fmt: skip
        self.n_workers = n_workers
        self.workers: list[subprocess.Popen | None] = [None] * n_workers
        self.killed_by_us: set[int] = set()
        self.api: subprocess.Popen | None = None

    def _spawn(self, args: list[str], name: str) -> subprocess.Popen:
        with open(self.folder / f"{name}.log", "ab") as out:  # the child keeps its own handle
            return subprocess.Popen([sys.executable, "-m", "quicknav_cli", *args], env=self.env,
                                    stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)  # fmt: skip

    def start(self) -> None:
        self.redis.start()
        self.env["QUICKNAV_REDIS_URL"] = self.redis.url
        self.api = self._spawn(
            ["serve", "--no-worker", "--no-grpc", "--port", str(self.port)], "api"
        )
        for i in range(self.n_workers):
            self.workers[i] = self._spawn(["worker"], f"worker{i}")
        deadline = time.time() + 120
        while time.time() < deadline:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        raise RuntimeError(f"the API did not come up; see {self.folder / 'api.log'}")

    def kill_worker(self, i: int) -> None:
        proc = self.workers[i]
        if proc is not None and proc.poll() is None:
            self.killed_by_us.add(proc.pid)
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)

    def restart_worker(self, i: int) -> None:
        self.workers[i] = self._spawn(["worker"], f"worker{i}")

    def self_exits(self) -> list[int]:
        """pids of workers that ended without being killed by us."""
        return [p.pid for p in self.workers
                if p is not None and p.poll() is not None and p.pid not in self.killed_by_us]  # fmt: skip

    def stop(self) -> None:
        for p in [*self.workers, self.api]:
            if p is not None and p.poll() is None:
                p.terminate()
        for p in [*self.workers, self.api]:
            if p is not None:
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
        self.redis.kill()


def post_retrying(client: httpx.Client, path: str, body: dict, stats: Counter) -> dict:
    """POST with one Idempotency-Key until the API accepts it (503s and dropped connections are
    what an outage looks like from outside)."""
    key = uuid.uuid4().hex
    for attempt in range(600):
        try:
            r = client.post(path, json=body, headers={"Idempotency-Key": key})
        except httpx.HTTPError:
            stats["no answer"] += 1
            time.sleep(0.5)
            continue
        if r.status_code == 503:
            stats["503"] += 1
            assert "retry-after" in r.headers, "a 503 without Retry-After"
            time.sleep(min(float(r.headers["retry-after"]), 2.0))
            continue
        if r.status_code in (200, 201, 202):
            if attempt:
                stats["accepted after a retry"] += 1
            return r.json()
        raise RuntimeError(f"{path} answered {r.status_code}: {r.text}")
    raise RuntimeError(f"{path}: gave up after 600 tries")


def get_json(client: httpx.Client, path: str) -> dict | None:
    try:
        r = client.get(path)
    except httpx.HTTPError:
        return None
    return r.json() if r.status_code == 200 else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--jobs", type=int, default=30)
    ap.add_argument("--workers", type=int, default=3)
    ap.add_argument("--chaos-s", type=float, default=120.0)
    ap.add_argument("--settle-s", type=float, default=300.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/chaos.json")
    args = ap.parse_args()
    rng = random.Random(args.seed)

    folder = Path(tempfile.mkdtemp(prefix="quicknav-chaos-"))
    cluster = Cluster(folder, args.workers)
    log(
        f"cluster in {folder}: redis {cluster.redis.url}, api {cluster.url}, {args.workers} workers"
    )
    t_start = time.time()
    cluster.start()
    client = httpx.Client(base_url=cluster.url, timeout=10)
    submit_stats: Counter = Counter()
    faults: Counter = Counter()
    redis_recovery: list[float] = []
    redis_down_s = 0.0
    accepted: dict[str, str] = {}  # id -> kind
    cancel_asked: set[str] = set()
    stop_faults = threading.Event()
    worker_kills: list[tuple[float, str | None]] = []  # (time, job the worker held)

    def held_jobs() -> dict[int, str]:
        """worker index -> the job it runs now."""
        page = get_json(client, "/jobs?status=running&limit=500")
        out = {}
        for job in (page or {}).get("data", []):
            for i, proc in enumerate(cluster.workers):
                if proc is not None and f"-{proc.pid}-" in (job.get("worker") or ""):
                    out[i] = job["id"]
        return out

    def fault_loop() -> None:
        nonlocal redis_down_s
        t_end = time.time() + args.chaos_s
        while time.time() < t_end and not stop_faults.is_set():
            time.sleep(rng.uniform(4.0, 9.0))
            if rng.random() < 0.6:
                held_by = held_jobs()  # mostly a busy worker: that is where a kill costs work
                busy = sorted(held_by)
                i = rng.choice(busy) if busy and rng.random() < 0.8 else rng.randrange(args.workers)
                held = held_by.get(i)
                cluster.kill_worker(i)
                faults["worker SIGKILL"] += 1
                worker_kills.append((time.time(), held))
                log(f"SIGKILL worker {i}" + (f" (running job {held[:8]})" if held else " (idle)"))
                time.sleep(1.0)
                cluster.restart_worker(i)
            else:
                down = rng.uniform(2.0, 6.0)
                cluster.redis.kill()
                faults["redis kill -9"] += 1
                log(f"kill -9 redis for {down:.1f} s")
                time.sleep(down)
                cluster.redis.start()
                t_back = time.time()
                redis_down_s += down
                while time.time() - t_back < 60:
                    if get_json(client, "/jobs?limit=1") is not None:
                        redis_recovery.append(time.time() - t_back)
                        break
                    time.sleep(0.1)

    chaos = threading.Thread(target=fault_loop, daemon=True)
    chaos.start()
    submit_every = args.chaos_s * 0.7 / max(args.jobs, 1)
    for n in range(args.jobs):
        if n % 3 == 2:
            body = {"policy": "random", "episodes": 64, "env": {"grid_size": 8, "max_steps": 60}}
            job = post_retrying(client, "/jobs/eval", body, submit_stats)
        else:
            steps = 512 * rng.randint(150, 450)
            body = {"preset": "demo", "overrides": {**TINY, "total_steps": steps}}
            job = post_retrying(client, "/jobs/train", body, submit_stats)
        accepted[job["id"]] = job["kind"]
        if rng.random() < 0.1:
            cancel_asked.add(job["id"])
        time.sleep(submit_every)
        for jid in list(cancel_asked):  # cancel the chosen ones once they run (or at once, queued)
            rec = get_json(client, f"/jobs/{jid}")
            if rec and rec["status"] in ("running", "queued") and rng.random() < 0.5:
                try:
                    client.post(f"/jobs/{jid}/cancel", json={})
                except httpx.HTTPError:
                    pass
    chaos.join()
    t_chaos_end = time.time()
    log(f"faults over ({dict(faults)}); {len(accepted)} jobs accepted; waiting for them to end")
    for jid in cancel_asked:
        try:
            client.post(f"/jobs/{jid}/cancel", json={})
        except httpx.HTTPError:
            pass

    # every accepted job must end
    deadline = time.time() + args.settle_s
    final: dict[str, dict] = {}
    while time.time() < deadline:
        for jid in accepted:
            if jid not in final or final[jid]["status"] not in TERMINAL:
                rec = get_json(client, f"/jobs/{jid}")
                if rec is not None:
                    final[jid] = rec
        if all(jid in final and final[jid]["status"] in TERMINAL for jid in accepted):
            break
        time.sleep(1.0)
    t_settled = time.time()

    page = get_json(client, "/jobs?limit=500") or {"data": [], "count": -1}
    lost = [j for j in accepted if j not in final]
    stuck = [j for j in accepted if j in final and final[j]["status"] not in TERMINAL]
    duplicated = page["count"] - len(accepted)
    outcomes = Counter(final[j]["status"] for j in final)
    reasons = Counter(
        (final[j].get("error") or "")[:80] for j in final if final[j]["status"] == "failed"
    )

    # a train run's metrics log: chunks 1..n, each once (a resume drops lines after its checkpoint)
    bad_logs = []
    for jid, kind in accepted.items():
        mfile = folder / "data" / "artifacts" / jid / "metrics.jsonl"
        if kind == "train" and final.get(jid, {}).get("status") == "succeeded":
            chunks = [json.loads(x)["chunk"] for x in mfile.read_text().splitlines() if x.strip()]
            res = final[jid]["result"]
            if chunks != list(range(1, len(chunks) + 1)) or res["env_steps"] != res["total_steps"]:
                bad_logs.append(jid)
    attempts = [final[j].get("attempts", 1) for j in final]
    # worker killed -> the job it held runs again: the lease must lapse (QUICKNAV_LEASE_S=6)
    from quicknav_service.jobs.redis_store import RedisJobStore

    store = RedisJobStore(cluster.redis.url)
    reclaim = []
    for t_kill, jid in worker_kills:
        if jid is None:
            continue
        starts = [e["time"] for _, e in store.events(jid, limit=100_000)
                  if e.get("type") == "started" and e["time"] > t_kill]  # fmt: skip
        if starts:
            reclaim.append(min(starts) - t_kill)
    self_exits = cluster.self_exits()
    cluster.stop()

    report = {
        "machine": os.uname().nodename, "cores": os.cpu_count(),
        "workers": args.workers, "chaos_s": args.chaos_s, "seed": args.seed,
        "jobs_accepted": len(accepted), "jobs_in_store": page["count"],
        "submission_retries": dict(submit_stats), "faults": dict(faults),
        "redis_down_s": round(redis_down_s, 1),
        "outcomes": dict(outcomes), "failed_reasons": dict(reasons),
        "lost": len(lost), "stuck": len(stuck), "duplicated": duplicated,
        "bad_metric_logs": len(bad_logs), "workers_exited_on_their_own": len(self_exits),
        "max_attempts_seen": max(attempts, default=0),
        "jobs_run_more_than_once": sum(a > 1 for a in attempts),
        "api_back_after_redis_restart_s": {
            "median": round(sorted(redis_recovery)[len(redis_recovery) // 2], 2) if redis_recovery else None,
            "max": round(max(redis_recovery), 2) if redis_recovery else None},
        "job_running_again_after_worker_kill_s": {
            "median": round(sorted(reclaim)[len(reclaim) // 2], 1) if reclaim else None,
            "max": round(max(reclaim), 1) if reclaim else None, "n": len(reclaim)},
        "settle_s": round(t_settled - t_chaos_end, 1),
        "wall_s": round(t_settled - t_start, 1),
    }  # fmt: skip
    print(json.dumps(report, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    ok = not lost and not stuck and duplicated == 0 and not bad_logs and not self_exits
    log(("every accepted job ended" if ok else "FAILED: see lost/stuck/duplicated above")
        + f"; logs in {folder}")  # fmt: skip
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
