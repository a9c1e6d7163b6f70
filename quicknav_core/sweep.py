"""Hyperparameter sweeps with Optuna, many trials per compiled program.

Optuna's ask-and-tell interface hands out ``parallel`` trials at a time. Their configs are grouped
by everything that fixes array shapes; trials in a group differ only in traced numbers (learning
rate, gamma, lambda, clip, coefficients, reward weights, ...) and train side by side in one
vmapped, jit-compiled program (one compile for the whole group). Every trial trains with the base
seed, so a batched trial equals the same trial trained alone.

Each finished trial is evaluated on the *train* room bank with its own episode seed (sweeps never
look at the held-out test bank) and told to the study; a trial that raises is told as failed and
its error kept in the trial's user attributes. Storage: an SQLite file (resumable: rerunning the
same command continues the study) or, with a Redis URL, Optuna's journal storage on Redis so several
workers share a study.
"""

from __future__ import annotations

import csv
import json
import math
import time
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from quicknav_core.config import TrainConfig

# --------------------------------------------------------------------------- config


class ParamSpec(BaseModel):
    """One dimension of a search space."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    type: Literal["float", "log_float", "int", "categorical"]
    low: float | None = None
    high: float | None = None
    choices: list[Any] | None = None

    @model_validator(mode="after")
    def _check(self) -> ParamSpec:
        if self.type == "categorical":
            if not self.choices:
                raise ValueError("categorical parameter needs a non-empty 'choices' list")
            return self
        if self.low is None or self.high is None:
            raise ValueError(f"{self.type} parameter needs 'low' and 'high'")
        if self.low > self.high:
            raise ValueError(f"low={self.low} > high={self.high}; allowed: low <= high")
        if self.type == "log_float" and self.low <= 0:
            raise ValueError(f"log_float needs low > 0 (got low={self.low})")
        return self


def _f(lo, hi):
    return {"type": "float", "low": lo, "high": hi}


def _cat(*choices):
    return {"type": "categorical", "choices": list(choices)}


_REWARDS = {
    "env.reward.step_penalty": _f(0.01, 0.5),
    "env.reward.progress_reward": _f(0.1, 1.0),
    "env.reward.cycle_penalty": _f(0.001, 0.5),
}
# The paper's appendix, parameter by parameter.
BUILTIN_SPACES: dict[str, dict[str, dict[str, Any]]] = {
    "ppo": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.num_minibatches": _cat(16, 32, 64, 128, 256),
        "algorithm.num_steps": _cat(64, 128, 256, 512),
        "algorithm.gae_lambda": _f(0.9, 1.0),
        "algorithm.ent_coef": _f(0.0, 0.1),
        "algorithm.clip_eps": _f(0.1, 0.3),
        "algorithm.gamma": _f(0.9, 0.999),
    },
    "sac": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.batch_size": _cat(64, 128, 256, 512),
        "algorithm.buffer_size": _cat(50_000, 100_000, 200_000, 500_000),
        "algorithm.polyak": _f(0.9, 0.999),
        "algorithm.target_entropy_ratio": _f(0.5, 1.0),
        "algorithm.target_update_freq": _cat(1, 2, 3, 4),
        "algorithm.gamma": _f(0.9, 0.999),
    },
    "td3": {
        "algorithm.learning_rate": {"type": "log_float", "low": 1e-5, "high": 1e-3},
        "algorithm.exploration_noise": _f(0.1, 0.5),
        "algorithm.buffer_size": _cat(50_000, 100_000, 200_000, 500_000),
        "algorithm.batch_size": _cat(64, 128, 256, 512),
        "algorithm.polyak": _f(0.9, 0.999),
        "algorithm.target_noise": _f(0.1, 0.4),
        "algorithm.policy_delay": _cat(1, 2, 3, 4),
    },
    "mlp": {
        "network.hidden_layers": {"type": "int", "low": 1, "high": 3},
        "network.hidden_size": _cat(64, 128, 256),
        **_REWARDS,
    },
    "lstm": {
        "network.num_layers": {"type": "int", "low": 2, "high": 10},
        "network.hidden_size": {"type": "int", "low": 5, "high": 16},
        **_REWARDS,
    },
    "gtrxl": {
        "network.embed_size": _cat(8, 16),
        "network.head_size": {"type": "int", "low": 1, "high": 8},
        "network.num_layers": {"type": "int", "low": 2, "high": 5},
        **_REWARDS,
    },
}
# Base presets the built-in spaces start from.
SPACE_PRESETS = {"ppo": "paper-ppo", "sac": "paper-sac", "td3": "paper-td3",
                 "mlp": "paper-mlp", "lstm": "paper-lstm", "gtrxl": "paper-gtrxl"}  # fmt: skip

METRICS = {
    "success_rate": ("success_rate", "maximize"),
    "spl": ("spl", "maximize"),
    "steps_to_goal": ("steps_to_goal_failures_as_limit", "minimize"),
    "return": ("return", "maximize"),
    "collisions": ("collisions_per_episode", "minimize"),
}


class SweepConfig(BaseModel):
    """A sweep: base TrainConfig, search space, objective, trials, sampler, pruner, storage."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base: TrainConfig
    space: dict[str, ParamSpec] = Field(min_length=1)
    objective: Literal["success_rate", "spl", "steps_to_goal", "return", "collisions"] = (
        "success_rate"
    )
    direction: Literal["maximize", "minimize"] | None = None  # default: the metric's natural one
    trials: int = Field(20, ge=1, le=100_000)
    parallel: int = Field(
        1, ge=1, le=1024, description="trials asked at once (batched when shapes agree)"
    )
    sampler: Literal["tpe", "random"] = "tpe"
    sampler_seed: int = Field(0, ge=0, le=2**31 - 1)
    pruner: Literal["none", "median"] = "none"
    storage: str | None = Field(
        None, description="None: SQLite file in the sweep folder; redis://... : journal on Redis"
    )
    study_name: str = Field("quicknav", min_length=1, max_length=200)
    eval_episodes: int = Field(50, ge=1, le=10_000)
    eval_seed: int = Field(1000, ge=0, le=2**31 - 1)

    @property
    def resolved_direction(self) -> str:
        return self.direction or METRICS[self.objective][1]

    @model_validator(mode="after")
    def _check_space(self) -> SweepConfig:
        for name, spec in self.space.items():
            probe = spec.choices[0] if spec.type == "categorical" else (
                int(spec.low) if spec.type == "int" else spec.low)  # fmt: skip
            try:
                apply_params(self.base, {name: probe}, validate=False)
            except KeyError as e:
                raise ValueError(f"space: unknown parameter {name!r}: {e.args[0]}") from None
        return self


