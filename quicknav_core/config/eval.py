"""Evaluation configuration: which policy drives, in which env, over which fixed-seed episodes."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from quicknav_core.config.base import Split, StrictModel
from quicknav_core.config.env import EnvConfig

BASELINES = ("random", "oracle", "dwa")
# Episodes run side by side in one compiled call; a larger evaluation runs in batches of this many
# (progress and cancellation between batches).
EVAL_BATCH = 256
# Planner nodes one mapped batch of reference/oracle planners holds (~100 MB of distance fields).
PLAN_NODES_AT_ONCE = 2**21


def plan_batch(grid: int | tuple[int, int], episodes: int, k: int = 5) -> int:
    """How many episodes' planners run side by side (``jax.lax.map``'s batch): all of them on small
    grids, fewer as the grid grows, so a planner's memory follows the batch, not the episodes.
    ``grid``: a square's side or (rows, cols)."""
    rows, cols = (grid, grid) if isinstance(grid, int) else grid
    return max(1, min(episodes, PLAN_NODES_AT_ONCE // (rows * cols * k * k)))


class EvalConfig(StrictModel):
    """A held-out evaluation.

    ``policy="trained"`` evaluates the checkpoint of ``source`` (a run folder, or a train job's id in
    the service) in that run's own env; ``"random"`` and ``"oracle"`` are baselines in ``env``. A
    resolved config (``config.resolve.resolve_eval``) always carries the env the episodes run in, so
    a stored eval job says everything about what was measured.
    """

    policy: Literal["trained", "random", "oracle", "dwa"] = Field(
        "trained", description="'trained' (the checkpoint of source) or a baseline"
    )
    source: str | None = Field(
        None, description="the trained policy: a run folder, or a train job id in the service"
    )
    env: EnvConfig | None = Field(None, description="the env of the episodes (resolved: always set)")
    episodes: int = Field(100, ge=1, le=100_000)
    seed: int = Field(0, ge=0, le=2**31 - 1, description="episode seed: same seed, same episodes")
    split: Split = Field("test", description="room bank: test (held out) or train")
    deterministic: bool = Field(True, description="act with the policy's mean, not a sample")
    gif_episodes: int = Field(
        3, ge=0, le=1024, description="episodes whose per-step poses, lidar and actions are kept"
    )
    pictures: bool = True
    robustness: bool = Field(
        False,
        description="also run the episodes at each perturbation level (lidar noise, dropout, bias,"
        " latency, wheel asymmetry; eval.robustness.LEVELS): success and SPL per level in"
        " eval.json and robustness.png",
    )
    shield: bool = Field(
        False,
        description="put the safety layer (eval.shield) between the policy and the wheels: a"
        " command that would bring the robot within 1 cm of a lidar return is slowed, down to"
        " turning in place",
    )

    @model_validator(mode="after")
    def _check_source(self) -> EvalConfig:
        if self.policy != "trained" and self.source is not None:
            raise ValueError(
                f"source={self.source!r} names a trained policy, but policy={self.policy!r} is a"
                " baseline; allowed: source only with policy='trained'"
            )
        return self
