"""Observation bounds, shared by the JAX env and the NumPy twin (no JAX import)."""

from __future__ import annotations

import numpy as np

from quicknav_core.config import EnvConfig
from quicknav_core.env.constants import GOAL_DIM, POSE_DIM


def observation_bounds(config: EnvConfig) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise (low, high) of the observation vector, float32."""
    b = config.lidar_beams
    low = [0.0, 0.0, -1.0, -1.0] + [0.0] * (3 * b)
    high = [1.0, 1.0, 1.0, 1.0] + [1.0] * (3 * b)
    if config.observe_goal:
        # goal x, goal y, distance (at most the room diagonal), sin and cos of the bearing
        low += [0.0, 0.0, 0.0, -1.0, -1.0]
        high += [1.0, 1.0, float(np.sqrt(2.0)), 1.0, 1.0]
    assert len(low) == POSE_DIM + 3 * b + (GOAL_DIM if config.observe_goal else 0)
    return np.asarray(low, np.float32), np.asarray(high, np.float32)
