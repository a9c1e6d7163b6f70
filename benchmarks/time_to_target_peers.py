"""The peers of `quicknav bench time-to-target`: what a user would pick instead, same protocol.

- PPO row: Stable-Baselines3's PPO (PyTorch, CPU) with a 2x128 MLP and its default
  hyperparameters, on 8 copies of QuickNav's NumPy twin (`DummyVecEnv`), the `paper-ppo` env.
- LSTM row: sb3-contrib's RecurrentPPO (`MlpLstmPolicy`, defaults) on 8 twins of the LSTM row's env
  (goal hidden, the paper's LSTM reward weights).

Protocol as `quicknav_core/bench/time_to_target.py`: the clock starts when the model is built and
runs through every rollout and update; when the training time has grown by 10 % (+1 s) since the
last evaluation, the policy plays 100 held-out episodes in the twin on the same test bank as
QuickNav's (deterministic; the evaluation's time is not counted); the run stops at the first
evaluation with success >= 90 % or at the cap (30 min).

The peers stay out of QuickNav's dependencies. Their environment (PyTorch's CPU build from this
machine's wheel; uv would fetch a CUDA build of several GB):

    python3 -m venv .peers
    .peers/bin/pip install torch==2.13.0 stable-baselines3 sb3-contrib pydantic gymnasium scipy
    uv run python benchmarks/time_to_target_peers.py --export-banks .peers/banks     # JAX side
    PYTHONPATH=. .peers/bin/python benchmarks/time_to_target_peers.py --banks .peers/banks \\
        [--row ppo --row lstm] [--seeds 3] [--cap-minutes 30]

writes benchmarks/results/time_to_target_peers.json; `quicknav bench time-to-target --report`
prints it beside QuickNav's rows.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

TARGET, EVAL_EPISODES, EVAL_GROWTH, EVAL_SLACK_S = 0.9, 100, 1.10, 1.0
NUM_ENVS = 8
# peer row -> (QuickNav preset whose env it trains on, the QuickNav row it stands beside)
ROWS = {"ppo": ("paper-ppo", "ppo"), "lstm": ("tuned-lstm", "lstm")}


def env_config(preset: str):
    """The preset's EnvConfig, read without JAX (the presets are plain data)."""
    from quicknav_core.config.presets import get_preset

    return get_preset(preset).env


def export_banks(folder: Path) -> None:
    """The train and test room banks of every peer row, as .npy (needs the JAX side)."""
    from quicknav_core.env.room_sources import make_room_bank

    folder.mkdir(parents=True, exist_ok=True)
    for preset, _ in ROWS.values():
        for split in ("train", "test"):
            np.save(folder / f"{preset}-{split}.npy", np.asarray(make_room_bank(env_config(preset), split)))
    print(f"wrote the room banks to {folder}")


def twin(config, bank: np.ndarray, split: str):
    from quicknav_core.env.numpy_env import QuickNavNumpyEnv

    return QuickNavNumpyEnv(config, split=split, rooms=bank)


def evaluate(model, config, test_bank: np.ndarray, recurrent: bool) -> float:
    """Held-out success of ``model`` over EVAL_EPISODES twin episodes, all stepped together."""
    envs = [twin(config, test_bank, "test") for _ in range(EVAL_EPISODES)]
    obs = np.stack([e.reset(seed=10_000 + i)[0] for i, e in enumerate(envs)])
    alive = np.ones(EVAL_EPISODES, bool)
    success = np.zeros(EVAL_EPISODES, bool)
    state, starts = None, np.ones(EVAL_EPISODES, bool)
    while alive.any():
        if recurrent:
            actions, state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
            starts = np.zeros(EVAL_EPISODES, bool)
        else:
            actions, _ = model.predict(obs, deterministic=True)
        for i in np.flatnonzero(alive):
            o, _, term, trunc, info = envs[i].step(actions[i])
            obs[i] = o
            if term or trunc:
                alive[i] = False
                success[i] = bool(info["goal_reached"])
    return float(success.mean())


