"""The pictures of training: a run's learning curve (``learning_curve.png``) and a sweep's study
plots (Optuna's optimisation history, parallel coordinates, parameter importances).

Drawn from what the runs wrote (``metrics.jsonl``, the study), never inside the code that computes
those numbers; a picture that fails is a warning, never a lost run or sweep.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from quicknav_core.drawing import draw_safely
from quicknav_core.layout import RunFolder


def draw_learning_curve(run_dir: Path) -> Path | None:
    """learning_curve.png: mean episode return and success rate against env steps."""
    from quicknav_core.config import TrainConfig

    run = RunFolder(run_dir)
    rows = run.read_metrics()
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["env_steps"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    a1.plot(steps, [r.get("mean_return", math.nan) for r in rows], marker=".")
    a1.set_xlabel("env steps")
    a1.set_ylabel("mean episode return")
    a1.grid(alpha=0.3)
    a2.plot(steps, [r.get("success_rate", math.nan) for r in rows], marker=".", color="tab:green")
    a2.set_xlabel("env steps")
    a2.set_ylabel("success rate (training episodes)")
    a2.set_ylim(-0.02, 1.02)
    a2.grid(alpha=0.3)
    if run.config.exists():
        cfg = TrainConfig.model_validate_json(run.config.read_text())
        fig.suptitle(
            f"{cfg.trainer_kind}, {cfg.network.kind}, grid {cfg.env.grid_size}", fontsize=10
        )
    fig.tight_layout()
    fig.savefig(run.curve, dpi=110)
    plt.close(fig)
    return run.curve


def draw_learning_curve_safely(run_dir: Path) -> list[str]:
    """``draw_learning_curve``; its failure as a warning naming the file (nothing half-drawn)."""
    run = RunFolder(run_dir)
    warning = draw_safely(run.curve, lambda _path: draw_learning_curve(run.path))
    return [warning] if warning else []


def draw_study(study, cfg, out_dir: Path) -> dict[str, str]:
    """A sweep's study plots as PNGs in ``out_dir`` (once a trial has completed); the plots that
    failed, by name, with their warnings (``drawing.picture_warning``)."""
    import optuna

    complete = [t for t in study.get_trials(deepcopy=False)
                if t.state == optuna.trial.TrialState.COMPLETE]  # fmt: skip
    if not complete:
        return {}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots = {"optimization_history": optuna.visualization.matplotlib.plot_optimization_history,
             "parallel_coordinate": optuna.visualization.matplotlib.plot_parallel_coordinate}  # fmt: skip
    if len(complete) >= 2 and len(cfg.space) >= 2:
        plots["param_importances"] = optuna.visualization.matplotlib.plot_param_importances
    def draw(fn, path: Path) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Optuna marks its matplotlib plots experimental
            ax = fn(study)
        fig = ax.figure if hasattr(ax, "figure") else np.ravel(ax)[0].figure
        fig.set_size_inches(9, 5)
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)

    errors: dict[str, Any] = {}
    for name, fn in plots.items():
        warning = draw_safely(Path(out_dir) / f"{name}.png", lambda path, fn=fn: draw(fn, path))
        if warning is not None:
            errors[name] = warning
    return errors
