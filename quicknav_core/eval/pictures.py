"""The pictures of an evaluation: trajectories.png, difficulty.png, episodes.gif and (with
``robustness``) robustness.png; and the learning report's performance profiles (``draw_profiles``).

``draw_all`` draws each one on its own: a picture that fails to render is reported as a warning
naming the file, and never costs the evaluation its numbers (eval.json is written before).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from quicknav_core.config import EnvConfig
from quicknav_core.drawing import draw_safely, picture_warning
from quicknav_core.eval.aggregate import performance_profile
from quicknav_core.eval.episodes import Episodes, episode_plan, outcome
from quicknav_core.layout import EVAL

__all__ = ["draw_all", "draw_difficulty", "draw_gif", "draw_profiles", "draw_robustness", "draw_trajectories",
           "episode_snapshot", "obstacles_at", "picture_warning", "rooms_in_words",
           "trajectory_panels"]  # fmt: skip


def rooms_in_words(config: EnvConfig, split: str = "test",
                   map_name: Callable[[str], str | None] | None = None) -> str:  # fmt: skip
    """Where an evaluation's episodes were, for a picture's title: a map by its file name, or an
    uploaded map by the name ``map_name`` (``Runtime.map_name``) gives it (its ``map:<id>`` when
    none), as the browser's replay words them; else the room bank it drew from."""
    if config.rooms == "maps":
        names = config.maps.test if split == "test" and config.maps.test else config.maps.train

        def shown_as(ref: str) -> str:
            if not ref.startswith("map:"):
                return Path(ref).name
            try:
                name = map_name(ref[4:]) if map_name is not None else None
            except Exception:  # a title never fails a picture
                name = None
            return f'"{name}"' if name else ref

        shown = [shown_as(n) for n in names[:3]] + names[3:]
        if len(shown) == 1:
            return f"map {shown[0]}"
        return f"{len(shown)} maps ({', '.join(shown[:3])}{', ...' if len(shown) > 3 else ''})"
    return "held-out test rooms" if split == "test" else "training rooms"


def draw_all(
    ep: Episodes, config: EnvConfig, rows: list[dict[str, Any]], out_dir: Path, title: str,
    gif: bool = True, robustness: list[dict[str, Any]] | None = None, split: str = "test",
    map_name: Callable[[str], str | None] | None = None,
) -> list[str]:  # fmt: skip
    """Draw every picture of an evaluation into ``out_dir``; the warnings of those that failed.
    ``map_name``: uploaded maps' names for the titles (``rooms_in_words``)."""
    where = rooms_in_words(config, split, map_name)
    jobs = [(EVAL.trajectories, lambda p: draw_trajectories(ep, config, p, title=title, where=where)),
            (EVAL.difficulty, lambda p: draw_difficulty(rows, p, title=title))]  # fmt: skip
    if robustness:
        jobs.append((EVAL.robustness, lambda p: draw_robustness(robustness, p, title=title)))
    if gif and ep.gif["theta"].shape[0]:
        jobs.append((EVAL.gif, lambda p: draw_gif(ep, config, p, title=title)))
    warnings = [draw_safely(Path(out_dir) / name, draw) for name, draw in jobs]
    return [w for w in warnings if w is not None]


