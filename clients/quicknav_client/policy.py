"""A policy exported by ``quicknav export``, run with onnxruntime and NumPy only (no JAX).

    from quicknav_client.policy import OnnxPolicy

    policy = OnnxPolicy.load("policy")          # the folder with policy.onnx and policy.json
    policy.reset()                              # a new episode (recurrent state back to its start)
    left, right = policy.act(scan, pose=(x, y, theta), goal=(gx, gy))   # wheel speeds, m/s

``scan`` is any planar lidar scan as robots publish it: an object or mapping with the fields of a
ROS ``sensor_msgs/LaserScan`` (``angle_min``, ``angle_increment``, ``ranges``, ``range_min``,
``range_max``; angles in the robot frame, counter-clockwise, 0 straight ahead; ``inf``/``NaN`` or a
range outside [range_min, range_max] is no return), or a plain array of ranges at the policy's own
beam angles. It is resampled onto the policy's beams (the valid return closest in angle to each
beam, within its sector) and normalised as in training. The goal is not a thing a lidar sees, but
in training the beams that crossed the goal disc reported it; ``act`` draws the goal disc (from
``goal`` and the trained ``goal_radius``) into the resampled scan the same way. ``pose`` and
``goal`` are in the room frame the policy was trained in (metres, radians).

Install: ``pip install 'quicknav-client[policy]'`` (onnxruntime).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

f32 = np.float32


@dataclass
class LaserScan:
    """The fields of a ROS LaserScan that the resampler reads."""

    angle_min: float
    angle_increment: float
    ranges: Any
    range_min: float = 0.0
    range_max: float = math.inf


def _field(scan: Any, name: str, default: Any = None) -> Any:
    if isinstance(scan, Mapping):
        return scan.get(name, default)
    return getattr(scan, name, default)


def scan_arrays(scan: Any, beam_angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ranges, angles, valid) of a scan, float64 metres and radians: a plain array of ranges is
    read at the policy's beams (``beam_angles``), a LaserScan at its own angles; valid: finite
    and within the scan's range_min..range_max."""
    if isinstance(scan, np.ndarray | list | tuple):
        ranges = np.asarray(scan, np.float64).reshape(-1)
        if ranges.size != beam_angles.size:
            raise ValueError(f"scan: {ranges.size} ranges given as an array; the policy has"
                             f" {beam_angles.size} beams (give a LaserScan for any other layout)")  # fmt: skip
        angles, lo, hi = beam_angles.astype(np.float64), 0.0, math.inf
    else:
        ranges = np.asarray(_field(scan, "ranges"), np.float64).reshape(-1)
        a0, inc = _field(scan, "angle_min"), _field(scan, "angle_increment")
        if a0 is None or inc is None or not ranges.size:
            raise ValueError("scan: needs angle_min, angle_increment and ranges (a ROS LaserScan's fields)")
        if not (math.isfinite(float(a0)) and math.isfinite(float(inc)) and float(inc) != 0.0):
            raise ValueError(f"scan: angle_min={float(a0):g}, angle_increment={float(inc):g}: both"
                             " must be finite and angle_increment non-zero (radians between"
                             " readings, negative for a clockwise scan)")  # fmt: skip
        angles = float(a0) + float(inc) * np.arange(ranges.size)
        lo, hi = float(_field(scan, "range_min", 0.0) or 0.0), float(_field(scan, "range_max", math.inf))
    return ranges, angles, np.isfinite(ranges) & (ranges >= lo) & (ranges <= hi)


