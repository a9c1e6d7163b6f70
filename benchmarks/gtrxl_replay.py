"""GTrXL training throughput: the PPO replay step by step (a scan over the rollout) against the
whole sequence at once (one banded attention per layer, `GTrXLPolicy.parallel_sequence`).

Both modes train the `paper-gtrxl` preset (256 envs, 64-step rollouts, 16 minibatches, 4 epochs)
in the same process, alternating, `--rounds` times each; the figure is env steps per second of
whole chunks (acting, replay, gradients), compile and first chunk excluded (`quicknav bench train`'s
`bench_row`). Prints the medians side by side and writes benchmarks/results/gtrxl_replay.json.

    uv run python benchmarks/gtrxl_replay.py [--rounds 2] [--chunk-steps 262144]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

from quicknav_core.bench.machine import machine_info  # noqa: E402
from quicknav_core.bench.train import bench_row  # noqa: E402
from quicknav_core.networks.gtrxl import GTrXLPolicy  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--chunk-steps", type=int, default=262_144)
    ap.add_argument("--chunks", type=int, default=2)
    args = ap.parse_args()
    rates: dict[str, list[float]] = {"step_by_step": [], "whole_sequence": []}
    for r in range(args.rounds):
        for mode, parallel in (("step_by_step", False), ("whole_sequence", True)):
            GTrXLPolicy.parallel_sequence = parallel
            row = bench_row(f"gtrxl-{mode}", "paper-gtrxl", args.chunk_steps, args.chunks)
            rates[mode].append(row.env_steps_per_s)
            print(f"round {r}: {mode:15s} {row.env_steps_per_s:10,.0f} env steps/s "
                  f"(compile + first chunk {row.compile_and_first_chunk_s:.1f} s)", flush=True)  # fmt: skip
    med = {k: statistics.median(v) for k, v in rates.items()}
    ratio = med["whole_sequence"] / med["step_by_step"]
    print(f"median: step by step {med['step_by_step']:,.0f}, whole sequence {med['whole_sequence']:,.0f} "
          f"env steps/s ({ratio:.1f}x)")  # fmt: skip
    out = ROOT / "benchmarks" / "results" / "gtrxl_replay.json"
    out.write_text(json.dumps({"machine": machine_info(), "preset": "paper-gtrxl",
                               "chunk_steps": args.chunk_steps, "rates": rates, "median": med,
                               "speedup": ratio}, indent=2) + "\n")  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
