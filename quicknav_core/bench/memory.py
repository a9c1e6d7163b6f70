"""Admission against reality: a job's estimated peak memory (``train.memory``, what the service
admits jobs by) beside the peak RSS of a process that runs it as a worker does (build, compile,
train a few chunks, write checkpoints), for every network kind and algorithm at two sizes; and
evaluations on maps from 45 to 203 cells a side (``EVAL_CASES``: 100 episodes of a baseline with
the building preset's sensors, its pictures written, as an eval job runs); and the gRPC server's
streams: a Rollout stream of a few to many envs (``ROLLOUT_CASES``) and a Policy stream of every
network kind acting for one stream's most robots (``POLICY_CASES``).

    uv run python -m quicknav_core.bench.memory [--out benchmarks/results/memory.json] [--case NAME]

Each case runs in a fresh process (``peak_rss`` reads its ``ru_maxrss``); ``tests/core/train/
test_memory_admission.py`` holds every training case's estimate to within 10 % of its recorded
measurement and, in the slow suite, measures the larger size of each kind again; README quotes the
tables. The large evaluations take long (about half an hour at grid 203 on 2 cores): benchmark only;
``tests/core/train/test_eval_memory.py`` holds the estimate to their recorded measurements, and
``tests/core/train/test_stream_memory.py`` the streams' estimates to theirs.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

MB = 2**20

# (case, preset, overrides): every algorithm and network kind, a small and a large size each
CASES: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("ppo-mlp-256", "paper-ppo", {"num_envs": 256, "algorithm.num_steps": 64}),
    ("ppo-mlp-2048", "paper-ppo", {"num_envs": 2048, "algorithm.num_steps": 64}),
    ("sac-100k", "paper-sac", {"algorithm.buffer_size": 100_000}),
    ("sac-1m", "paper-sac", {"algorithm.buffer_size": 1_000_000}),
    ("td3-50k", "paper-td3", {"algorithm.buffer_size": 50_000}),
    ("td3-1m", "paper-td3", {"algorithm.buffer_size": 1_000_000}),
    ("mlp-memory-256", "paper-mlp", {"num_envs": 256}),
    ("mlp-memory-1024", "paper-mlp", {"num_envs": 1024}),
    ("lstm-256", "paper-lstm", {"num_envs": 256}),
    ("lstm-1024", "paper-lstm", {"num_envs": 1024}),
    ("gtrxl-512", "paper-gtrxl", {"num_envs": 512}),
    ("gtrxl-2048", "paper-gtrxl", {"num_envs": 2048}),
)

# (case, map, cell size in metres, baseline): 100 episodes each; the oracle and DWA keep every
# episode's plan (two distance fields over 5 x 5 nodes per cell) for the whole episode
EVAL_CASES: tuple[tuple[str, str, float, str], ...] = (
    ("eval-office-oracle", "examples/maps/office.yaml", 0.5, "oracle"),
    ("eval-warehouse-0.5m-oracle", "examples/maps/slam/warehouse.yaml", 0.5, "oracle"),
    ("eval-warehouse-0.25m-oracle", "examples/maps/slam/warehouse.yaml", 0.25, "oracle"),
)
EVAL_EPISODES = 100

# (case, preset, envs): a gRPC Rollout stream of the preset's env (the demo's small rooms; the
# building preset's plan and people), at a few and at many envs
ROLLOUT_CASES: tuple[tuple[str, str, int], ...] = (
    ("rollout-demo-64", "demo", 64),
    ("rollout-demo-4096", "demo", 4096),
    ("rollout-demo-16384", "demo", 16384),
    ("rollout-building-256", "building", 256),
    ("rollout-building-4096", "building", 4096),
)
# (case, preset, envs per stream, streams): several Rollout streams open at once in one server,
# stepped side by side as its executor threads step them; admitted together by
# ``train.memory.together`` (QUICKNAV_ROLLOUT_MEMORY_MB)
ROLLOUT_TOGETHER_CASES: tuple[tuple[str, str, int, int], ...] = (
    ("rollout-building-4096-x4", "building", 4096, 4),
    ("rollout-demo-4096-x16", "demo", 4096, 16),
)
ROLLOUT_STEPS = 20
# each stream case runs twice and the higher peak counts: the same rollout case read 468 and 513 MB
# in two runs (XLA compiles in threads, and how their work overlaps varies), and admission must
# cover the higher
STREAM_RUNS = 2

# (case, preset): a Policy stream serving a policy of every network kind (trained a few updates,
# as a job's run folder holds it), acting for one stream's most robots (POLICY_MAX_ROWS)
POLICY_CASES: tuple[tuple[str, str], ...] = (
    ("policy-demo-mlp", "demo"),
    ("policy-building-mlp", "building"),
    ("policy-mlp-memory", "paper-mlp"),
    ("policy-lstm", "paper-lstm"),
    ("policy-gtrxl", "paper-gtrxl"),
)

# both import what the gRPC server's process imports (quicknav_service.rollout.server) before
# doing what one stream does: build and step the envs (the servicer's BatchedEnv), or load the
# run's policy and act (the Policy servicer's LoadedPolicy and its batcher's jitted act)
_ROLLOUT_CHILD = """
import json, resource, sys
import numpy as np
import quicknav_service.rollout.server  # noqa: F401
from quicknav_core.config import EnvConfig
from quicknav_core.env.batch import BatchedEnv
from quicknav_core.runtime import Runtime
from concurrent.futures import ThreadPoolExecutor
case = json.loads(sys.argv[1])
runtime, n = Runtime(), case["num_envs"]  # one runtime, as the server's streams share it
envs = [BatchedEnv(EnvConfig.model_validate(case["env"]), n, seed=i, split="train", runtime=runtime)
        for i in range(case.get("streams", 1))]