def resample(scan: Any, beam_angles: np.ndarray, fov_deg: float, max_range: float) -> np.ndarray:
    """Ranges (float32, metres, ``inf`` where no return) at the policy's beams: for each beam, the
    valid return closest in angle to the beam's direction (the ray the simulator's beam measures),
    looked for within the beam's sector (the half-open interval halfway to its neighbours; the edge
    beams of a partial field of view get a sector as wide as the inner ones); two returns as close
    give the shorter range; a sector without a valid return is no return."""
    beams = beam_angles.size
    ranges, angles, valid = scan_arrays(scan, beam_angles)
    if fov_deg >= 360.0 or beams == 1:
        width = 2.0 * math.pi / beams
    else:
        width = math.radians(fov_deg) / (beams - 1)
    # angle of every return relative to every beam, wrapped into [-pi, pi)
    rel = (angles[None, :] - beam_angles.astype(np.float64)[:, None] + math.pi) % (2.0 * math.pi) - math.pi
    sector = (rel >= -width / 2) & (rel < width / 2)
    # a beam whose direction the scan does not sweep (valid reading or not) is blind
    span = abs(angles[-1] - angles[0]) + (abs(angles[1] - angles[0]) if angles.size > 1 else 0.0)
    start = min(angles[0], angles[-1]) - (span - abs(angles[-1] - angles[0])) / 2
    blind = ((beam_angles.astype(np.float64) - start) % (2.0 * math.pi)) > span + 1e-9
    if blind.any():
        # a beam the scanner cannot see is not "no return": that would read as open space
        seen = np.degrees(angles)
        sweep = math.degrees(abs(angles[-1] - angles[0]))  # first to last reading, as a datasheet says
        if math.degrees(span) + 1e-6 >= fov_deg:  # wide enough, pointing elsewhere: a frame, not a scanner
            centre = (math.degrees(start + span / 2.0) + 180.0) % 360.0 - 180.0
            what = (f" The scan sweeps {sweep:.0f} degrees, as wide as the policy's {fov_deg:g}, but"
                    f" centred at {centre:.0f} degrees, not on the robot's heading: give it in the"
                    " robot's frame (base_link, x forward), or rotate angle_min by the scanner's yaw")  # fmt: skip
        else:
            what = (f" The policy was trained for a {fov_deg:g}-degree lidar: train one for this"
                    f" scanner (env.lidar_fov_deg={sweep:.0f}, this scan's field of view) or give a"
                    " scan that covers every beam")  # fmt: skip
        raise ValueError(
            f"scan: covers {seen.min():.0f} to {seen.max():.0f} degrees; {int(blind.sum())} of the"
            f" policy's {beams} beams (at {_degrees(beam_angles[blind])}) fall outside it.{what}")
    inside = sector & valid[None, :]
    # not the shortest return of the sector: that would show the policy every beam shortened
    # towards its neighbours' walls, which it never saw in training (the demo policy driven from a
    # 360-beam scan: 88 % held-out success with the sector's shortest return, 97 % with the closest
    # in angle, 98 % from its own 16 beams)
    off = np.where(inside, np.abs(rel), np.inf)
    closest = inside & (off <= off.min(axis=1, keepdims=True) + 1e-9)
    return np.where(closest, ranges[None, :], np.inf).min(axis=1).astype(f32)


def _degrees(angles: np.ndarray, most: int = 6) -> str:
    text = ", ".join(f"{math.degrees(float(a)):.0f}" for a in angles[:most])
    return text + (f" and {angles.size - most} more" if angles.size > most else "") + " degrees"


