"""Evaluation memory on a large map: a 50 m x 30 m office floor (0.1 m per pixel, rooms off two
corridors, 1 m doors) laid at 0.25 m cells (a grid of 202), the oracle driving ``--episodes``
episodes with ``quicknav eval --map``, as a user runs it; the peak RSS of that process and its
wall time are printed and written beside the map.

    uv run python benchmarks/large_map.py [--episodes 100] [--out /tmp/large-map]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RES = 0.1  # metres per pixel
WIDTH_M, HEIGHT_M = 50.0, 30.0


def office_floor() -> np.ndarray:
    """The floor as a map_server picture: 254 free, 0 occupied; three bands of 5 m rooms split by
    two 2 m corridors, every room with a 1 m door onto a corridor, the corridors joined at both
    ends through the middle band."""
    px = lambda m: round(m / RES)  # noqa: E731
    h, w = px(HEIGHT_M), px(WIDTH_M)
    img = np.zeros((h, w), np.uint8)
    img[px(0.2) : px(HEIGHT_M - 0.2), px(0.2) : px(WIDTH_M - 0.2)] = 254
    wall = np.zeros((h, w), bool)
    corridor_sides = (9.0, 11.0, 19.0, 21.0)
    for y in corridor_sides:
        wall[px(y) : px(y) + 2, :] = True
    rng = np.random.default_rng(0)
    for low, high in ((0.0, 9.0), (11.0, 19.0), (21.0, 30.0)):
        for x in np.arange(5.0, WIDTH_M, 5.0):
            wall[px(low) : px(high), px(x) : px(x) + 2] = True
        for x in np.arange(0.0, WIDTH_M, 5.0):
            for y in (low, high):
                if y in corridor_sides:  # a door onto the corridor
                    d = x + 1.5 + rng.uniform(0.0, 2.0)
                    wall[px(y) : px(y) + 2, px(d) : px(d + 1.0)] = False
    for x in (1.0, 46.0):  # the corridors joined through the middle band
        for y in (11.0, 19.0):
            wall[px(y) : px(y) + 2, px(x) : px(x + 2.0)] = False
    img[wall] = 0
    return img


def main() -> None:
    from PIL import Image

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--out", type=Path, default=Path("/tmp/large-map"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    Image.fromarray(office_floor()).save(args.out / "floor.pgm")
    (args.out / "floor.yaml").write_text(
        f"image: floor.pgm\nresolution: {RES}\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    # the oracle's env at 0.25 m cells (room_size / grid_size); the map sets the grid
    cmd = [sys.executable, "-m", "quicknav_cli.main", "eval", "--policy", "oracle",
           "--map", str(args.out / "floor.yaml"), "--set", "room_size=4", "--set", "grid_size=16",
           "--episodes", str(args.episodes), "--out", str(args.out / "eval")]  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall_s = time.perf_counter() - t0
    print(done.stdout[-3000:], done.stderr[-3000:], sep="\n")
    if done.returncode != 0:
        raise SystemExit(f"eval failed ({done.returncode})")
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    from quicknav_core.bench.machine import machine_line

    result = json.loads((args.out / "eval" / "eval.json").read_text())
    row = {"machine": machine_line(), "episodes": args.episodes, "peak_rss_mb": round(peak_mb),
           "wall_s": round(wall_s, 1), "success": result["metrics"]["success_rate"],
           "grid_size": result["env_config"]["grid_size"]}  # fmt: skip
    print(json.dumps(row))
    (args.out / "memory.json").write_text(json.dumps(row, indent=2) + "\n")


if __name__ == "__main__":
    main()
