"""`quicknav bench` (or `quicknav bench env`): environment throughput, JAX versus the NumPy twin (the paper's Figure 3, redone).

For every grid size it measures, with uniformly random actions:
  numpy        the NumPy twin, one env stepped in a Python loop (the paper's baseline)
  jax-b1-py    the JAX env, one env, a jitted step called from Python each step
  jax-b1-scan  the JAX env, one env, ``lax.scan`` over steps inside one jitted call
  jax-bN       N envs vmapped inside ``lax.scan`` (auto-reset), for each batch size N

Compile time is measured apart (ahead-of-time ``lower().compile()``); steady state is the median of
``repeats`` timed runs after one warm-up run. Loops driven from Python (numpy, jax-b1-py) stop early
when their share of the time budget runs out; their rate is then measured over fewer steps, and the
time for ``steps`` steps is computed from it (the JSON says how many steps were timed).
"""

from __future__ import annotations

import json
import math
import statistics
import time
import tracemalloc
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from quicknav_core.bench.machine import machine_info
from quicknav_core.config import EnvConfig

DEFAULT_GRIDS = (4, 8, 16)
DEFAULT_BATCHES = (64, 1024, 4096, 16384)
GPU_EXTRA_BATCHES = (65536, 262144, 1048576)

# The targets, checked on the measured figures.
TARGET_STEPS_PER_S = 1_000_000  # grid 16, 4,096 envs
TARGET_SPEEDUP = 100.0  # JAX 4,096 envs over the NumPy twin, grid 16
TARGET_GROWTH = 2.0  # time per env-step, grid 16 over grid 4, 4,096 envs
TARGET_COMPILE_S = 10.0


@dataclass
class Measurement:
    """One row of the table."""

    grid: int
    impl: str  # numpy | jax-b1-py | jax-b1-scan | jax-b<N>
    batch: int
    steps_timed: int  # env steps in one timed repeat
    repeats: int
    seconds: list[float]  # wall-clock of each timed repeat
    steps_per_s: float  # steps_timed / median(seconds)
    time_for_steps_s: float  # wall-clock for ``BenchConfig.steps`` steps at that rate
    compile_s: float | None = None
    peak_memory_bytes: int | None = None
    memory_source: str = ""
    devices: int = 1  # devices the batch was sharded over
    note: str = ""


@dataclass
class BenchConfig:
    grids: Sequence[int] = DEFAULT_GRIDS
    batches: Sequence[int] = DEFAULT_BATCHES
    beams: int = 16
    steps: int = 100_000
    repeats: int = 3
    budget_s: float = 240.0
    room_size: float = 8.0
    final_obs: bool = False
    seed: int = 0
    lidar_method: str = "auto"


@dataclass
class BenchReport:
    config: dict[str, Any]
    machine: dict[str, Any]
    results: list[Measurement] = field(default_factory=list)
    targets: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "config": self.config,
            "machine": self.machine,
            "results": [asdict(r) for r in self.results],
            "targets": self.targets,
        }


def env_config_for(grid: int, cfg: BenchConfig) -> EnvConfig:
    """The benchmark's env: room 8 m, defaults otherwise; a smaller robot only where the grid needs it."""
    cell = cfg.room_size / grid
    radius = min(0.15, 0.45 * cell)
    return EnvConfig(
        grid_size=grid,
        room_size=cfg.room_size,
        lidar_beams=cfg.beams,
        robot_radius=radius,
        max_wheel_speed=min(1.0, cell / 0.1),
        final_obs=cfg.final_obs,
        room_seed=cfg.seed,
        lidar_method=cfg.lidar_method,
    )


def _median(xs: Sequence[float]) -> float:
    return float(statistics.median(xs))