rng = np.random.default_rng(0)
with ThreadPoolExecutor(len(envs)) as pool:
    list(pool.map(lambda env: env.reset(), envs))
    for _ in range(case["steps"]):
        actions = [rng.uniform(-1.0, 1.0, (n, 2)).astype(np.float32) for _ in envs]
        list(pool.map(lambda pair: pair[0].step(pair[1]), zip(envs, actions)))
print(json.dumps({"peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""

_POLICY_CHILD = """
import json, resource, sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
import numpy as np
import quicknav_service.rollout.server  # noqa: F401
from quicknav_core.train.run import load_policy
from quicknav_service.rollout.policy import LoadedPolicy
case = json.loads(sys.argv[1])
config, policy, meta = load_policy(Path(case["run_dir"]))
rows, obs_dim = case["rows"], config.env.obs_dim
loaded = LoadedPolicy(policy, obs_dim, "{}", ThreadPoolExecutor(1))
carry = loaded.initial(rows)
rng = np.random.default_rng(0)
for i in range(5):
    obs = rng.uniform(-1.0, 1.0, (rows, obs_dim)).astype(np.float32)
    [(carry, actions)] = loaded._run([(carry, obs, np.full(rows, i == 0))])
print(json.dumps({"peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""

_EVAL_CHILD = """
import json, resource, sys, tempfile
from pathlib import Path
from quicknav_core.config import EvalConfig
from quicknav_core.eval.evaluate import run_eval
cfg = EvalConfig.model_validate_json(sys.argv[1])
with tempfile.TemporaryDirectory() as out:
    run_eval(cfg, Path(out))
print(json.dumps({"peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""

_CHILD = """
import json, resource, sys, tempfile
from quicknav_core.config import resolve_train
from quicknav_core.train.run import train_run
request = json.loads(sys.argv[1])
cfg = resolve_train(request)
with tempfile.TemporaryDirectory() as run_dir:
    train_run(cfg, run_dir)
print(json.dumps({"peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
"""


def case_request(preset: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """The train request of a case: a few chunks of its config, a checkpoint after each."""
    from quicknav_core.config import resolve_train

    base = resolve_train({"preset": preset, "overrides": overrides})
    per_update = base.steps_per_update
    units = 3 if base.trainer_kind.startswith("rejax-") and preset != "paper-ppo" else 2
    steps = max(per_update * 2, 4096 * units)
    return {"preset": preset, "overrides": {**overrides, "total_steps": steps,
                                             "chunk_steps": max(per_update, steps // 3)}}  # fmt: skip


# a persistent compilation cache would hand the process programs compiled before and hide the
# compile's peak (measured: sac-100k peaks at 1,235 MB cold and 996 MB from a warm cache), so the
# measured process always compiles, as a worker's first job of a kind does
_CACHE_VARIABLES = ("JAX_COMPILATION_CACHE_DIR", "QUICKNAV_JAX_CACHE")


def _child_peak(script: str, argument: str, env: dict[str, str] | None, timeout: float) -> int:
    """Peak resident bytes of a fresh Python process running ``script`` with ``argument``,
    compiling every program (no persistent compilation cache)."""
    child_env = {k: v for k, v in (os.environ if env is None else env).items()
                 if k not in _CACHE_VARIABLES}  # fmt: skip
    done = subprocess.run([sys.executable, "-c", script, argument], capture_output=True, text=True,
                          env=child_env, timeout=timeout)  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"case failed:\n{done.stderr[-3000:]}")
    return int(json.loads(done.stdout.strip().splitlines()[-1])["peak_rss"])


def peak_rss(request: dict[str, Any], env: dict[str, str] | None = None) -> int:
    """Peak resident bytes of a fresh process that trains ``request`` into a temporary folder."""
    return _child_peak(_CHILD, json.dumps(request), env, timeout=1800)


def eval_case(map_path: str, cell_m: float, policy: str, episodes: int = EVAL_EPISODES):
    """The EvalConfig of an evaluation case: ``policy`` on the map at ``cell_m`` cells with the
    building preset's sensors, the grid and the step limit following the map (as ``quicknav eval
    --map`` gives them)."""
    from quicknav_core.config import EnvConfig, EvalConfig, resolve_train
    from quicknav_core.eval.map_fit import fit_map

    building = resolve_train({"preset": "building"}).env
    grid = building.grid_size
    env = EnvConfig.model_validate({**building.model_dump(), "room_size": grid * cell_m, "obstacles": None})
    where = str(Path(map_path).resolve())
    fit = fit_map(env, where)
    env = EnvConfig.model_validate({**env.model_dump(), **fit.env_overrides(where)})
    return EvalConfig(policy=policy, env=env, episodes=episodes)


def eval_peak_rss(cfg) -> int:
    """Peak resident bytes of a fresh process that runs the evaluation ``cfg`` (pictures written)."""
    return _child_peak(_EVAL_CHILD, cfg.model_dump_json(), None, timeout=7200)


def rollout_case(preset: str, num_envs: int, streams: int = 1) -> dict[str, Any]:
    """What a Rollout case's process is given: the preset's env, each stream's envs, streams."""
    from quicknav_core.config import resolve_train

    env = resolve_train({"preset": preset}).env
    return {"env": env.model_dump(mode="json"), "num_envs": num_envs, "steps": ROLLOUT_STEPS,
            "streams": streams}  # fmt: skip


def rollout_estimate(case: dict[str, Any]):
    """What admission holds the case's streams to, together (one server's runtime)."""
    from quicknav_core.config import EnvConfig
    from quicknav_core.train.memory import rollout_memory, together

    one = rollout_memory(EnvConfig.model_validate(case["env"]), case["num_envs"])
    return together([one] * case["streams"])


def run_rollout_cases(cases=ROLLOUT_CASES + ROLLOUT_TOGETHER_CASES) -> list[dict[str, Any]]:
    rows = []
    for name, preset, num_envs, *streams in cases:
        case = rollout_case(preset, num_envs, *streams)
        runs = [_child_peak(_ROLLOUT_CHILD, json.dumps(case), None, timeout=1800) for _ in range(STREAM_RUNS)]
        what = {"preset": preset, "num_envs": num_envs, **({"streams": streams[0]} if streams else {})}
        rows.append(_row(name, what, rollout_estimate(case), runs))
    return rows


def policy_run(preset: str, run_dir: Path) -> Path:
    """A run folder of ``preset`` trained a few updates (a fresh process, its own compiles)."""
    script = ("import sys; from quicknav_core.config import resolve_train; from quicknav_core.train.run"
              " import train_run; train_run(resolve_train({'preset': sys.argv[1], 'overrides':"
              " {'num_envs': 64, 'total_steps': 4096}}), sys.argv[2])")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", script, preset, str(run_dir)], capture_output=True,
                          text=True, timeout=1800)  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"training {preset} failed:\n{done.stderr[-3000:]}")
    return run_dir


def run_policy_cases(cases=POLICY_CASES) -> list[dict[str, Any]]:
    from quicknav_core.config import resolve_train
    from quicknav_core.train.memory import POLICY_MAX_ROWS, policy_memory

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name, preset in cases:
            run_dir = policy_run(preset, Path(folder) / name)
            est = policy_memory(resolve_train({"preset": preset}))
            case = {"run_dir": str(run_dir), "rows": POLICY_MAX_ROWS}
            runs = [_child_peak(_POLICY_CHILD, json.dumps(case), None, timeout=1800)
                    for _ in range(STREAM_RUNS)]  # fmt: skip
            rows.append(_row(name, {"preset": preset, "rows": POLICY_MAX_ROWS}, est, runs))
    return rows


def _row(name: str, what: dict[str, Any], est, runs: list[int]) -> dict[str, Any]:
    measured = max(runs)
    print(f"{name:<28} estimate {est.total / MB:7.0f} MB  measured {measured / MB:7.0f} MB"
          f"  ratio {est.total / measured:.2f}", flush=True)
    return {"case": name, **what, "estimate_mb": round(est.total / MB),
            "estimate_parts": est.describe(), "measured_mb": round(measured / MB),
            "measured_runs_mb": [round(r / MB) for r in runs],
            "ratio": round(est.total / measured, 3)}  # fmt: skip


def estimate(request: dict[str, Any]) -> int:
    from quicknav_core.config import resolve_train
    from quicknav_core.train.memory import train_memory

    return train_memory(resolve_train(request)).total


def run_eval_cases(cases=EVAL_CASES) -> list[dict[str, Any]]:
    from quicknav_core.train.memory import eval_memory

    rows = []
    for name, map_path, cell_m, policy in cases:
        cfg = eval_case(map_path, cell_m, policy)
        est = eval_memory(cfg)
        measured = eval_peak_rss(cfg)
        rows.append({"case": name, "map": map_path, "cell_m": cell_m, "policy": policy,
                     "episodes": cfg.episodes, "grid_size": cfg.env.grid_size,
                     "grid": list(cfg.env.grid_shape),
                     "max_steps": cfg.env.max_steps, "estimate_mb": round(est.total / MB),
                     "estimate_parts": est.describe(), "measured_mb": round(measured / MB),
                     "ratio": round(est.total / measured, 3)})  # fmt: skip
        print(f"{name:<28} grid {cfg.env.grid_size:>3} estimate {est.total / MB:7.0f} MB  measured"
              f" {measured / MB:7.0f} MB  ratio {est.total / measured:.2f}", flush=True)
    return rows


def run(cases=CASES) -> list[dict[str, Any]]:
    rows = []
    for name, preset, overrides in cases:
        request = case_request(preset, overrides)
        measured, est = peak_rss(request), estimate(request)
        rows.append({"case": name, "preset": preset, "overrides": overrides,
                     "estimate_mb": round(est / MB), "measured_mb": round(measured / MB),
                     "ratio": round(est / measured, 3)})  # fmt: skip
        print(f"{name:<16} estimate {est / MB:7.0f} MB  measured {measured / MB:7.0f} MB"
              f"  ratio {est / measured:.2f}", flush=True)
    return rows


def main() -> None:
    import argparse

    from quicknav_core.bench.machine import machine_info

    groups = (CASES, EVAL_CASES, ROLLOUT_CASES, ROLLOUT_TOGETHER_CASES, POLICY_CASES)
    names = [c[0] for group in groups for c in group]
    ap = argparse.ArgumentParser(description="Memory admission's estimates beside measured peaks.")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/memory.json"))
    ap.add_argument("--case", action="append", choices=names, metavar="NAME",
                    help=f"only these cases (repeat it): {', '.join(names)}")  # fmt: skip
    args = ap.parse_args()
    chosen = [c for c in CASES if not args.case or c[0] in args.case]
    evals = [c for c in EVAL_CASES if not args.case or c[0] in args.case]
    rollouts = [c for c in ROLLOUT_CASES + ROLLOUT_TOGETHER_CASES if not args.case or c[0] in args.case]
    policies = [c for c in POLICY_CASES if not args.case or c[0] in args.case]
    rows, eval_rows = run(chosen), run_eval_cases(evals)
    rollout_rows, policy_rows = run_rollout_cases(rollouts), run_policy_cases(policies)
    # a run of some cases keeps the others' rows (the large evaluations take long)
    kept = json.loads(args.out.read_text()) if args.case and args.out.exists() else {}

    def merged(old: list[dict[str, Any]], new: list[dict[str, Any]], order) -> list[dict[str, Any]]:
        by_case = {r["case"]: r for r in old} | {r["case"]: r for r in new}
        return [by_case[c[0]] for c in order if c[0] in by_case]

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine_info(),
                                    "rows": merged(kept.get("rows", []), rows, CASES),
                                    "eval_rows": merged(kept.get("eval_rows", []), eval_rows, EVAL_CASES),
                                    "rollout_rows": merged(kept.get("rollout_rows", []), rollout_rows,
                                                           ROLLOUT_CASES + ROLLOUT_TOGETHER_CASES),
                                    "policy_rows": merged(kept.get("policy_rows", []), policy_rows,
                                                          POLICY_CASES)},
                                   indent=2))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    with tempfile.TemporaryDirectory():
        main()
