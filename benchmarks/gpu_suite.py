"""The GPU suite: every figure issue 15 asks of a GPU machine, in one command.

    uv run python benchmarks/gpu_suite.py                 # full suite, on whatever backend JAX finds
    uv run python benchmarks/gpu_suite.py --quick         # small sizes: a CPU check of every code path
    uv run python benchmarks/gpu_suite.py --stages env,lidar --minutes 10

Stages (each writes its part of the JSON as soon as it ends, so a run cut short keeps what it did):
  env      env steps/s at grid 16 and 32, 16 and 64 beams, batches 4,096 up to 1,048,576 (or until
           memory or the stage's time runs out), whole observation consumed, for each lidar method;
           compile time and peak device memory per row
  lidar    the ratio dda / crossings per (grid, beams, batch), from the env stage's rows, and the
           method that won on this backend (the value for FASTEST_LIDAR in env/lidar.py)
  train    env steps/s of PPO-MLP (rejax), recurrent PPO with LSTM and GTrXL, SAC and TD3 at the
           paper's sizes, and the PPO rows again at a GPU-sized batch (4,096 envs)
  learning the Table 1 PPO row once: wall time and held-out success (time to 95 %)
  service  `quicknav serve` with its worker on this machine: a demo train job through the REST API
           to success; then the gRPC Rollout benchmark (benchmarks/rollout.py) at 4,096 and 65,536
           envs per message, server on the accelerator, client on the CPU

Writes benchmarks/results/gpu-suite-<backend>-<device>.json and a .md with the tables; with
--readme, also replaces the block between the gpu-suite markers of docs/performance.md by those tables.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
import traceback
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# this folder holds service.py, named like the `service` package: keep it off the import path
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]

README_START = "<!-- gpu-suite:start -->"
README_END = "<!-- gpu-suite:end -->"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def device_name() -> tuple[str, str]:
    import jax

    d = jax.devices()[0]
    return jax.default_backend(), getattr(d, "device_kind", str(d))


def is_oom(e: BaseException) -> bool:
    text = f"{type(e).__name__}: {e}"
    return "RESOURCE_EXHAUSTED" in text or "out of memory" in text.lower()


# --------------------------------------------------------------------------- stages
def stage_env(args, deadline: float) -> list[dict]:
    from quicknav_core.bench.env import BenchConfig, bench_jax_scan

    if args.quick:
        grids, beams_list, batches, steps = (8, 16), (16,), (64, 256), 4096
    else:
        grids, beams_list, steps = (16, 32), (16, 64), 0
        batches = tuple(4096 * 4**k for k in range(6))  # 4,096 .. 4,194,304, cut by memory
        batches = tuple(b for b in batches if b <= args.max_batch)
    rows = []
    for grid in grids:
        for beams in beams_list:
            for method in ("crossings", "dda"):
                for batch in batches:
                    if time.time() > deadline:
                        log("env: out of time")
                        return rows
                    # at least 64 steps per env per timed call, and 2M+ env steps per call
                    n = steps or max(batch * 64, 2_000_000)
                    cfg = BenchConfig(grids=(grid,), batches=(batch,), beams=beams, steps=n,
                                      repeats=3, lidar_method=method)  # fmt: skip
                    try:
                        m = bench_jax_scan(grid, batch, cfg)
                    except Exception as e:  # memory ends the row, anything else is recorded
                        reason = "out of memory" if is_oom(e) else f"{type(e).__name__}: {e}"[:300]
                        rows.append({"grid": grid, "beams": beams, "lidar": method, "batch": batch,
                                     "error": reason})  # fmt: skip
                        log(f"env grid {grid} beams {beams} {method} {batch:,}: {reason}")
                        break
                    row = {"grid": grid, "beams": beams, "lidar": method, "batch": batch,
                           "steps_per_s": round(m.steps_per_s), "compile_s": round(m.compile_s, 2),
                           "peak_memory_bytes": m.peak_memory_bytes,
                           "memory_source": m.memory_source, "steps_timed": m.steps_timed}  # fmt: skip
                    rows.append(row)
                    log(f"env grid {grid} beams {beams} {method} {batch:,}: "
                        f"{m.steps_per_s:,.0f} steps/s, compile {m.compile_s:.1f} s")  # fmt: skip
    return rows


def stage_lidar(env_rows: list[dict]) -> dict:
    ok = [r for r in env_rows if "steps_per_s" in r]
    by = {(r["grid"], r["beams"], r["batch"], r["lidar"]): r["steps_per_s"] for r in ok}
    ratios = []
    for (grid, beams, batch, method), rate in sorted(by.items()):
        if method != "dda" or (grid, beams, batch, "crossings") not in by:
            continue
        base = by[(grid, beams, batch, "crossings")]
        ratios.append({"grid": grid, "beams": beams, "batch": batch,
                       "dda_over_crossings": round(rate / base, 3)})  # fmt: skip
    wins = sum(r["dda_over_crossings"] > 1.0 for r in ratios)
    faster = "dda" if ratios and wins > len(ratios) / 2 else "crossings"
    return {"ratios": ratios, "dda_wins": wins, "compared": len(ratios), "faster": faster}


def stage_train(args, deadline: float) -> list[dict]:
    from quicknav_core.bench.train import bench_row

    paper = [("ppo-mlp", "paper-ppo", 262_144), ("rppo-lstm", "paper-lstm", 262_144),
             ("rppo-gtrxl", "paper-gtrxl", 262_144), ("sac-mlp", "paper-sac", 8_192),
             ("td3-mlp", "paper-td3", 8_192)]  # fmt: skip
    big = [("ppo-mlp@4096", "paper-ppo"), ("rppo-lstm@4096", "paper-lstm"),
           ("rppo-gtrxl@4096", "paper-gtrxl")]  # fmt: skip
    rows = []
    plans = [(name, preset, chunk, None) for name, preset, chunk in paper]
    plans += [(name, preset, 4096 * 64 * 4, {"num_envs": 4096}) for name, preset in big]
    if args.quick:  # the smallest chunk each preset allows, one timed chunk
        plans = [(n, p, 1, {"env.grid_size": 8, "env.train_rooms": 32, "env.test_rooms": 16,
                            **(o or {}), **({"num_envs": 64} if o else {})}) for n, p, _, o in plans]  # fmt: skip
    for name, preset, chunk, overrides in plans:
        if time.time() > deadline:
            log("train: out of time")
            break
        try:
            r = bench_row(name, preset, chunk, 1 if args.quick else 3, overrides)
        except Exception as e:  # recorded, the next row runs
            reason = "out of memory" if is_oom(e) else f"{type(e).__name__}: {e}"[:300]
            rows.append({"name": name, "preset": preset, "error": reason})
            log(f"train {name}: {reason}")
            continue
        row = asdict(r)
        row["env_steps_per_s"] = round(row["env_steps_per_s"])
        rows.append(row)
        log(f"train {name}: {r.env_steps_per_s:,.0f} env steps/s ({r.num_envs} envs), "
            f"compile+first chunk {r.compile_and_first_chunk_s:.1f} s")  # fmt: skip
    return rows


def stage_learning(args, out_dir: Path) -> dict:
    from quicknav_core.bench.learning import ROWS, run_one

    row = next(r for r in ROWS if r.preset == "paper-ppo")
    scale = 0.02 if args.quick else 1.0
    runs = out_dir / "gpu-suite-runs"
    t0 = time.time()
    result = run_one(row, seed=0, runs_dir=runs, scale=scale, say=log)
    out = {"row": row.name, "wall_s": round(time.time() - t0, 1), "training": result["training"],
           "held_out": {k: result["metrics"].get(k) for k in ("success_rate", "success_ci95", "spl", "steps_to_goal_successes")}}  # fmt: skip
    # the first chunk whose training episodes reached 95 % success (held-out success is at the end)
    metrics = [json.loads(x) for x in next(runs.glob("*-s0")).joinpath("metrics.jsonl").read_text().splitlines() if x]  # fmt: skip
    first = next((m for m in metrics if m.get("success_rate", 0) >= 0.95), None)
    out["train_success_95"] = None if first is None else {
        "env_steps": first["env_steps"], "wall_s_of_training": round(sum(
            m.get("wall_s", 0) for m in metrics if m["chunk"] <= first["chunk"]), 1)}  # fmt: skip
    return out


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stage_service(args, out_dir: Path) -> dict:
    import tempfile

    import httpx

    out: dict = {}
    data = Path(tempfile.mkdtemp(prefix="quicknav-gpu-suite-"))
    port, grpc_port = _free_port(), _free_port()
    env = {**os.environ, "QUICKNAV_DATA_DIR": str(data), "PYTHONUNBUFFERED": "1"}
    env.pop("QUICKNAV_REDIS_URL", None)
    with open(data / "serve.log", "wb") as serve_log:
        proc = subprocess.Popen([sys.executable, "-m", "quicknav_cli", "serve", "--port", str(port),
                                 "--grpc-port", str(grpc_port)], env=env, cwd=ROOT,
                                stdout=serve_log, stderr=subprocess.STDOUT)  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        t0 = time.time()
        while time.time() - t0 < 120:
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        overrides = {"total_steps": 200_000} if args.quick else {}
        t0 = time.time()
        job = httpx.post(f"{url}/jobs/train", json={"preset": "demo", "overrides": overrides},
                         timeout=30).json()  # fmt: skip
        while True:
            rec = httpx.get(f"{url}/jobs/{job['id']}", timeout=30).json()
            if rec["status"] in ("succeeded", "failed", "cancelled"):
                break
            time.sleep(2)
        final = (rec.get("result") or {}).get("final", {})
        out["demo_job"] = {"status": rec["status"], "error": rec.get("error"),
                           "wall_s": round(time.time() - t0, 1), "env_steps": final.get("env_steps"),
                           "success_rate": final.get("success_rate"),
                           "steps_per_s": final.get("steps_per_s")}  # fmt: skip
        log(f"service: demo job {rec['status']} in {out['demo_job']['wall_s']} s")
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    envs = ["64", "256"] if args.quick else ["4096", "65536"]
    result = out_dir / "gpu-suite-rollout.json"
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks/rollout.py"), "--envs", *envs,
                        "--seconds", "2" if args.quick else "5", "--out", str(result)],
                       cwd=ROOT, capture_output=True, text=True)  # fmt: skip
    out["rollout"] = json.loads(result.read_text()) if result.exists() else {
        "error": (r.stderr or r.stdout)[-1000:]}  # fmt: skip
    return out


# --------------------------------------------------------------------------- report
def markdown(report: dict) -> str:
    lines = [f"GPU suite on **{report['device']}** ({report['backend']}, jax {report['jax']}), "
             f"{report['date']}.", ""]  # fmt: skip
    env_rows = report.get("env") or []
    if env_rows:
        lines += ["| grid | beams | lidar | envs | steps/s | compile s | peak MiB |",
                  "|---:|---:|---|---:|---:|---:|---:|"]  # fmt: skip
        for r in env_rows:
            if "error" in r:
                lines.append(f"| {r['grid']} | {r['beams']} | {r['lidar']} | {r['batch']:,} |"
                             f" {r['error']} | | |")  # fmt: skip
                continue
            mem = f"{r['peak_memory_bytes'] / 2**20:,.0f}" if r.get("peak_memory_bytes") else ""
            lines.append(f"| {r['grid']} | {r['beams']} | {r['lidar']} | {r['batch']:,} |"
                         f" {r['steps_per_s']:,} | {r['compile_s']} | {mem} |")  # fmt: skip
        lines.append("")
    lid = report.get("lidar")
    if lid and lid.get("ratios"):
        lines += [f"Lidar: dda / crossings steps/s, faster here: **{lid['faster']}** "
                  f"(dda won {lid['dda_wins']} of {lid['compared']}).", "",
                  "| grid | beams | envs | dda / crossings |", "|---:|---:|---:|---:|"]  # fmt: skip
        lines += [f"| {r['grid']} | {r['beams']} | {r['batch']:,} | {r['dda_over_crossings']} |"
                  for r in lid["ratios"]]  # fmt: skip
        lines.append("")
    train = report.get("train") or []
    if train:
        lines += ["| training row | envs | env steps/s | compile + first chunk s |",
                  "|---|---:|---:|---:|"]  # fmt: skip
        for r in train:
            if "error" in r:
                lines.append(f"| {r['name']} | | {r['error']} | |")
            else:
                lines.append(f"| {r['name']} | {r['num_envs']:,} | {r['env_steps_per_s']:,} |"
                             f" {r['compile_and_first_chunk_s']} |")  # fmt: skip
        lines.append("")
    if report.get("learning"):
        lr = report["learning"]
        lines += [f"Table 1 PPO row: held-out {json.dumps(lr.get('held_out'))}, training"
                  f" {json.dumps(lr.get('training'))}, first chunk at 95 % training success:"
                  f" {json.dumps(lr.get('train_success_95'))}", ""]  # fmt: skip
    if report.get("service"):
        lines += [f"Service: {json.dumps(report['service'].get('demo_job'))}", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes, to check every path on CPU")
    ap.add_argument("--stages", default="env,lidar,train,learning,service")
    ap.add_argument("--minutes", type=float, default=25.0, help="time budget for the whole suite")
    ap.add_argument("--max-batch", type=int, default=1_048_576)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results")
    ap.add_argument("--readme", action="store_true", help="put the tables into docs/performance.md")
    args = ap.parse_args()
    stages = [s.strip() for s in args.stages.split(",") if s.strip()]
    unknown = set(stages) - {"env", "lidar", "train", "learning", "service"}
    if unknown:
        ap.error(
            f"--stages: unknown {sorted(unknown)}; allowed env, lidar, train, learning, service"
        )

    import jax

    backend, device = device_name()
    slug = re.sub(r"[^a-z0-9]+", "-", f"{backend}-{device}".lower()).strip("-")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"gpu-suite-{slug}{'-quick' if args.quick else ''}.json"
    report = {"backend": backend, "device": device, "jax": jax.__version__,
              "devices": len(jax.devices()), "date": time.strftime("%Y-%m-%d"),
              "quick": args.quick, "cpu_cores": os.cpu_count()}  # fmt: skip
    t_end = time.time() + args.minutes * 60
    share = {"env": 0.35, "train": 0.25, "learning": 0.25, "service": 0.15}
    log(f"{device} ({backend}), {len(jax.devices())} device(s); stages {stages}; writing {path}")

    def save() -> None:
        path.write_text(json.dumps(report, indent=2) + "\n")
        path.with_suffix(".md").write_text(markdown(report) + "\n")

    for stage in stages:
        t0 = time.time()
        deadline = min(t_end, t0 + share.get(stage, 0.1) * args.minutes * 60 * 1.5)
        try:
            if stage == "env":
                report["env"] = stage_env(args, deadline)
            elif stage == "lidar":
                report["lidar"] = stage_lidar(report.get("env") or [])
                log(f"lidar: faster here {report['lidar']['faster']}")
            elif stage == "train":
                report["train"] = stage_train(args, deadline)
            elif stage == "learning":
                report["learning"] = stage_learning(args, args.out)
            elif stage == "service":
                report["service"] = stage_service(args, args.out)
        except Exception as e:  # a stage that breaks must not lose the others
            report[stage] = {
                "error": f"{type(e).__name__}: {e}",
                "trace": traceback.format_exc()[-2000:],
            }
            log(f"{stage}: FAILED {type(e).__name__}: {e}")
        report.setdefault("stage_seconds", {})[stage] = round(time.time() - t0, 1)
        save()
    if args.readme:
        readme = ROOT / "docs" / "performance.md"
        text = readme.read_text()
        if README_START not in text or README_END not in text:
            log(f"--readme: {readme} has no {README_START} ... {README_END} block; tables not placed")
        else:
            head, rest = text.split(README_START, 1)
            _, tail = rest.split(README_END, 1)
            readme.write_text(
                head + README_START + "\n" + markdown(report) + "\n" + README_END + tail
            )
    log(f"wrote {path} and {path.with_suffix('.md')}")


if __name__ == "__main__":
    main()