# --------------------------------------------------------------------------- NumPy twin
def bench_numpy(grid: int, cfg: BenchConfig, cap_s: float) -> Measurement:
    """The twin, one env, Python loop, auto-reset by calling reset()."""
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv

    config = env_config_for(grid, cfg)
    from quicknav_core.env.room_sources import make_room_bank

    # the same pre-generated rooms as the JAX env, so neither side carves while being timed
    env = QuickNavNumpyEnv(config, rooms=make_room_bank(config, "train"))
    rng = np.random.default_rng(cfg.seed)
    env.reset(seed=cfg.seed)

    def run(max_steps: int, deadline_s: float) -> tuple[int, float]:
        t0 = time.perf_counter()
        n = 0
        while n < max_steps:
            for _ in range(100):
                _, _, term, trunc, _ = env.step(rng.uniform(-1.0, 1.0, 2))
                if term or trunc:
                    env.reset()
            n += 100
            if time.perf_counter() - t0 > deadline_s:
                break
        return n, time.perf_counter() - t0

    # peak memory from a short separate pass: tracemalloc slows Python down, so never while timing
    tracemalloc.start()
    run(2000, cap_s)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    run(2000, cap_s)  # warm-up
    counts, secs = [], []
    for _ in range(cfg.repeats):
        n, s = run(cfg.steps, cap_s)
        counts.append(n)
        secs.append(s)
    rates = [n / s for n, s in zip(counts, secs, strict=True)]
    rate = _median(rates)
    n_timed = int(min(counts))
    return Measurement(
        grid=grid, impl="numpy", batch=1, steps_timed=n_timed, repeats=cfg.repeats,
        seconds=[round(s, 4) for s in secs], steps_per_s=rate, time_for_steps_s=cfg.steps / rate,
        peak_memory_bytes=int(peak), memory_source="tracemalloc peak (Python + NumPy heap)",
        note="" if n_timed >= cfg.steps else f"timed {n_timed:,}/repeat",
    )  # fmt: skip


# --------------------------------------------------------------------------- JAX
def _compiled_memory(compiled) -> tuple[int | None, str]:
    try:
        m = compiled.memory_analysis()
        total = (
            m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes
            - m.alias_size_in_bytes
        )  # fmt: skip
        return int(total), "XLA memory analysis (arguments + outputs + temporaries)"
    except Exception:
        return None, ""


def _device_peak() -> int | None:
    import jax

    try:
        stats = jax.devices()[0].memory_stats()
        return int(stats["peak_bytes_in_use"]) if stats else None
    except Exception:
        return None


def _time_compiled(fn: Callable[[], Any], repeats: int) -> list[float]:
    import jax

    jax.block_until_ready(fn())  # warm-up
    secs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        secs.append(time.perf_counter() - t0)
    return secs


def bench_jax_python_loop(grid: int, cfg: BenchConfig, cap_s: float) -> Measurement:
    """One env; every step is one call of a jitted function from Python (dispatch included)."""
    import jax

    env, params = env_config_for(grid, cfg).build("train")

    def one_step(key, state):
        key, k_act, k_step = jax.random.split(key, 3)
        action = jax.random.uniform(k_act, (2,), minval=-1.0, maxval=1.0)
        _, state, reward, done, _ = env.step(k_step, state, action, params)
        return key, state, reward

    key = jax.random.PRNGKey(cfg.seed)
    _, state = env.reset(key, params)
    t0 = time.perf_counter()
    step = jax.jit(one_step, donate_argnums=(1,)).lower(key, state).compile()
    compile_s = time.perf_counter() - t0
    mem, mem_src = _compiled_memory(step)

    def run(max_steps: int, deadline_s: float) -> tuple[int, float]:
        nonlocal key, state
        t0 = time.perf_counter()
        n = 0
        reward = None
        while n < max_steps:
            for _ in range(100):
                key, state, reward = step(key, state)
            n += 100
            if time.perf_counter() - t0 > deadline_s:
                break
        jax.block_until_ready(reward)
        return n, time.perf_counter() - t0

    run(500, cap_s)
    counts, secs = [], []
    for _ in range(cfg.repeats):
        n, s = run(cfg.steps, cap_s)
        counts.append(n)
        secs.append(s)
    rate = _median([n / s for n, s in zip(counts, secs, strict=True)])
    n_timed = int(min(counts))
    return Measurement(
        grid=grid, impl="jax-b1-py", batch=1, steps_timed=n_timed, repeats=cfg.repeats,
        seconds=[round(s, 4) for s in secs], steps_per_s=rate, time_for_steps_s=cfg.steps / rate,
        compile_s=compile_s, peak_memory_bytes=mem, memory_source=mem_src,
        note="" if n_timed >= cfg.steps else f"timed {n_timed:,}/repeat",
    )  # fmt: skip


