"""The pictures of ``quicknav bench`` (``bench.env``'s report): the time for the paper's step
count per implementation and grid (``bench_time_100k.png``, the paper's figure) and throughput
against batch size (``bench_batch.png``). Drawn from the report, never inside the code that
measures it."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from quicknav_core.bench.env import BenchReport


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_time(report: BenchReport, path: Path) -> Path:
    """Wall-clock for the report's step count, a bar per implementation and grid (log scale)."""
    plt = _pyplot()
    steps = report.config["steps"]
    grids = report.config["grids"]
    impls = []
    for r in report.results:
        if r.impl not in impls:
            impls.append(r.impl)
    by = {(r.grid, r.impl): r for r in report.results}

    fig, ax = plt.subplots(figsize=(9.5, 4.5))
    width = 0.8 / max(len(impls), 1)
    for i, impl in enumerate(impls):
        xs = [g_i + (i - (len(impls) - 1) / 2) * width for g_i in range(len(grids))]
        ys = [by[(g, impl)].time_for_steps_s if (g, impl) in by else np.nan for g in grids]
        ax.bar(xs, ys, width, label=impl)
    ax.set_xticks(range(len(grids)), [f"{g}x{g}" for g in grids])
    ax.set_yscale("log")
    ax.set_xlabel("grid size")
    ax.set_ylabel(f"wall-clock for {steps:,} steps (s, log)")
    ax.set_title(f"JAX vs NumPy: time for {steps:,} random-action steps")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), title="implementation")
    ax.grid(axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def draw_batch(report: BenchReport, path: Path) -> Path:
    """Env steps per second against the vmap batch, a line per grid, the NumPy twin dashed."""
    plt = _pyplot()
    grids = report.config["grids"]
    by = {(r.grid, r.impl): r for r in report.results}

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for g in grids:
        rows = sorted(
            (
                r
                for r in report.results
                if r.grid == g and r.impl.startswith("jax-b") and r.impl != "jax-b1-py"
            ),
            key=lambda r: r.batch,
        )
        ax.plot(
            [r.batch for r in rows], [r.steps_per_s for r in rows], marker="o", label=f"JAX {g}x{g}"
        )
        if (g, "numpy") in by:
            ax.axhline(
                by[(g, "numpy")].steps_per_s, ls="--", lw=0.8, color=ax.lines[-1].get_color()
            )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("envs per call (vmap batch)")
    ax.set_ylabel("env steps / s (log)")
    ax.set_title("Throughput vs batch size (dashed: NumPy twin, 1 env)")
    ax.legend(fontsize=8)
    ax.grid(which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
