"""The numbers of an evaluation: success with its 95 % Wilson interval, SPL, steps, collisions,
and the same per difficulty bin (the oracle's shortest path to the goal).

SPL (Anderson et al. 2018) = mean_i S_i * l_i / max(p_i, l_i), with p_i the path the robot drove
until it reached the goal disc and l_i the shortest disc path into the goal disc
(``env.plan.shortest_path_length``).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from quicknav_core.eval.episodes import Episodes

__all__ = ["PATH_BIN_EDGES", "by_path_length", "spl", "summarize", "wilson_interval"]


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of ``successes`` out of ``n``: ``lower <= successes / n <= upper``
    and both inside [0, 1], exactly at the edges (0 of n has lower 0.0, n of n has upper 1.0).

    The formula's rounding alone gives 0.9999999999999999 for n of n (57 of the sizes 1..200), and
    a picture's error bar below such a point comes out negative: the ends are pinned, not computed."""
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    lower = 0.0 if successes == 0 else min(p, max(0.0, centre - half))
    upper = 1.0 if successes == n else max(p, min(1.0, centre + half))
    return (lower, upper)


def spl(success: np.ndarray, path_length: np.ndarray, reference_length: np.ndarray) -> float:
    """Success weighted by (normalised inverse) path length."""
    s = success.astype(np.float64)
    ref = reference_length.astype(np.float64)
    denom = np.maximum(np.maximum(path_length, ref), 1e-9)
    if s.size == 0:
        return math.nan
    # each term is in [0, 1] (ref <= denom); the clip keeps a mean of them there too
    return float(np.clip(np.mean(s * ref / denom), 0.0, 1.0))


def _mean_std(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {"mean": math.nan, "std": math.nan}
    return {"mean": float(np.mean(x)), "std": float(np.std(x))}


def summarize(ep: Episodes, max_steps: int, step_length: float) -> dict[str, Any]:
    """All metrics of a set of episodes."""
    n = int(ep.success.size)
    k = int(ep.success.sum())
    lo, hi = wilson_interval(k, n)
    steps_all = np.where(ep.success, ep.steps, max_steps)
    lower_bound = np.ceil(ep.reference_length / step_length)
    return {
        "episodes": n,
        "success_rate": k / n,
        "success_ci95": [lo, hi],
        "steps_to_goal_successes": _mean_std(ep.steps[ep.success]),
        "steps_to_goal_failures_as_limit": _mean_std(steps_all),
        "return": _mean_std(ep.returns),
        "collisions_per_episode": float(np.mean(ep.collisions)),
        # the goal reached without touching anything on the way: what a robot owner counts as a
        # success, and what success_rate alone hides in an env where a collision does not end
        # the episode (a policy that slides along walls to the goal)
        "collision_free_success_rate": float(np.mean(ep.success & (ep.collisions == 0))),
        "timeout_rate": float(np.mean(ep.truncated)),
        "spl": spl(ep.success, ep.path_length, ep.reference_length),
        "path_length_successes": _mean_std(ep.path_length[ep.success]),
        "reference_length": _mean_std(ep.reference_length),
        "steps_lower_bound": _mean_std(lower_bound),
    }


# Difficulty bins: the oracle's shortest path to the goal disc, as fractions of the room's side
PATH_BIN_EDGES = (0.0, 0.25, 0.5, 0.75, 1.0, math.inf)


def by_path_length(ep: Episodes, room_size: float, max_steps: int) -> list[dict[str, Any]]:
    """Success, its 95 % interval, SPL and steps (failures as the limit) per difficulty bin: the
    episodes grouped by the oracle's shortest-path length (metres). Empty bins are left out."""
    edges = [e * room_size for e in PATH_BIN_EDGES]
    rows = []
    for lo, hi in itertools.pairwise(edges):
        inside = (ep.reference_length >= lo) & (ep.reference_length < hi)
        n = int(inside.sum())
        if n == 0:
            continue
        k = int(ep.success[inside].sum())
        steps = np.where(ep.success[inside], ep.steps[inside], max_steps)
        rows.append({
            "path_m": [round(lo, 3), None if math.isinf(hi) else round(hi, 3)],
            "episodes": n, "success_rate": k / n, "success_ci95": list(wilson_interval(k, n)),
            "spl": spl(ep.success[inside], ep.path_length[inside], ep.reference_length[inside]),
            "steps_failures_as_limit": float(np.mean(steps)),
        })  # fmt: skip
    return rows