def draw_difficulty(rows: list[dict[str, Any]], path: Path, title: str = "") -> Path:
    """Success (with its 95 % interval) and SPL against the oracle's path length, per bin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{r['path_m'][0]:g}-{r['path_m'][1]:g} m" if r["path_m"][1] is not None
              else f">= {r['path_m'][0]:g} m" for r in rows]  # fmt: skip
    x = np.arange(len(rows))
    success = np.array([r["success_rate"] for r in rows])
    ci = np.array([r["success_ci95"] for r in rows]).reshape(-1, 2)
    fig, ax = plt.subplots(figsize=(7, 4))
    # an interval always holds its point (statistics.wilson_interval); the clip only guards
    # matplotlib, which refuses a negative error bar, against intervals read from older files
    yerr = np.clip([success - ci[:, 0], ci[:, 1] - success], 0.0, None)
    ax.errorbar(x, success, yerr=yerr, marker="o",
                capsize=4, label="success rate (95 % CI)", color="tab:green")  # fmt: skip
    ax.plot(x, [r["spl"] for r in rows], marker="s", label="SPL", color="tab:blue")
    for xi, r in zip(x, rows, strict=True):
        ax.annotate(f"n={r['episodes']}", (xi, 0.98), ha="center", va="top", fontsize=8, color="0.4")
    ax.set_xticks(x, labels)
    ax.set_ylim(0, 1.05)
    ax.set_xlabel("oracle shortest path to the goal")
    ax.set_title(f"{title}: by difficulty" if title else "by difficulty", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="center right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def draw_robustness(rows: list[dict[str, Any]], path: Path, title: str = "") -> Path:
    """Success (95 % interval) and SPL against each perturbation's level, one panel each; every
    panel starts at the unperturbed row (level 0)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = next(r for r in rows if r["perturbation"] == "none")
    kinds = list(dict.fromkeys(r["perturbation"] for r in rows if r["perturbation"] != "none"))
    fig, axes = plt.subplots(1, len(kinds), figsize=(3.2 * len(kinds), 3.4), sharey=True,
                             squeeze=False)  # fmt: skip
    for ax, kind in zip(axes[0], kinds, strict=True):
        own = sorted([r for r in rows if r["perturbation"] == kind], key=lambda r: r["level"])
        points = sorted([{**base, "level": 0.0, "unit": own[0]["unit"]}, *own], key=lambda r: r["level"])
        scale = 100.0 if own[0]["unit"] == "%" else 1.0
        x = np.array([r["level"] for r in points]) * scale
        success = np.array([r["success_rate"] for r in points])
        ci = np.array([r["success_ci95"] for r in points]).reshape(-1, 2)
        yerr = np.clip([success - ci[:, 0], ci[:, 1] - success], 0.0, None)
        ax.errorbar(x, success, yerr=yerr, marker="o", capsize=3, color="tab:green",
                    label="success (95 % CI)")  # fmt: skip
        ax.plot(x, [r["spl"] for r in points], marker="s", color="tab:blue", label="SPL")
        ax.set_xlabel(f"{kind.replace('_', ' ')} ({own[0]['unit']})", fontsize=9)
        ax.set_ylim(0, 1.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("held-out episodes")
    axes[0][0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"{title}: robustness" if title else "robustness", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def draw_trajectories(ep: Episodes, config: EnvConfig, path: Path, title: str = "",
                      where: str = "held-out test rooms") -> Path:  # fmt: skip
    """Nine episodes with their trajectories (the paper's trajectory figures), 3 x 3, or in a row
    or a column for a long narrow map (``trajectory_panels``); ``where``: the rooms they ran in
    (``rooms_in_words``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from quicknav_core.env import render

    count = min(9, ep.success.size)
    views = [render.room_view(ep.walls[i], config) for i in range(count)]  # as the GIF's frames
    rows, cols, figsize = trajectory_panels([(x1 - x0, y1 - y0) for x0, x1, y0, y1 in views])
    fig, axes = plt.subplots(rows, cols, figsize=figsize, squeeze=False)
    for i, ax in enumerate(axes.flat):
        if i >= count:
            ax.axis("off")
            continue
        render.draw_room(ax, ep.walls[i], config.room_size, views[i])
        if (plan := episode_plan(ep, config, i)) is not None:  # the global plan, dashed
            ax.plot(plan[:, 0], plan[:, 1], color=render.PLAN_COLOUR, lw=1.2, ls=(0, (3, 2)))
        if ep.obstacles is not None:  # boxes where they stood; people where they started, and
            k = config.obstacles.static  # their walk when the episode's steps were kept
            for j, (x, y, r) in enumerate(ep.obstacles[i]):
                if r <= 0:
                    continue
                person = j >= k
                ax.add_patch(plt.Circle((x, y), r, lw=0,
                                        color=render.PERSON_COLOUR if person else render.BOX_COLOUR))
                if person and "obstacles" in ep.gif and i < ep.gif["obstacles"].shape[0]:
                    walk = ep.gif["obstacles"][i, : ep.steps[i] + 1, j]
                    ax.plot(walk[:, 0], walk[:, 1], color=render.PERSON_COLOUR, lw=0.8, alpha=0.7)
        traj = ep.trajectories[i, : ep.steps[i] + 1]
        ax.plot(traj[:, 0], traj[:, 1], color=render.PATH_COLOUR, lw=1.6)
        ax.plot(*traj[0], "o", color=render.PATH_COLOUR, ms=6)
        ax.add_patch(plt.Circle(ep.goals[i], config.goal_radius, color=render.GOAL_COLOUR, alpha=0.4))
        ax.plot(*ep.goals[i], "*", color=render.GOAL_COLOUR, ms=12)
        narrow = "\n" if rows == 1 and cols > 1 else " "  # a row of tall maps: titles on two lines
        ax.set_title(f"episode {i + 1}:{narrow}{outcome(ep, i, config)}, {ep.steps[i]} steps", fontsize=9)
    fig.suptitle(f"{title}: {where}" if title else where, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def trajectory_panels(sizes: list[tuple[float, float]]) -> tuple[int, int, tuple[float, float]]:
    """(rows, columns, figure size in inches) for ``draw_trajectories``' panels of views of these
    (width, height) metres: a 3 x 3 grid, but a row of panels for tall views and a column for wide
    ones (``render.narrow_shape``), so the map fills its panel instead of a strip of a square."""
    from quicknav_core.env.render import narrow_shape

    count = max(len(sizes), 1)
    shape, tallest = narrow_shape(sizes)
    if shape == "tall":  # side by side, 8.4 in high
        width = max(8.4 / tallest, 1.1)
        return 1, count, (max(count * (width + 0.35) + 0.4, 4.0), 9.6)
    if shape == "wide":  # one above the other, 9 in wide
        height = max(9.0 * tallest, 1.0)
        return count, 1, (9.4, count * (height + 0.45) + 0.7)
    return 3, 3, (9.0, 9.4)


def episode_snapshot(ep: Episodes, config: EnvConfig, i: int, t: int,
                     plan: np.ndarray | None = None) -> dict[str, Any]:  # fmt: skip
    """Picture episode ``i`` at step ``t`` as ``FrameDrawer`` draws it: the room, pose, goal,
    lidar, the plan (``episode_plan``, computed once per episode by the caller) and the unmapped
    obstacles at that step."""
    return {"walls": ep.walls[i], "pos": ep.trajectories[i, t], "theta": ep.gif["theta"][i, t],
            "goal": ep.goals[i], "lidar_ranges": ep.gif["lidar_ranges"][i, t],
            "lidar_hits": ep.gif["lidar_hits"][i, t], "plan": plan,
            **obstacles_at(ep, config, i, t)}  # fmt: skip


def obstacles_at(ep: Episodes, config: EnvConfig, i: int, t: int) -> dict[str, np.ndarray]:
    """Picture episode ``i``'s unmapped obstacles at step ``t`` (``boxes``, ``people``: (M, 3) x,
    y, radius of those present); {} for an env without them."""
    if ep.obstacles is None or "obstacles" not in ep.gif:
        return {}
    from quicknav_core.env.render import boxes_and_people

    return boxes_and_people(np.concatenate([ep.gif["obstacles"][i, t], ep.obstacles[i, :, 2:]], axis=1), config)


def draw_gif(
    ep: Episodes, config: EnvConfig, path: Path, title: str = "", max_frames: int = 60
) -> Path:
    """A GIF of the first episodes with lidar rays, one after the other, in frames that follow
    the maps' shape (``render.gif_frame_size``)."""
    from quicknav_core.env.render import FrameDrawer, gif_frame_size, room_view, save_gif

    shown = range(ep.gif["theta"].shape[0])
    size = gif_frame_size([room_view(ep.walls[i], config) for i in shown], 320)
    frames = []
    with FrameDrawer(config, size_px=size) as drawer:
        for i in shown:
            length = int(ep.steps[i]) + 1
            stride = max(1, math.ceil(length / max_frames))
            plan = episode_plan(ep, config, i)
            for t in [*range(0, length, stride), length - 1]:
                snap = episode_snapshot(ep, config, i, t, plan)
                frames.append(drawer.draw(snap, ep.trajectories[i, : t + 1],
                                          title=f"{title} episode {i + 1}  t={t}"))  # fmt: skip
    return save_gif(frames, path, fps=10)


def draw_profiles(
    panels: Sequence[tuple[str, Sequence[tuple[str, np.ndarray, bool]]]],
    path: Path,
    xlabel: str = "SPL threshold τ",
) -> Path:
    """One panel per (title, rows); a row is (label, (seeds, episodes) scores in [0, 1], dashed).
    Each curve is the fraction of runs x episodes with a score above τ, its band the 95 % interval;
    rows labelled as a baseline are drawn in grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    taus = np.linspace(0.0, 1.0, 101)
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.4), squeeze=False)
    for ax, (title, rows) in zip(axes[0], panels, strict=True):
        for i, (label, scores, dashed) in enumerate(rows):
            point, lo, hi = performance_profile(scores, taus)
            colour = "0.45" if "baseline" in label else f"C{i % 10}"
            n = np.asarray(scores).shape[0]
            ax.plot(taus, point, color=colour, linestyle="--" if dashed else "-",
                    label=f"{label} ({n} seed{'s' if n != 1 else ''})")  # fmt: skip
            if not np.isnan(lo).all():
                ax.fill_between(taus, lo, hi, color=colour, alpha=0.15, linewidth=0)
        ax.set_title(title)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of seeds x episodes with score > τ")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        if rows:
            ax.legend(fontsize=7, loc="lower left")
        else:
            ax.text(0.5, 0.5, "no row with per-episode scores yet", ha="center", va="center")
    fig.suptitle("Performance profiles (held-out test bank; bands: stratified bootstrap 95 %)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
