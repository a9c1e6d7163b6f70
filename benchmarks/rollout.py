"""gRPC Rollout throughput and latency over loopback, lock-step and asynchronous, against the same
batch stepped in-process.

Starts `quicknav rollout-server` in its own process on a free port, then drives one stream per
batch size from this process with `quicknav_client.RolloutClient`:

- lock-step: each Step waits for its Transition, as a plain agent does; env steps/s and the
  p50/p99 round trip per message;
- asynchronous (`--groups G`, default 2): the batch in G groups; the client keeps every group in
  flight, sending a group's next actions as soon as its Transition arrives (EnvPool's send/recv),
  so the server steps one group while another's messages travel;
- in-process: the same batch stepped with `BatchedEnv` in this process (no gRPC), the anchor.

    uv run python benchmarks/rollout.py [--envs 1 64 1024 4096] [--groups 2] [--seconds 3]

Goals (issue 27): asynchronous >= 0.9x in-process at 4,096 envs and >= 1M env steps/s; p50 round
trip at 64 envs <= 0.5 ms.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import time
from pathlib import Path

# run as a script from anywhere: never let this folder shadow the project's packages
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import numpy as np  # noqa: E402
from quicknav_client.rollout import RolloutClient  # noqa: E402

CONFIG = {}  # the default EnvConfig: grid 16, 16 beams


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def measure_stream(target: str, n: int, seconds: float, min_messages: int = 50) -> dict:
    """Lock-step Steps through one stream for about ``seconds``."""
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (n, 2)).astype(np.float32) for _ in range(16)]
    with RolloutClient(target) as rc:
        t0 = time.perf_counter()
        rc.start(num_envs=n, seed=0, config=CONFIG)
        start_s = time.perf_counter() - t0
        for i in range(20):  # warm-up
            rc.step(actions[i % 16])
        rtts = []
        begin = time.perf_counter()
        while len(rtts) < min_messages or time.perf_counter() - begin < seconds:
            t = time.perf_counter()
            rc.step(actions[len(rtts) % 16])
            rtts.append(time.perf_counter() - t)
        total = time.perf_counter() - begin
    rtts = np.asarray(rtts)
    return {
        "num_envs": n,
        "messages": len(rtts),
        "env_steps_per_s": n * len(rtts) / total,
        "rtt_p50_ms": float(np.percentile(rtts, 50) * 1e3),
        "rtt_p99_ms": float(np.percentile(rtts, 99) * 1e3),
        "start_s": start_s,
    }


def measure_async(target: str, n: int, groups: int, seconds: float, min_messages: int = 50) -> dict:
    """Every group in flight: send a group's next actions as soon as its Transition arrives."""
    k = n // groups
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (k, 2)).astype(np.float32) for _ in range(16)]
    with RolloutClient(target) as rc:
        rc.start(num_envs=n, seed=0, config=CONFIG, groups=groups)
        for g in range(groups):
            rc.send(actions[g % 16], group=g)
        for i in range(20 * groups):  # warm-up
            t = rc.recv()
            rc.send(actions[i % 16], group=t.group)
        received = 0
        begin = time.perf_counter()
        while received < min_messages or time.perf_counter() - begin < seconds:
            t = rc.recv()
            received += 1
            rc.send(actions[received % 16], group=t.group)
        total = time.perf_counter() - begin
    return {"num_envs": n, "groups": groups, "messages": received,
            "env_steps_per_s": k * received / total}  # fmt: skip


def measure_local(n: int, seconds: float) -> dict:
    """The same lock-step loop with BatchedEnv in this process: the env's share of a round trip."""
    from quicknav_core.config import EnvConfig
    from quicknav_core.env.batch import BatchedEnv

    env = BatchedEnv(EnvConfig(**CONFIG), n, seed=0)
    env.reset()
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (n, 2)).astype(np.float32) for _ in range(16)]
    for i in range(20):
        env.step(actions[i % 16])
    times = []
    begin = time.perf_counter()
    while len(times) < 50 or time.perf_counter() - begin < seconds:
        t = time.perf_counter()
        env.step(actions[len(times) % 16])
        times.append(time.perf_counter() - t)
    total = time.perf_counter() - begin
    times = np.asarray(times)
    return {
        "num_envs": n,
        "env_steps_per_s": n * len(times) / total,
        "step_p50_ms": float(np.percentile(times, 50) * 1e3),
    }


