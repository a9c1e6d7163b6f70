"""Memoryless MLP training throughput: the PPO replay step by step (a scan over the rollout)
against the whole sequence in one call (`MLPPolicy.parallel_sequence`), with one frame and with
two (`network.frames`, the `building` preset's).

Each row trains the `building` preset (256 envs, 64-step rollouts, 8 minibatches, 4 epochs; its
network with the row's frames) in a process of its own; the figure is env steps per second of
whole chunks (acting, replay, gradients), compile and first chunk excluded (`quicknav bench
train`'s `bench_row`). Prints the rows side by side and writes benchmarks/results/mlp_replay.json.

    uv run python benchmarks/mlp_replay.py [--chunk-steps 1048576] [--chunks 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

from quicknav_core.bench.machine import machine_info  # noqa: E402

MODES = ("step_by_step", "whole_sequence")


def one_row(frames: int, mode: str, chunk_steps: int, chunks: int) -> dict:
    """In this process: one row (the replay mode is set before any trainer is built)."""
    from quicknav_core.bench.train import bench_row
    from quicknav_core.networks.mlp import MLPPolicy

    MLPPolicy.parallel_sequence = mode == "whole_sequence"
    network = {"kind": "mlp", "hidden_sizes": [128, 128], "frames": frames}
    row = bench_row(
        f"building-frames{frames}-{mode}", "building", chunk_steps, chunks, {"network": network}
    )
    return {"frames": frames, "mode": mode, "env_steps_per_s": row.env_steps_per_s,
            "chunk_s": row.chunk_seconds, "compile_and_first_chunk_s": row.compile_and_first_chunk_s}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--chunk-steps", type=int, default=1_048_576)
    ap.add_argument("--chunks", type=int, default=2)
    ap.add_argument("--row", nargs=2, metavar=("FRAMES", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.row:
        print(json.dumps(one_row(int(args.row[0]), args.row[1], args.chunk_steps, args.chunks)))
        return
    rows = []
    for frames in (1, 2):
        for mode in MODES:
            out = subprocess.run(
                [sys.executable, __file__, "--row", str(frames), mode, "--chunk-steps",
                 str(args.chunk_steps), "--chunks", str(args.chunks)],
                check=True, capture_output=True, text=True, cwd=ROOT,
            )  # fmt: skip
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"frames {frames}, {mode:14s} {row['env_steps_per_s']:10,.0f} env steps/s "
                  f"(chunks {row['chunk_s']} s)", flush=True)  # fmt: skip
    for frames in (1, 2):
        a, b = (next(r for r in rows if r["frames"] == frames and r["mode"] == m) for m in MODES)
        print(
            f"frames {frames}: whole sequence {b['env_steps_per_s'] / a['env_steps_per_s']:.2f}x step by step"
        )
    out = ROOT / "benchmarks" / "results" / "mlp_replay.json"
    out.write_text(json.dumps({"machine": machine_info(), "preset": "building",
                               "chunk_steps": args.chunk_steps, "rows": rows}, indent=2) + "\n")  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