def run_one(row: str, seed: int, banks: Path, cap_s: float, threads: int) -> dict:
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv

    torch.set_num_threads(threads)
    preset, _ = ROWS[row]
    config = env_config(preset)
    train_bank = np.load(banks / f"{preset}-train.npy")
    test_bank = np.load(banks / f"{preset}-test.npy")
    vec = DummyVecEnv([lambda: twin(config, train_bank, "train") for _ in range(NUM_ENVS)])
    vec.seed(seed)
    t0 = time.perf_counter()
    if row == "ppo":
        from stable_baselines3 import PPO

        model = PPO("MlpPolicy", vec, policy_kwargs={"net_arch": [128, 128]}, seed=seed,
                    device="cpu", verbose=0)  # fmt: skip
    else:
        from sb3_contrib import RecurrentPPO

        model = RecurrentPPO("MlpLstmPolicy", vec, seed=seed, device="cpu", verbose=0)
    per_update = model.n_steps * NUM_ENVS
    result = {"row": row, "seed": seed, "cap_s": cap_s, "reached": False, "time_to_target_s": None,
              "steps_to_target": None, "train_s": 0.0, "eval_s": 0.0, "evaluations": []}  # fmt: skip
    last_eval = 0.0
    while result["train_s"] < cap_s:
        model.learn(total_timesteps=per_update, reset_num_timesteps=False)
        result["train_s"] = time.perf_counter() - t0 - result["eval_s"]
        if result["train_s"] < last_eval * EVAL_GROWTH + EVAL_SLACK_S:
            continue
        e0 = time.perf_counter()
        success = evaluate(model, config, test_bank, recurrent=row != "ppo")
        spent = time.perf_counter() - e0
        result["eval_s"] += spent
        last_eval = result["train_s"]
        result["evaluations"].append({"train_s": round(result["train_s"], 3),
                                      "env_steps": int(model.num_timesteps), "success": success,
                                      "eval_s": round(spent, 3)})  # fmt: skip
        print(f"  {row} s{seed}: {model.num_timesteps:,} steps, {result['train_s']:.1f} s,"
              f" held-out success {success:.0%}", flush=True)
        if success >= TARGET:
            result.update(reached=True, time_to_target_s=result["train_s"],
                          steps_to_target=int(model.num_timesteps))  # fmt: skip
            break
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--export-banks", type=Path, help="write the room banks here (JAX side) and exit")
    ap.add_argument("--banks", type=Path, help="the folder --export-banks wrote")
    ap.add_argument("--row", action="append", choices=sorted(ROWS))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--cap-minutes", type=float, default=30.0)
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="PyTorch's threads (small networks: 1 was the fastest here)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/time_to_target_peers.json")
    args = ap.parse_args()
    if args.export_banks:
        export_banks(args.export_banks)
        return
    if not args.banks:
        ap.error("--banks is required (write them first with --export-banks)")
    import sb3_contrib
    import stable_baselines3
    import torch

    data = json.loads(args.out.read_text()) if args.out.exists() else {"rows": {}}
    data["machine"] = {"cpu": _cpu(), "cores": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
                       "stable_baselines3": stable_baselines3.__version__,
                       "sb3_contrib": sb3_contrib.__version__,
                       "torch_threads": args.torch_threads}  # fmt: skip
    for row in args.row or sorted(ROWS):
        runs = [run_one(row, seed, args.banks, args.cap_minutes * 60, args.torch_threads)
                for seed in range(args.seeds)]  # fmt: skip
        times = [r["time_to_target_s"] for r in runs if r["reached"]]
        data["rows"][row] = {
            "label": {"ppo": "Stable-Baselines3 PPO (PyTorch, MLP 2x128), 8 NumPy twins",
                      "lstm": "sb3-contrib RecurrentPPO (PyTorch, MlpLstmPolicy), 8 NumPy twins"}[row],
            "beside": ROWS[row][1], "env_preset": ROWS[row][0], "runs": runs,
            "summary": {"runs": len(runs), "reached": len(times),
                        "median_s": statistics.median(times) if len(times) == len(runs) else None,
                        "min_s": min(times) if times else None, "max_s": max(times) if times else None,
                        "times_s": [r["time_to_target_s"] for r in runs]},
        }  # fmt: skip
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(data, indent=2))
        print(f"{row}: {data['rows'][row]['summary']}")
    print(f"wrote {args.out}")


def _cpu() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


if __name__ == "__main__":
    main()