def builtin_sweep(name: str, **kw) -> SweepConfig:
    """A SweepConfig over a built-in space on its paper preset."""
    from quicknav_core.train.presets import get_preset

    if name not in BUILTIN_SPACES:
        raise ValueError(f"unknown search space {name!r}; built-in: {', '.join(BUILTIN_SPACES)}")
    base = kw.pop("base", None) or get_preset(SPACE_PRESETS[name])
    return SweepConfig(base=base, space=BUILTIN_SPACES[name], **kw)


# --------------------------------------------------------------------------- params -> config
def apply_params(base: TrainConfig, params: dict[str, Any], validate: bool = True) -> TrainConfig:
    """Set dotted-path parameters on the base config. ``network.hidden_layers``/``hidden_size`` of an
    MLP become ``hidden_sizes``. Unknown paths raise KeyError."""
    data = base.model_dump(mode="json")
    mlp_layers = mlp_size = None
    for path, value in params.items():
        if data["network"]["kind"] == "mlp" and path == "network.hidden_layers":
            mlp_layers = int(value)
            continue
        if data["network"]["kind"] == "mlp" and path == "network.hidden_size":
            mlp_size = int(value)
            continue
        node = data
        parts = path.split(".")
        for part in parts[:-1]:
            if not isinstance(node, dict) or part not in node or not isinstance(node[part], dict):
                raise KeyError(f"{part!r} is not a section of the config")
            node = node[part]
        if parts[-1] not in node:
            raise KeyError(
                f"{parts[-1]!r} is not a field of {'.'.join(parts[:-1]) or 'TrainConfig'}"
            )
        node[parts[-1]] = value
    if mlp_layers is not None or mlp_size is not None:
        sizes = data["network"]["hidden_sizes"]
        layers = mlp_layers or len(sizes)
        size = mlp_size or sizes[0]
        data["network"]["hidden_sizes"] = [size] * layers
    return TrainConfig.model_validate(data) if validate else base


TRACED_FIELDS = {
    "algorithm": {
        "learning_rate",
        "gamma",
        "gae_lambda",
        "clip_eps",
        "ent_coef",
        "vf_coef",
        "max_grad_norm",
        "polyak",
        "target_entropy_ratio",
        "exploration_noise",
        "target_noise",
        "target_noise_clip",
    },
    "reward": {
        "exploration_reward",
        "step_penalty",
        "collision_penalty",
        "cycle_penalty",
        "progress_reward",
        "goal_reward",
        "cycle_cap",
    },
}