def make_scan_rollout(env, params, batch: int, length: int, final_obs: bool, batched: bool = False):
    """A jittable rollout: ``length`` steps of ``batch`` vmapped envs with random actions.

    ``batched``: step with ``env.batch.batched_step`` (as QuickNav's PPO does: only the envs that
    ended are reset) instead of ``vmap(env.step)`` (gymnax's auto-reset, every env every step)."""
    import jax
    import jax.numpy as jnp

    from quicknav_core.env.batch import batched_step

    vstep = jax.vmap(env.step, in_axes=(0, 0, 0, None))

    def step(keys, state, actions):
        if not batched:
            obs, state, reward, done, info = vstep(keys, state, actions, params)
            return obs, state, reward, done, info.get("final_obs")
        obs, state, reward, info, final = batched_step(env, keys, state, actions, params)
        return obs, state, reward, info["terminated"] | info["truncated"], final

    def rollout(key, state):
        def body(carry, _):
            key, state, total = carry
            key, k_act, k_step = jax.random.split(key, 3)
            actions = jax.random.uniform(k_act, (batch, 2), minval=-1.0, maxval=1.0)
            obs, state, reward, done, final = step(jax.random.split(k_step, batch), state, actions)
            # consume the whole observation and the outputs: none of the step's work is dead code
            total = total + reward.sum() + obs.sum() + done.sum()
            if final_obs:
                total = total + final.sum()
            return (key, state, total), None

        (key, state, total), _ = jax.lax.scan(body, (key, state, jnp.float32(0.0)), None, length)
        return key, state, total

    return rollout


def shard_rollout(rollout, devices):
    """Run ``rollout(key, state)`` on every device, each on its slice of the env batch (shard_map)."""
    import jax
    from jax.sharding import Mesh, PartitionSpec

    mesh = Mesh(np.array(devices), ("envs",))
    spec = PartitionSpec("envs")

    def local(keys, state):
        key, state, total = rollout(keys[0], state)
        return key[None], state, total[None]

    return jax.shard_map(
        local, mesh=mesh, in_specs=(spec, spec), out_specs=(spec, spec, spec), check_vma=False
    )


