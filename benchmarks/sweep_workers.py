"""One sweep job, spread over 1 and then 2 `quicknav worker` processes on the Redis store.

The same sweep (the built-in `ppo` space, TRIALS trials one per batch, a small budget per trial) is
submitted to a fresh Redis DB with N worker processes running; the wall time from submission to the
sweep's end and the trials per hour are printed side by side and written to
benchmarks/results/sweep_workers.json. Each N gets a fresh data folder (no compilation cache carried
over from the previous N), so both pay the same compiles.

    uv run python benchmarks/sweep_workers.py [--trials 16] [--workers 1 2] [--redis redis://127.0.0.1:6379/11]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# benchmarks/service.py would shadow the service package: import from the repository root
ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import redis  # noqa: E402

from quicknav_core.bench.machine import machine_info  # noqa: E402
from quicknav_core.config import resolve_sweep  # noqa: E402
from quicknav_service.jobs.models import JobKind  # noqa: E402
from quicknav_service.jobs.redis_store import RedisJobStore  # noqa: E402


def run(workers: int, trials: int, url: str, total_steps: int) -> dict:
    redis.Redis.from_url(url).flushdb()
    store = RedisJobStore(url)
    data = Path(tempfile.mkdtemp(prefix=f"sweep-bench-{workers}-"))
    env = {**os.environ, "QUICKNAV_REDIS_URL": url, "QUICKNAV_DATA_DIR": str(data)}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    procs = [subprocess.Popen([sys.executable, "-m", "quicknav_cli", "worker"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for _ in range(workers)]  # fmt: skip
    try:
        request = {"space": "ppo", "trials": trials, "parallel": 1, "total_steps": total_steps,
                   "overrides": {"base.num_envs": 64}}  # fmt: skip
        config = resolve_sweep(request).model_dump(mode="json")
        t0 = time.perf_counter()
        sweep, _ = store.submit(JobKind.sweep, request, config)
        while not (job := store.get(sweep.id)).status.finished:
            time.sleep(0.5)
        wall = time.perf_counter() - t0
        kids, _ = store.list(kind=JobKind.trial, limit=500)
        by_worker: dict[str, int] = {}
        for k in kids:
            by_worker[k.worker] = by_worker.get(k.worker, 0) + 1
        return {"workers": workers, "trials": trials, "status": job.status.value,
                "wall_s": round(wall, 1), "trials_per_hour": round(3600 * trials / wall, 1),
                "best_value": job.result.get("best_value") if job.result else None,
                "batches_per_worker": sorted(by_worker.values(), reverse=True)}  # fmt: skip
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(60)
            except subprocess.TimeoutExpired:
                p.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=16)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--total-steps", type=int, default=131072, help="env steps per trial")
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/11")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sweep_workers.json")
    args = ap.parse_args()
    rows = [run(n, args.trials, args.redis, args.total_steps) for n in args.workers]
    base = rows[0]["wall_s"]
    print(f"{'workers':>7} {'wall s':>8} {'trials/h':>9} {'speed-up':>8}  batches per worker  status")
    for r in rows:
        print(f"{r['workers']:>7} {r['wall_s']:>8.1f} {r['trials_per_hour']:>9.1f} "
              f"{base / r['wall_s']:>7.2f}x  {r['batches_per_worker']!s:<19} {r['status']}")  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine_info(), "total_steps_per_trial": args.total_steps,
                                    "rows": rows}, indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