def canonical(cfg: TrainConfig) -> TrainConfig:
    """The config with every traced number at its default: one template per shape signature."""
    data = cfg.model_dump(mode="json")
    algo_defaults = type(cfg.algorithm)().model_dump(mode="json")
    for k in TRACED_FIELDS["algorithm"]:
        if k in data["algorithm"]:
            data["algorithm"][k] = algo_defaults[k]
    reward_defaults = type(cfg.env.reward)().model_dump(mode="json")
    for k in TRACED_FIELDS["reward"]:
        data["env"]["reward"][k] = reward_defaults[k]
    return TrainConfig.model_validate(data)


def shape_signature(cfg: TrainConfig) -> str:
    """The config with every traced number blanked: trials with equal signatures batch together."""
    data = cfg.model_dump(mode="json")
    for k in TRACED_FIELDS["algorithm"]:
        data["algorithm"].pop(k, None)
    for k in TRACED_FIELDS["reward"]:
        data["env"]["reward"].pop(k, None)
    return json.dumps(data, sort_keys=True)


# --------------------------------------------------------------------------- batched training
# compiled batched programs, reused by later groups with the same shapes and trial count
_COMPILED: dict[Any, Any] = {}


def train_batch(
    configs: list[TrainConfig], on_chunk: Callable[[int, list[dict]], bool] | None = None
):
    """Train configs with one shape signature together. Returns (trainer, per-trial states, metrics).

    Recurrent PPO vmaps over (PPOHyper, EnvParams) inside its state; rejax algorithms are pytrees
    whose traced fields are stacked and vmapped over.
    """
    from quicknav_core.train.recurrent_ppo import PPOHyper
    from quicknav_core.train.stats import summarize
    from quicknav_core.train.trainers import RecurrentPPOTrainer, RejaxTrainer, make_trainer

    sigs = {shape_signature(c) for c in configs}
    if len(sigs) != 1:
        raise ValueError("train_batch needs configs with one shape signature")
    template = make_trainer(canonical(configs[0]))
    k = len(configs)
    env_params = [template.env_params.replace(**_reward_params(c)) for c in configs]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    key = jax.random.PRNGKey(configs[0].seed)
    if isinstance(template, RecurrentPPOTrainer):
        hypers = stack([PPOHyper.from_config(c.algorithm) for c in configs])
        cache_key = ("rppo", shape_signature(configs[0]), k)
        if cache_key not in _COMPILED:
            algo = template.algo
            _COMPILED[cache_key] = (
                jax.jit(jax.vmap(algo.init, in_axes=(None, 0, 0))),
                jax.jit(jax.vmap(lambda s: algo.chunk(s, template.updates_per_chunk))),
            )
        init, chunk = _COMPILED[cache_key]
        states = init(key, hypers, stack(env_params))

        def run(states):
            states, _ = chunk(states)
            return states, jax.vmap(lambda st: st.stats)(states)

        clear = jax.jit(
            jax.vmap(lambda s: s.replace(stats=jax.vmap(lambda x: x.clear_totals())(s.stats)))
        )
    elif isinstance(template, RejaxTrainer):
        # rejax builds its optimiser (a static closure over the learning rate) in init_state, so
        # init and training must sit inside one vmapped call: the group trains in one go.
        steps = template.num_updates * configs[0].steps_per_update
        full = template.algo.replace(total_timesteps=steps, eval_freq=template.steps_per_chunk)

        def trial_algo(c, p):
            # the template's algorithm (same static fields) with this trial's traced numbers
            algo = c.algorithm
            values = {n: jnp.float32(getattr(algo, n)) for n in TRACED_FIELDS["algorithm"]
                      if hasattr(algo, n) and hasattr(full, n)}  # fmt: skip
            return full.replace(env_params=p, **values)

        algos = stack([trial_algo(c, p) for c, p in zip(configs, env_params, strict=True)])
        cache_key = ("rejax", shape_signature(configs[0]), k)
        if cache_key not in _COMPILED:
            _COMPILED[cache_key] = jax.jit(
                jax.vmap(lambda a, key: a.train(key)[0], in_axes=(0, None))
            )
        final = _COMPILED[cache_key](algos, key)
        stats = final.env_state.stats
        per_trial = [summarize(jax.tree.map(lambda x, i=i: x[i], stats)) for i in range(k)]
        if on_chunk:
            on_chunk(0, per_trial)
        unstacked = [jax.tree.map(lambda x, i=i: x[i], final) for i in range(k)]
        return template, unstacked, env_params, [per_trial]
    else:  # pragma: no cover
        raise TypeError(type(template).__name__)
    chunks = template.num_updates // template.updates_per_chunk
    history: list[list[dict]] = []
    for c in range(chunks):
        states, stats = run(states)
        per_trial = [summarize(jax.tree.map(lambda x, i=i: x[i], stats)) for i in range(k)]
        history.append(per_trial)
        states = clear(states)
        if on_chunk and on_chunk(c, per_trial):
            break
    unstacked = [jax.tree.map(lambda x, i=i: x[i], states) for i in range(k)]
    return template, unstacked, env_params, history


