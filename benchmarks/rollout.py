"""gRPC Rollout throughput and latency over loopback.

Starts `quicknav rollout-server` in its own process on a free port, then drives one stream per
batch size from this process with `quicknav_client.RolloutClient` (lock-step: each Step waits for
its Transition, as an agent does), and reports env steps/s and the p50/p99 round trip per message.
The same batch sizes are also stepped in-process with `BatchedEnv` (no gRPC), so the transport's
share of the time is visible.

    uv run python benchmarks/rollout.py [--envs 1 64 1024 4096] [--seconds 3] [--out FILE]

Targets (issue 8): >= 1,000,000 env steps/s with 4,096 envs per message; p50 < 1 ms with 1 env.
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096])
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
        target = f"127.0.0.1:{port}"
        streams = []
        for n in args.envs:
            r = measure_stream(target, n, args.seconds)
            streams.append(r)
            print(f"gRPC  {n:>6} envs/msg: {r['env_steps_per_s']:>12,.0f} env steps/s,"
                  f" round trip p50 {r['rtt_p50_ms']:.3f} ms, p99 {r['rtt_p99_ms']:.3f} ms",
                  flush=True)  # fmt: skip
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
        "local": local,
        "targets": {"env_steps_per_s_4096": 1_000_000, "rtt_p50_ms_1_env": 1.0},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