def _ratios(streams: list[dict], asynchronous: list[dict], local: list[dict]) -> dict:
    """Per batch size: lock-step and asynchronous env steps/s over the in-process figure."""
    out = {}
    for loc in local:
        n, base = loc["num_envs"], loc["env_steps_per_s"]
        row = {}
        for mode, found in (("lock_step", streams), ("async", asynchronous)):
            for r in found:
                if r["num_envs"] == n:
                    row[mode] = r["env_steps_per_s"] / base
        out[str(n)] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096])
    ap.add_argument("--groups", type=int, default=2, help="groups of the asynchronous mode")
    ap.add_argument("--seconds", type=float, default=3.0, help="measuring time per batch size")
    ap.add_argument(
        "--cpu-devices", type=int, default=None, help="passed to rollout-server (default 1)"
    )
    ap.add_argument("--no-local", action="store_true", help="skip the in-process comparison")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rollout.json"))
    args = ap.parse_args()

    port = _free_port()
    cmd = [sys.executable, "-m", "quicknav_cli", "rollout-server", "--port", str(port)]
    if args.cpu_devices:
        cmd += ["--cpu-devices", str(args.cpu_devices)]
    env = {**os.environ, "QUICKNAV_MAX_ENVS": str(max(args.envs))}
    server = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)  # fmt: skip
    try:
        line = server.stdout.readline()
        if "listening" not in line:
            raise SystemExit(f"rollout-server did not start: {line}{server.stdout.read()}")
        # keep reading what the server writes: a full pipe (64 KiB) would stop it mid-measurement
        import threading

        threading.Thread(target=server.stdout.read, name="server-output", daemon=True).start()
        target = f"127.0.0.1:{port}"
        streams, asynchronous = [], []
        for n in args.envs:
            r = measure_stream(target, n, args.seconds)
            streams.append(r)
            print(f"gRPC lock-step {n:>6} envs: {r['env_steps_per_s']:>12,.0f} env steps/s,"
                  f" round trip p50 {r['rtt_p50_ms']:.3f} ms, p99 {r['rtt_p99_ms']:.3f} ms",
                  flush=True)  # fmt: skip
            if n >= 2 * args.groups and n % args.groups == 0:
                a = measure_async(target, n, args.groups, args.seconds)
                asynchronous.append(a)
                print(f"gRPC async     {n:>6} envs: {a['env_steps_per_s']:>12,.0f} env steps/s"
                      f" ({args.groups} groups of {n // args.groups})", flush=True)  # fmt: skip
    finally:
        server.terminate()
        server.wait(10)
    local = []
    if not args.no_local:
        for n in args.envs:
            r = measure_local(n, args.seconds)
            local.append(r)
            print(f"local {n:>6} envs/step: {r['env_steps_per_s']:>12,.0f} env steps/s,"
                  f" step p50 {r['step_p50_ms']:.3f} ms (BatchedEnv in-process, no gRPC)",
                  flush=True)  # fmt: skip

    import grpc
    import jax

    result = {
        "machine": {
            "cpu": _cpu_model(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "grpcio": grpc.__version__,
            "backend": jax.default_backend(),
        },
        "config": {
            "env": CONFIG or "EnvConfig() defaults (grid 16, 16 beams)",
            "seconds": args.seconds,
            "server_cpu_devices": args.cpu_devices or "default",
        },
        "streams": streams,
        "async": asynchronous,
        "local": local,
        "ratios_to_in_process": _ratios(streams, asynchronous, local),
        "goals": {"async_ratio_4096": 0.9, "env_steps_per_s_4096": 1_000_000,
                  "rtt_p50_ms_64_envs": 0.5},
    }  # fmt: skip
    for n, ratio in result["ratios_to_in_process"].items():
        print(f"{n:>6} envs: " + ", ".join(f"{k} {v:.2f}x in-process" for k, v in ratio.items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