def _reward_params(cfg: TrainConfig) -> dict[str, Any]:
    r = cfg.env.reward
    return {
        "step_penalty": np.float32(r.step_penalty), "collision_penalty": np.float32(r.collision_penalty),
        "cycle_penalty": np.float32(r.cycle_penalty), "progress_reward": np.float32(r.progress_reward),
        "goal_reward": np.float32(r.goal_reward), "cycle_cap": np.int32(r.cycle_cap),
        "exploration_reward": np.float32(r.exploration_reward),
    }  # fmt: skip


def evaluate_trial(trainer, state, env_params, cfg: SweepConfig) -> dict[str, Any]:
    """Navigation metrics of one trained trial on the train bank (never the test bank)."""
    from quicknav_core.evaluate import EvalConfig, PolicyAgent, run_episodes, summarize

    ecfg = EvalConfig(episodes=cfg.eval_episodes, seed=cfg.eval_seed, split="train", pictures=False,
                      gif_episodes=0)  # fmt: skip
    ep = run_episodes(trainer.env, env_params, PolicyAgent(trainer.policy(state)), ecfg)
    env_cfg = trainer.config.env
    return summarize(ep, env_cfg.max_steps, env_cfg.max_wheel_speed * env_cfg.dt)


def objective_value(metrics: dict[str, Any], objective: str) -> float:
    value = metrics[METRICS[objective][0]]
    return float(value["mean"] if isinstance(value, dict) else value)


# --------------------------------------------------------------------------- study
def make_storage(cfg: SweepConfig, out_dir: Path):
    import optuna

    if cfg.storage is None:
        return optuna.storages.RDBStorage(f"sqlite:///{(out_dir / 'study.db').resolve()}")
    if cfg.storage.startswith("redis://") or cfg.storage.startswith("rediss://"):
        from optuna.storages import JournalStorage
        from optuna.storages.journal import JournalRedisBackend

        return JournalStorage(JournalRedisBackend(cfg.storage))
    return cfg.storage  # any other Optuna storage URL (e.g. postgresql://)


def _sample(trial, space: dict[str, ParamSpec]) -> dict[str, Any]:
    params = {}
    for name, spec in space.items():
        if spec.type == "float":
            params[name] = trial.suggest_float(name, spec.low, spec.high)
        elif spec.type == "log_float":
            params[name] = trial.suggest_float(name, spec.low, spec.high, log=True)
        elif spec.type == "int":
            params[name] = trial.suggest_int(name, int(spec.low), int(spec.high))
        else:
            params[name] = trial.suggest_categorical(name, spec.choices)
    return params