class Observer:
    """Builds a policy's observation vector from what a robot has (a scan, a pose, a goal and, for
    a policy that follows a global plan, the plan's features), part by part as the manifest's
    observation layout lists them; no model needed."""

    def __init__(self, manifest: Mapping[str, Any]):
        env, lidar = manifest["env"], manifest["lidar"]
        self.beam_angles = np.asarray(lidar["beam_angles_rad"], f32)
        self.fov_deg = float(lidar["fov_deg"])
        self.max_range = float(lidar["max_range_m"])
        self.room_size = float(env["room_size"])
        self.goal_radius = float(env["goal_radius"])
        self.observe_goal = bool(env["observe_goal"])
        self.observe_plan = bool(env.get("observe_plan", False))
        self.obs_size = int(manifest["observation"]["size"])
        layout = manifest["observation"].get("layout")
        # manifests written before the layout was generic always started with the pose
        self.parts = [p["name"] for p in layout] if layout else None

    def __call__(self, scan: Any, pose: Any, goal: Any = None, plan: Any = None) -> np.ndarray:
        """The policy's observation vector (float32) for a scan, a pose (x, y, theta in the frame
        the goal is in) and a goal; ``plan``: the plan's features (``GridPlanner.features``)."""
        x, y, theta = finite_numbers(pose, "pose", 3, "(x, y, yaw): metres and radians")
        if self.observe_goal and goal is None:
            raise ValueError("goal: this policy observes its goal; give goal=(x, y) in metres")
        if goal is not None:
            goal = finite_numbers(goal, "goal", 2, "(x, y) in metres")
        # what the policy reads in the room frame must be in the room it trained in: a pose or a
        # goal outside it is no observation it ever saw (and the demo policy, given a goal 300 m
        # away, drove full speed in reverse)
        names = self.parts or ["position"] + (["goal_position"] if self.observe_goal else [])
        if "position" in names:
            self._inside("pose", (x, y))
        if goal is not None and "goal_position" in names:
            self._inside("goal", goal)
        if self.observe_plan and plan is None:
            raise ValueError("plan: this policy follows a global plan; give plan= the plan's features"
                             " (quicknav_client.navigate.GridPlanner.features), or drive it with"
                             " quicknav_client.navigate.Navigator, which plans on the exported map")  # fmt: skip
        b = self.beam_angles.size
        ranges = resample(scan, self.beam_angles, self.fov_deg, self.max_range)
        wall = np.isfinite(ranges) & (ranges <= self.max_range)
        ranges = np.where(wall, ranges, f32(self.max_range)).astype(f32)
        goal_hit = np.zeros(b, bool)
        if goal is not None:
            # each beam's ray against the goal disc, as the simulator's lidar reports it
            c, s = f32(math.cos(theta)), f32(math.sin(theta))
            ca, sa = np.cos(self.beam_angles), np.sin(self.beam_angles)
            dx, dy = c * ca - s * sa, s * ca + c * sa
            fx, fy = f32(goal[0] - x), f32(goal[1] - y)
            proj = fx * dx + fy * dy
            perp2 = fx * fx + fy * fy - proj * proj
            r2 = f32(self.goal_radius) ** 2
            half = np.sqrt(np.maximum(r2 - perp2, f32(0)))
            meets = (perp2 <= r2) & (proj + half >= 0)
            t_goal = np.where(meets, np.maximum(proj - half, f32(0)), np.inf)
            goal_hit = (t_goal < np.where(wall, ranges, np.inf)) & (t_goal <= self.max_range)
            ranges = np.where(goal_hit, t_goal, ranges).astype(f32)
            wall &= ~goal_hit
        room = f32(self.room_size)
        parts: dict[str, Any] = {
            "position": np.asarray([x, y], f32) / room, "heading": [math.sin(theta), math.cos(theta)],
            "ranges": ranges / f32(self.max_range), "wall_hits": wall, "goal_hits": goal_hit,
        }  # fmt: skip
        if goal is not None:
            rx, ry = goal[0] - x, goal[1] - y
            dist = math.hypot(rx, ry)
            if dist > 0:
                fwd = (math.cos(theta) * rx + math.sin(theta) * ry) / dist
                left = (math.cos(theta) * ry - math.sin(theta) * rx) / dist
            else:
                fwd, left = 1.0, 0.0
            parts.update(goal_position=np.asarray(goal, f32) / room,
                         goal_distance=[dist / self.room_size], goal_bearing=[left, fwd])  # fmt: skip
        if plan is not None:
            plan = np.asarray(plan, f32).reshape(-1)
            parts.update(waypoints=plan[:-1], path_left=plan[-1:])
        names = self.parts or ["position", "heading", "ranges", "wall_hits", "goal_hits"] + (
            ["goal_position", "goal_distance", "goal_bearing"] if self.observe_goal else [])
        missing = [n for n in names if n not in parts]
        if missing:
            raise ValueError(f"the policy's observation has parts this client cannot build: {missing}"
                             " (a newer quicknav-client may)")  # fmt: skip
        obs = np.concatenate([np.asarray(parts[n], f32).reshape(-1) for n in names]).astype(f32)
        if obs.size != self.obs_size:
            raise ValueError(f"built an observation of {obs.size} entries; the policy takes {self.obs_size}")
        return obs

    def _inside(self, what: str, xy) -> None:
        """Refuse a point outside the room frame the policy observes positions in."""
        room, slack = self.room_size, 1e-6 * self.room_size
        if not all(-slack <= v <= room + slack for v in xy):
            raise ValueError(
                f"{what}: ({xy[0]:g}, {xy[1]:g}) is outside the room this policy was trained in"
                f" (0 to {room:g} m on each axis: the room frame, origin at its corner); the policy"
                f" reads its {'position' if what == 'pose' else 'goal'} in that frame, so give it"
                " there (for a map's frame, export with --map and drive with Navigator)")


