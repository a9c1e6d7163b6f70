"""Pictures of QuickNav: frames (PNG), episode GIFs and the room-generation figure.

The only module of the environment that imports matplotlib (Agg backend, no screen needed).
A "snapshot" is anything with ``walls, pos, theta, goal, lidar_ranges, lidar_hits`` (an ``EnvState``
of one env, or the NumPy twin's ``snapshot()`` dict).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Circle, FancyArrow
from PIL import Image

from quicknav_core.env.constants import HIT_GOAL, HIT_NONE, HIT_WALL, beam_angles

if TYPE_CHECKING:  # pragma: no cover
    from quicknav_core.config import EnvConfig

WALL_COLOUR = "#3b3b3b"
FREE_COLOUR = "#f4f1ea"
RAY_COLOURS = {HIT_NONE: "#9e9e9e", HIT_WALL: "#d62728", HIT_GOAL: "#2ca02c"}  # grey / red / green
ROBOT_COLOUR = "#1f77b4"
GOAL_COLOUR = "#2ca02c"
PATH_COLOUR = "#ff7f0e"


def as_snapshot(state: Any) -> dict[str, np.ndarray]:
    """Plain NumPy dict of the fields a picture needs, from an EnvState or a dict."""
    get = state.get if isinstance(state, Mapping) else (lambda k: getattr(state, k))
    out = {k: np.asarray(get(k)) for k in ("walls", "pos", "theta", "goal")}
    for k in ("lidar_ranges", "lidar_hits"):
        try:
            out[k] = np.asarray(get(k))
        except (AttributeError, KeyError):
            pass
    return out


def draw_room(ax: Axes, walls: np.ndarray, room_size: float) -> None:
    """Walls dark, free cells light; x right, y up, 1 unit = 1 metre."""
    from matplotlib.colors import ListedColormap

    ax.imshow(
        walls.astype(float),
        origin="lower",
        extent=(0, room_size, 0, room_size),
        cmap=ListedColormap([FREE_COLOUR, WALL_COLOUR]),
        vmin=0,
        vmax=1,
        interpolation="nearest",
    )
    ax.set_xlim(0, room_size)
    ax.set_ylim(0, room_size)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_scene(
    ax: Axes,
    snap: Mapping[str, np.ndarray],
    config: EnvConfig,
    trajectory: np.ndarray | None = None,
    rays: bool = True,
    start: np.ndarray | None = None,
) -> None:
    """Room, goal, optional trajectory, lidar rays coloured by hit type, robot with heading."""
    draw_room(ax, snap["walls"], config.room_size)
    goal = snap["goal"]
    ax.add_patch(Circle(goal, config.goal_radius, color=GOAL_COLOUR, alpha=0.35, lw=0))
    ax.plot(*goal, marker="*", color=GOAL_COLOUR, ms=10)
    if trajectory is not None and len(trajectory) > 1:
        ax.plot(trajectory[:, 0], trajectory[:, 1], color=PATH_COLOUR, lw=1.5)
    if start is not None:
        ax.plot(*start, marker="o", color=PATH_COLOUR, ms=5)
    pos, theta = snap["pos"], float(snap["theta"])
    if rays and "lidar_ranges" in snap:
        angles = theta + beam_angles(config.lidar_beams, config.lidar_fov_deg)
        for ang, rng_m, hit in zip(angles, snap["lidar_ranges"], snap["lidar_hits"], strict=True):
            end = pos + rng_m * np.array([np.cos(ang), np.sin(ang)])
            ax.plot([pos[0], end[0]], [pos[1], end[1]], color=RAY_COLOURS[int(hit)], lw=0.8)
    r = config.robot_radius
    ax.add_patch(Circle(pos, r, color=ROBOT_COLOUR, zorder=5))
    ax.add_patch(
        FancyArrow(
            pos[0], pos[1], 1.6 * r * np.cos(theta), 1.6 * r * np.sin(theta),
            width=0.25 * r, head_width=0.7 * r, head_length=0.5 * r, color="white", zorder=6,
        )
    )  # fmt: skip


def _figure_to_rgb(fig) -> np.ndarray:
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb


def render_frame(
    state: Any,
    config: EnvConfig,
    trajectory: np.ndarray | None = None,
    title: str | None = None,
    size_px: int = 360,
) -> np.ndarray:
    """One frame as an RGB uint8 array (size_px x size_px)."""
    snap = as_snapshot(state)
    fig = plt.figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.90 if title else 0.96))
    draw_scene(ax, snap, config, trajectory=trajectory)
    if title:
        fit_title(fig, ax, title)
    return _figure_to_rgb(fig)


def fit_title(fig, ax: Axes, title: str, largest: float = 9.0, smallest: float = 6.0) -> None:
    """A title that fits the figure's width: a smaller font, then two lines, never cut off."""
    renderer = fig.canvas.get_renderer()
    room = 0.98 * fig.bbox.width
    text = ax.set_title(title, fontsize=largest)
    size = largest
    while text.get_window_extent(renderer).width > room and size > smallest:
        size -= 0.5
        text.set_fontsize(size)
    if text.get_window_extent(renderer).width > room:
        import textwrap

        width = max(8, int(len(title) * room / text.get_window_extent(renderer).width))
        text.set_text("\n".join(textwrap.wrap(title, width)[:2]))
        ax.set_position((0.02, 0.02, 0.96, 0.84))