def run_sweep(
    cfg: SweepConfig, out_dir: Path, progress: Callable[[dict], None] | None = None
) -> dict[str, Any]:
    """Run (or continue) a study until it has ``cfg.trials`` finished trials; write the outputs."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "sweep_config.json").write_text(cfg.model_dump_json(indent=2))
    sampler = (optuna.samplers.TPESampler(seed=cfg.sampler_seed) if cfg.sampler == "tpe"
               else optuna.samplers.RandomSampler(seed=cfg.sampler_seed))  # fmt: skip
    pruner = optuna.pruners.MedianPruner() if cfg.pruner == "median" else optuna.pruners.NopPruner()
    study = optuna.create_study(
        study_name=cfg.study_name, storage=make_storage(cfg, out_dir), sampler=sampler, pruner=pruner,
        direction=cfg.resolved_direction, load_if_exists=True,
    )  # fmt: skip
    # trials left running by an interrupted earlier run are failed, not lost
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        study.tell(t.number, state=optuna.trial.TrialState.FAIL)
    finished_states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED,
                       optuna.trial.TrialState.FAIL)  # fmt: skip
    timings = []
    while True:
        done = len(study.get_trials(deepcopy=False, states=finished_states))
        if done >= cfg.trials:
            break
        asked = [study.ask() for _ in range(min(cfg.parallel, cfg.trials - done))]
        groups: dict[str, list[tuple[Any, TrainConfig]]] = {}
        for trial in asked:
            try:
                tcfg = apply_params(cfg.base, _sample(trial, cfg.space))
            except Exception as e:
                trial.set_user_attr("error", f"{type(e).__name__}: {e}")
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
                continue
            groups.setdefault(shape_signature(tcfg), []).append((trial, tcfg))
        for members in groups.values():
            t0 = time.perf_counter()
            trials = [m[0] for m in members]
            try:

                def on_chunk(c, per_trial, trials=trials):
                    for tr, m in zip(trials, per_trial, strict=True):
                        tr.report(m.get("success_rate", float("nan")), c)
                    return all(tr.should_prune() for tr in trials) and cfg.pruner != "none"

                trainer, states, env_params, _ = train_batch([m[1] for m in members], on_chunk)
                for trial, state, params in zip(trials, states, env_params, strict=True):
                    metrics = evaluate_trial(trainer, state, params, cfg)
                    value = objective_value(metrics, cfg.objective)
                    trial.set_user_attr("metrics", json.loads(json.dumps(metrics, default=float)))
                    if math.isnan(value):
                        trial.set_user_attr(
                            "error", f"objective {cfg.objective} is NaN (no successes)"
                        )
                        study.tell(trial, state=optuna.trial.TrialState.FAIL)
                    else:
                        study.tell(trial, value)
            except Exception as e:
                msg = f"{type(e).__name__}: {e}"
                for trial in trials:
                    trial.set_user_attr("error", msg)
                    trial.set_user_attr("traceback", traceback.format_exc()[-4000:])
                    study.tell(trial, state=optuna.trial.TrialState.FAIL)
            timings.append({"trials": len(members), "seconds": time.perf_counter() - t0})
            if progress:
                best = _best(study)
                stop = progress({"finished": len(study.get_trials(deepcopy=False, states=finished_states)),
                                 "total": cfg.trials, "best_value": best[0], "best_params": best[1]})  # fmt: skip
                if stop:  # the caller asked to stop between groups (cancel, shutdown)
                    summary = write_outputs(study, cfg, out_dir)
                    summary["timings"] = timings
                    summary["stopped"] = True
                    return summary
    summary = write_outputs(study, cfg, out_dir)
    summary["timings"] = timings
    return summary


def _best(study) -> tuple[float | None, dict | None]:
    try:
        return study.best_value, study.best_params
    except ValueError:
        return None, None


def write_outputs(study, cfg: SweepConfig, out_dir: Path) -> dict[str, Any]:
    """best_params.json, best_config.json, trials.csv and the Optuna plots (PNG)."""
    import optuna

    trials = study.get_trials(deepcopy=False)
    with open(out_dir / "trials.csv", "w", newline="") as f:
        names = sorted({k for t in trials for k in t.params})
        w = csv.writer(f)
        w.writerow(["number", "state", "value", *names, "error"])
        for t in trials:
            w.writerow([t.number, t.state.name, t.value, *[t.params.get(n) for n in names],
                        t.user_attrs.get("error", "")])  # fmt: skip
    best_value, best_params = _best(study)
    out = {"study": study.study_name, "trials": len(trials), "best_value": best_value,
           "best_params": best_params, "direction": cfg.resolved_direction, "objective": cfg.objective}  # fmt: skip
    if best_params is not None:
        (out_dir / "best_params.json").write_text(
            json.dumps({"value": best_value, "params": best_params}, indent=2)
        )
        (out_dir / "best_config.json").write_text(
            apply_params(cfg.base, best_params).model_dump_json(indent=2)
        )
    complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    if complete:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        plots = {"optimization_history": optuna.visualization.matplotlib.plot_optimization_history,
                 "parallel_coordinate": optuna.visualization.matplotlib.plot_parallel_coordinate}  # fmt: skip
        if len(complete) >= 2 and len(cfg.space) >= 2:
            plots["param_importances"] = optuna.visualization.matplotlib.plot_param_importances
        for name, fn in plots.items():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter(
                        "ignore"
                    )  # Optuna marks its matplotlib plots experimental
                    ax = fn(study)
                fig = ax.figure if hasattr(ax, "figure") else np.ravel(ax)[0].figure
                fig.set_size_inches(9, 5)
                fig.tight_layout()
                fig.savefig(out_dir / f"{name}.png", dpi=100)
                plt.close(fig)
            except Exception as e:
                out.setdefault("plot_errors", {})[name] = f"{type(e).__name__}: {e}"
    (out_dir / "summary.json").write_text(json.dumps(out, indent=2, default=str))
    return out
