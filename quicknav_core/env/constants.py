"""Constants and layouts shared by the JAX env, the NumPy twin, rendering and clients.

NumPy only (no JAX, no config import): every number the two implementations must agree on lives
here once.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# What a lidar beam reports it hit.
HIT_NONE = 0  # nothing within lidar_max_range
HIT_WALL = 1
HIT_GOAL = 2

# Observation layout (B = lidar_beams): see quicknav_core.env.quicknav.QuickNavEnv.
POSE_DIM = 4  # x / room_size, y / room_size, sin(theta), cos(theta)
GOAL_DIM = 5  # goal x / room_size, goal y / room_size, distance / room_size, sin, cos of bearing
PLAN_POINT_DIM = 2  # per waypoint: forward, left in the robot frame / the waypoint's reach
PATH_SCALE_M = 10.0  # the path left to the goal, observed as tanh(metres / PATH_SCALE_M)

# Room carving moves (d_row, d_col): up, down, left, right.
CARVE_MOVES = np.array([[1, 0], [-1, 0], [0, -1], [0, 1]], dtype=np.int32)

# PRNG stream of each room bank: train and test rooms never share a stream.
SPLIT_STREAM = {"train": 0, "test": 1}

# A distance no real one reaches ("never" for ray hits).
BIG = 1e30

# Obstacles the map does not show (``env.obstacles``): random words a spawn draws per obstacle (its
# cell, radius, direction, speed), and where an absent one is parked (radius 0, far outside).
OBSTACLE_WORDS = 4
OBSTACLE_ABSENT = -1e4

# Sensor and actuator randomisation (``EnvConfig.randomize``): the longest action latency, in steps.
# It fixes the length of the per-env queue of past commands, so it is a constant, not a config
# field: every latency range up to it runs on the same compiled program.
LATENCY_MAX_STEPS = 4


def check_split(split: str) -> str:
    """``split`` if it names a room bank, else a ValueError saying which ones exist."""
    if split not in SPLIT_STREAM:
        raise ValueError(f"split={split!r}: allowed values are 'train' and 'test'")
    return split


def beam_angles(num_beams: int, fov_deg: float) -> np.ndarray:
    """Beam angles relative to the heading, float32 radians, counter-clockwise.

    A 360° lidar spreads beams evenly around the robot starting at the heading; a narrower one
    spreads them evenly from -fov/2 to +fov/2, both ends included (one beam looks straight ahead).
    """
    i = np.arange(num_beams, dtype=np.float64)
    if fov_deg >= 360.0:
        angles = 2.0 * np.pi * i / num_beams
    elif num_beams == 1:
        angles = np.zeros(1)
    else:
        fov = np.deg2rad(fov_deg)
        angles = -0.5 * fov + fov * i / (num_beams - 1)
    return angles.astype(np.float32)


def beam_offsets(num_beams: int, fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of ``beam_angles``, float32 (computed in float64).

    A beam's direction is the heading's rotated by its offset: (cos θ·cos a − sin θ·sin a,
    sin θ·cos a + cos θ·sin a). The JAX env and the twin both compute it so: two sines and cosines
    per pose instead of two per beam."""
    a = beam_angles(num_beams, fov_deg).astype(np.float64)
    return np.cos(a).astype(np.float32), np.sin(a).astype(np.float32)


def observation_parts(config: Any) -> list[tuple[str, list[float], list[float]]]:
    """The observation vector of an ``EnvConfig``, part by part in order: (name, low, high per
    entry). The one description of the layout that the env, the twin, the bounds, ``obs_dim`` and
    the export manifest follow."""
    b = config.lidar_beams
    parts = []
    if config.observe_pose:
        parts += [("position", [0.0, 0.0], [1.0, 1.0]), ("heading", [-1.0, -1.0], [1.0, 1.0])]
    parts += [("ranges", [0.0] * b, [1.0] * b), ("wall_hits", [0.0] * b, [1.0] * b),
              ("goal_hits", [0.0] * b, [1.0] * b)]  # fmt: skip
    if config.observe_goal:
        # goal x, goal y, distance (at most the room diagonal), sin and cos of the bearing
        parts += [("goal_position", [0.0, 0.0], [1.0, 1.0]),
                  ("goal_distance", [0.0], [float(np.sqrt(2.0))]),
                  ("goal_bearing", [-1.0, -1.0], [1.0, 1.0])]  # fmt: skip
    if config.observe_plan:
        w = config.plan_waypoints
        parts += [("waypoints", [-1.0] * (PLAN_POINT_DIM * w), [1.0] * (PLAN_POINT_DIM * w)),
                  ("path_left", [0.0], [1.0])]  # fmt: skip
    return parts


def observation_size(config: Any) -> int:
    return sum(len(low) for _, low, _ in observation_parts(config))


def observation_bounds(config: Any) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise (low, high) of the observation vector of an ``EnvConfig``, float32."""
    parts = observation_parts(config)
    low = [v for _, lo, _ in parts for v in lo]
    high = [v for _, _, hi in parts for v in hi]
    return np.asarray(low, np.float32), np.asarray(high, np.float32)