def save_png(rgb: np.ndarray, path: str | Path) -> Path:
    """Write an RGB array as PNG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(path)
    return path


def save_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10.0) -> Path:
    """Write RGB frames as a looping GIF."""
    if not frames:
        raise ValueError("save_gif needs at least one frame")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path


def episode_frames(
    snapshots: Iterable[Any], config: EnvConfig, title: str | None = None, size_px: int = 360
) -> list[np.ndarray]:
    """Frames of an episode with its trajectory so far drawn behind the robot."""
    frames, path = [], []
    for t, state in enumerate(snapshots):
        snap = as_snapshot(state)
        path.append(snap["pos"])
        label = f"{title}  t={t}" if title else f"t={t}"
        frames.append(render_frame(snap, config, np.array(path), title=label, size_px=size_px))
    return frames


def rooms_figure(
    rooms_by_grid: Mapping[int, Sequence[np.ndarray]], room_size: float, path: str | Path
) -> Path:
    """Rows of generated rooms, one row per grid size (the paper's Figure 1)."""
    rows = len(rooms_by_grid)
    cols = max(len(v) for v in rooms_by_grid.values())
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.3 * rows), squeeze=False)
    for r, (g, rooms) in enumerate(rooms_by_grid.items()):
        for c in range(cols):
            ax = axes[r, c]
            if c < len(rooms):
                draw_room(ax, np.asarray(rooms[c]), room_size)
                free = (~np.asarray(rooms[c])).sum() / max((g - 2) ** 2, 1)
                ax.set_title(f"{g}x{g}, {free:.0%} of inner free", fontsize=8)
            else:
                ax.axis("off")
    fig.suptitle("Procedurally carved rooms (random-walk carving)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# map pictures: free, unknown and occupied pixels (the colours of the replay's room and walls)
MAP_FREE, MAP_UNKNOWN, MAP_OCCUPIED = (244, 241, 234), (190, 190, 190), (59, 59, 59)


def map_picture_step(shape: tuple[int, ...], max_side: int = 1024) -> int:
    """Map pixels per picture pixel (a side) of ``map_picture``."""
    return max(1, -(-max(shape) // max_side))  # ceil


def map_picture(blocked: np.ndarray, unknown: np.ndarray | None, max_side: int = 1024) -> np.ndarray:
    """A loaded map as an RGB picture, top row first, at most ``max_side`` pixels a side.

    ``blocked`` and ``unknown`` are (H, W) bool with y up (``maps.OccupancyMap``). A shrunk picture
    (``map_picture_step`` map pixels per pixel) keeps a pixel occupied if any pixel it stands for
    is, so thin walls stay visible; a partial last row or column counts as occupied (the grid's
    wall beyond the map)."""
    blocked = np.asarray(blocked, dtype=bool)
    unknown = np.asarray(unknown, dtype=bool) if unknown is not None else None
    occupied = blocked & ~unknown if unknown is not None else blocked
    step = map_picture_step(blocked.shape, max_side)
    if step > 1:
        h, w = blocked.shape
        pad = ((0, -h % step), (0, -w % step))

        def shrink(a: np.ndarray, edge: bool) -> np.ndarray:
            a = np.pad(a, pad, constant_values=edge)
            return a.reshape(a.shape[0] // step, step, a.shape[1] // step, step).any(axis=(1, 3))

        occupied = shrink(occupied, True)
        unknown = shrink(unknown, False) & ~occupied if unknown is not None else None
    rgb = np.empty((*occupied.shape, 3), dtype=np.uint8)
    rgb[:] = MAP_FREE
    if unknown is not None:
        rgb[unknown] = MAP_UNKNOWN
    rgb[occupied] = MAP_OCCUPIED
    return rgb[::-1].copy()
