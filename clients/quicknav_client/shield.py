"""The safety layer a robot runs between the policy and its wheels (NumPy, no JAX): the same rule
as ``quicknav_core.eval.shield``, which evaluations with ``shield=True`` run, and held equal to it
by ``tests/core/eval/test_shield.py``.

A command whose next pose (one control period of the robot's differential drive) would bring the
robot's disc within ``MARGIN_M`` of a scan return, and closer than it is now, has its forward part
scaled by the first of ``SCALES`` that does not; its turning part is kept, and at scale 0 the robot
turns in place (a disc can always do that). Wheel-speed errors and latency are not modelled.
"""

from __future__ import annotations

import math

import numpy as np

SCALES = (1.0, 0.5, 0.25, 0.0)  # of the command's forward part, tried in order
MARGIN_M = 0.01  # kept between the robot's edge and a return


def shield_command(action, points: np.ndarray, *, radius: float, max_wheel_speed: float,
                   wheel_base: float, dt: float) -> tuple[float, float]:  # fmt: skip
    """The (left, right) command in [-1, 1] let through, from the policy's ``action`` (left,
    right in [-1, 1]) and the scan's returns ``points`` ((n, 2) metres in the robot's frame: x
    ahead, y to the left)."""
    left, right = (0.0 if math.isnan(float(v)) else min(max(float(v), -1.0), 1.0) for v in action)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if not len(pts):
        return left, right
    now = float(np.min(np.hypot(pts[:, 0], pts[:, 1])))
    forward, turn = 0.5 * (left + right), 0.5 * (right - left)
    for s in SCALES:
        cmd = (s * forward - turn, s * forward + turn)
        v = 0.5 * (cmd[0] + cmd[1]) * max_wheel_speed
        mid = 0.5 * (cmd[1] - cmd[0]) * max_wheel_speed / wheel_base * dt
        dx, dy = v * dt * math.cos(mid), v * dt * math.sin(mid)
        after = float(np.min(np.hypot(pts[:, 0] - dx, pts[:, 1] - dy)))
        if s == 0.0 or after >= radius + MARGIN_M or after >= now:
            return cmd
    raise AssertionError("unreachable: scale 0 is always let through")


def scan_in_robot_frame(ranges: np.ndarray, angles: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(n, 2) robot-frame points of a scan's valid returns (``policy.scan_arrays``'s three)."""
    r, a = np.asarray(ranges, np.float64)[valid], np.asarray(angles, np.float64)[valid]
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=-1)