def finite_numbers(values: Any, what: str, size: int, form: str) -> tuple[float, ...]:
    """``values`` as ``size`` finite floats, or a ValueError naming ``what`` and ``form``."""
    try:
        numbers = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: {values!r} is not {size} numbers {form}") from None
    if len(numbers) != size or not all(map(math.isfinite, numbers)):
        raise ValueError(f"{what}: {values!r}: give {size} finite numbers {form}")
    return numbers


class OnnxPolicy:
    """An exported QuickNav policy: one robot, one step at a time (the model takes batches; use
    ``session`` and the manifest directly for several)."""

    def __init__(self, folder: str | Path):
        import onnxruntime as ort

        folder = Path(folder)
        self.manifest: dict[str, Any] = json.loads((folder / "policy.json").read_text())
        m = self.manifest
        if m.get("format") != "quicknav-policy":
            raise ValueError(f"{folder / 'policy.json'}: not a QuickNav policy manifest")
        options = ort.SessionOptions()
        options.log_severity_level = 3
        self.session = ort.InferenceSession(str(folder / m["onnx"]["file"]), options,
                                            providers=["CPUExecutionProvider"])  # fmt: skip
        self.observer = Observer(m)
        self.obs_size = self.observer.obs_size
        self.max_wheel_speed = float(m["action"]["max_wheel_speed_mps"])
        self.reset()

    @classmethod
    def load(cls, folder: str | Path) -> OnnxPolicy:
        return cls(folder)

    def reset(self) -> None:
        """Start a new episode: the next ``act`` is its first step."""
        self._start = True
        self._state = [np.full([1, *s["shape"][1:]], s["initial"], np.dtype(s["dtype"]))
                       for s in self.manifest["state"]]  # fmt: skip

    def observation(self, scan: Any, pose: Any, goal: Any = None, plan: Any = None) -> np.ndarray:
        """The policy's observation vector (float32) for a scan, a pose, a goal and a plan."""
        return self.observer(scan, pose, goal, plan)

    def act(self, scan: Any, pose: Any, goal: Any = None, plan: Any = None) -> tuple[float, float]:
        """(left, right) wheel speeds in m/s for this step (the policy's deterministic action);
        ``plan``: the plan's features, for a policy that follows one (``Navigator`` finds them)."""
        return self.act_on(self.observation(scan, pose, goal, plan))

    def act_on(self, obs: np.ndarray) -> tuple[float, float]:
        """(left, right) wheel speeds in m/s for an observation vector built as in training."""
        feed = {"obs": np.asarray(obs, f32).reshape(1, self.obs_size)}
        if self._state:
            feed["start"] = np.asarray([self._start])
            feed.update({s["input"]: v for s, v in zip(self.manifest["state"], self._state, strict=True)})
        action, *state = self.session.run(None, feed)
        self._state, self._start = state, False
        left, right = (float(v) * self.max_wheel_speed for v in action[0])
        return left, right
