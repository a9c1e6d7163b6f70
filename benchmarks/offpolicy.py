"""SAC and TD3 training throughput: rejax's replay sampling against QuickNav's, and both against
what this machine's matrix units do for these networks.

For `paper-sac` and `paper-td3` (2x128 MLPs, 16 envs, minibatch 512 / 256, buffer 500,000 / the
preset's), in one process, alternating, `--rounds` times each:

- `rejax sampler`: rejax's `ReplayBuffer.sample` (without replacement, `jax.random.choice` over every
  slot of the buffer, weighted by which are filled: work that grows with the buffer);
- `uniform sampler`: `UniformReplayBuffer.sample` (uniform indices among the filled slots, with
  replacement, and a gather: work that grows with the minibatch), what QuickNav trains with.

The figure is env steps per second of whole units (acting, storing, sampling, gradient steps;
`fill_buffer` random steps are over before timing starts), compile excluded. The same update-to-data
ratio and widths in both arms: only the sampler differs. XLA's cost analysis counts the FLOPs of one
iteration; FLOP/s of the iterations is set beside the machine's measured matmul throughput for the same matrix
sizes (a jit-compiled chain of [minibatch x 128] @ [128 x 128] products), the ceiling for these
networks on this machine. XLA's count is of one iteration (its loops' bodies are counted once).

    uv run python benchmarks/offpolicy.py [--rounds 3] [--units 4]

Prints a table and writes benchmarks/results/offpolicy.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from rejax.buffers import ReplayBuffer  # noqa: E402

from quicknav_core.bench.machine import machine_info  # noqa: E402
from quicknav_core.config import resolve_train  # noqa: E402
from quicknav_core.train import trainers  # noqa: E402
from quicknav_core.train.rejax_parts import UniformReplayBuffer  # noqa: E402

UNIT_STEPS = 8192  # env steps per timed compiled call


def with_sampler(state, cls):
    """The state with its replay buffer as ``cls`` (same data: only ``sample`` differs)."""
    buf = state.replay_buffer
    return state.replace(replay_buffer=cls(size=buf.size, data=buf.data, index=buf.index,
                                           full=buf.full))  # fmt: skip


def iteration_flops(trainer, state) -> float:
    """XLA's FLOP count of one iteration (one vector env step, its gradient steps). Counted on
    the iteration alone: XLA's cost analysis counts a loop's body once, whatever its trip count."""
    compiled = jax.jit(lambda algo, s: algo.train_iteration(s)).lower(trainer.algo, state).compile()
    analysis = compiled.cost_analysis()
    if isinstance(analysis, list):  # older jax: one dict per computation
        analysis = analysis[0]
    return float(analysis.get("flops", float("nan")))


def measure(preset: str, sampler: str, units: int) -> dict:
    cfg = resolve_train({"preset": preset, "overrides": {"chunk_steps": UNIT_STEPS}})
    cfg = cfg.model_copy(update={"total_steps": UNIT_STEPS * (units + 1)})
    trainer = trainers.make_trainer(cfg)
    state = trainer.init_state()
    cls = ReplayBuffer if sampler == "rejax" else UniformReplayBuffer
    state = with_sampler(state, cls)
    # past fill_buffer, so every timed step samples and updates
    while trainer.env_steps(state) < cfg.algorithm.fill_buffer + trainer.steps_per_unit:
        state = jax.block_until_ready(trainers._rejax_unit(trainer.algo, state))
    flops = iteration_flops(trainer, state)
    seconds = []
    for _ in range(units):
        t0 = time.perf_counter()
        state = jax.block_until_ready(trainers._rejax_unit(trainer.algo, state))
        seconds.append(time.perf_counter() - t0)
    s = statistics.median(seconds)
    steps = trainer.steps_per_unit
    iterations = steps // cfg.num_envs
    return {"preset": preset, "sampler": sampler, "width": list(cfg.network.hidden_sizes),
            "batch_size": cfg.algorithm.batch_size, "buffer_size": cfg.algorithm.buffer_size,
            "env_steps_per_unit": steps, "unit_seconds": seconds, "env_steps_per_s": steps / s,
            "ms_per_iteration": 1000 * s / iterations, "mflop_per_iteration": flops / 1e6,
            "gflops_per_s": flops * iterations / s / 1e9}  # fmt: skip


def matmul_gflops(rows: int = 512, width: int = 128, depth: int = 64, reps: int = 50) -> float:
    """FLOP/s of a jit-compiled chain of [rows x width] @ [width x width] products."""
    w = jax.random.normal(jax.random.PRNGKey(0), (depth, width, width)) / width**0.5
    x = jax.random.normal(jax.random.PRNGKey(1), (rows, width))

    @jax.jit
    def chain(x, w):
        return jax.lax.fori_loop(0, reps, lambda _, x: jax.lax.scan(
            lambda h, wi: (jnp.tanh(h @ wi), None), x, w)[0], x)  # fmt: skip

    jax.block_until_ready(chain(x, w))
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(chain(x, w))
        best = min(best, time.perf_counter() - t0)
    return 2 * rows * width * width * depth * reps / best / 1e9


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--units", type=int, default=4)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/offpolicy.json")
    args = ap.parse_args()
    runs: dict[tuple[str, str], list[dict]] = {}
    for _ in range(args.rounds):
        for preset in ("paper-sac", "paper-td3"):
            for sampler in ("rejax", "uniform"):
                runs.setdefault((preset, sampler), []).append(measure(preset, sampler, args.units))
    peak = {f"{rows}x128": matmul_gflops(rows) for rows in (256, 512)}
    rows = []
    for rs in runs.values():
        rows.append({**rs[-1], "env_steps_per_s": statistics.median(r["env_steps_per_s"] for r in rs),
                     "ms_per_iteration": statistics.median(r["ms_per_iteration"] for r in rs),
                     "gflops_per_s": statistics.median(r["gflops_per_s"] for r in rs),
                     "rounds": [r["env_steps_per_s"] for r in rs]})  # fmt: skip
    info = machine_info()
    print(f"\nSAC / TD3 throughput, {info.get('cpu', '?')}, {info.get('cores', '?')} cores,"
          f" jax {jax.__version__}")
    print(f"{'preset':<10} {'sampler':<8} {'env steps/s':>12} {'ms/iter':>8} {'GFLOP/s':>8}")
    for r in rows:
        print(f"{r['preset']:<10} {r['sampler']:<8} {r['env_steps_per_s']:>12,.0f}"
              f" {r['ms_per_iteration']:>8.2f} {r['gflops_per_s']:>8.1f}")
    for preset in ("paper-sac", "paper-td3"):
        old, new = (next(r for r in rows if r["preset"] == preset and r["sampler"] == s)
                    for s in ("rejax", "uniform"))  # fmt: skip
        print(f"{preset}: uniform sampler {new['env_steps_per_s'] / old['env_steps_per_s']:.2f}x"
              f" rejax's")
    print("matmul ceiling: " + ", ".join(f"[{k}] @ [128x128] {v:.1f} GFLOP/s" for k, v in peak.items()))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": info, "jax": jax.__version__, "rows": rows,
                                    "matmul_gflops": peak}, indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