def bench_jax_scan(grid: int, batch: int, cfg: BenchConfig) -> Measurement:
    """``batch`` envs (vmapped when > 1) inside lax.scan, one jitted call per repeat.

    With several local devices (GPUs, or CPU cores exposed as devices) a batch that divides evenly
    is sharded over them, each device stepping its slice.
    """
    import jax

    env, params = env_config_for(grid, cfg).build("train")
    length = max(math.ceil(cfg.steps / batch), 8)
    devices = jax.local_devices()
    ndev = len(devices) if batch > 1 and batch % len(devices) == 0 else 1
    key = jax.random.PRNGKey(cfg.seed)
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, batch), params)
    rollout = make_scan_rollout(env, params, batch // ndev, length, cfg.final_obs)
    if ndev > 1:
        rollout = shard_rollout(rollout, devices)
        key = jax.random.split(key, ndev)
    t0 = time.perf_counter()
    compiled = jax.jit(rollout, donate_argnums=(1,)).lower(key, state).compile()
    compile_s = time.perf_counter() - t0
    mem, mem_src = _compiled_memory(compiled)
    carry = [key, state]

    def call():
        carry[0], carry[1], total = compiled(carry[0], carry[1])
        return total

    secs = _time_compiled(call, cfg.repeats)
    dev_peak = _device_peak()
    if dev_peak is not None:
        mem, mem_src = dev_peak, "device peak_bytes_in_use"
    steps_timed = length * batch
    rate = steps_timed / _median(secs)
    impl = "jax-b1-scan" if batch == 1 else f"jax-b{batch}"
    return Measurement(
        grid=grid, impl=impl, batch=batch, steps_timed=steps_timed, repeats=cfg.repeats,
        seconds=[round(s, 5) for s in secs], steps_per_s=rate, time_for_steps_s=cfg.steps / rate,
        compile_s=compile_s, peak_memory_bytes=mem, memory_source=mem_src, devices=ndev,
    )  # fmt: skip


# --------------------------------------------------------------------------- driver
def check_targets(results: Sequence[Measurement], cfg: BenchConfig) -> list[dict[str, Any]]:
    """The issue's targets against the measured figures (skipped when not measured)."""
    by = {(r.grid, r.impl): r for r in results}
    out = []
    jb = by.get((16, "jax-b4096"))
    if jb:
        out.append({
            "target": "JAX grid 16, 4,096 envs >= 1,000,000 steps/s",
            "measured": round(jb.steps_per_s), "met": jb.steps_per_s >= TARGET_STEPS_PER_S,
        })  # fmt: skip
    npr = by.get((16, "numpy"))
    if jb and npr:
        ratio = jb.steps_per_s / npr.steps_per_s
        out.append({
            "target": "JAX 4,096 envs over NumPy twin at grid 16 >= 100x",
            "measured": round(ratio, 1), "met": ratio >= TARGET_SPEEDUP,
        })  # fmt: skip
    j4 = by.get((4, "jax-b4096"))
    if jb and j4:
        growth = j4.steps_per_s / jb.steps_per_s
        out.append({
            "target": "JAX cost growth grid 4 -> 16 (4,096 envs) < 2x",
            "measured": round(growth, 2), "met": growth < TARGET_GROWTH,
        })  # fmt: skip
    batched = [r for r in results if r.impl.startswith("jax-b") and r.batch > 1 and r.compile_s]
    if batched:
        worst = max(r.compile_s for r in batched)
        out.append({
            "target": "compile time of the batched step < 10 s",
            "measured": round(worst, 2), "met": worst < TARGET_COMPILE_S,
        })  # fmt: skip
    return out


def run_bench(cfg: BenchConfig, progress: Callable[[str], None] | None = None) -> BenchReport:
    """Run every measurement of ``cfg``; the two Python-driven loops share half the time budget."""

    say = progress or (lambda _msg: None)
    report = BenchReport(config=asdict(cfg), machine=machine_info())
    report.config["grids"] = list(cfg.grids)
    report.config["batches"] = list(cfg.batches)
    slow_cap = max(0.5, 0.5 * cfg.budget_s / (2 * len(cfg.grids) * (cfg.repeats + 1)))
    for grid in cfg.grids:
        say(f"grid {grid}: NumPy twin")
        report.results.append(bench_numpy(grid, cfg, slow_cap))
        say(f"grid {grid}: JAX, 1 env, jitted step from Python")
        report.results.append(bench_jax_python_loop(grid, cfg, slow_cap))
        say(f"grid {grid}: JAX, 1 env, lax.scan")
        report.results.append(bench_jax_scan(grid, 1, cfg))
        for batch in cfg.batches:
            say(f"grid {grid}: JAX, {batch} envs, vmap + lax.scan")
            report.results.append(bench_jax_scan(grid, batch, cfg))
    report.targets = check_targets(report.results, cfg)
    return report


def write_outputs(report: BenchReport, out_dir: Path,
                  warn: Callable[[str], None] | None = None) -> dict[str, Path]:  # fmt: skip
    """bench.json, then its pictures (``bench.pictures``): bench_time_100k.png (the paper's figure)
    and bench_batch.png; the files written. A picture that fails is left out and told to ``warn``
    (default: ``warnings.warn``), never a lost result."""
    import warnings

    from quicknav_core.bench.pictures import draw_batch, draw_time
    from quicknav_core.drawing import draw_safely

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "bench.json"}
    paths["json"].write_text(json.dumps(report.to_json(), indent=2))
    for key, name, draw in (("time_png", "bench_time_100k.png", draw_time),
                            ("batch_png", "bench_batch.png", draw_batch)):  # fmt: skip
        warning = draw_safely(out_dir / name, lambda path, draw=draw: draw(report, path))
        if warning is None:
            paths[key] = out_dir / name
        else:
            (warn or warnings.warn)(warning)
    return paths


def format_table(report: BenchReport) -> list[list[str]]:
    """Rows for the terminal table."""
    rows = []
    for r in report.results:
        rows.append([
            f"{r.grid}x{r.grid}", r.impl, f"{r.batch:,}", f"{r.steps_per_s:,.0f}",
            f"{r.time_for_steps_s:.3g}", "" if r.compile_s is None else f"{r.compile_s:.2f}",
            "" if r.peak_memory_bytes is None else f"{r.peak_memory_bytes / 2**20:.2f}",
            str(r.devices), r.note,
        ])  # fmt: skip
    return rows
