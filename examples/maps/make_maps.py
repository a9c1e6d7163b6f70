"""Draw the example maps shipped in this folder (nothing is downloaded): run it to make them again.

    uv run python examples/maps/make_maps.py

- ``office.yaml`` + ``office.pgm``: a ROS map_server map (as map_saver writes one: P5 PGM, 0.05 m
  per pixel, 254 free / 0 occupied / 205 unknown) of a 20 m x 12 m office floor: a 2 m corridor
  along its length, offices on both sides with 1 m doors, desks and cabinets, and unknown space
  around the building as a SLAM map has it.
- ``warehouse.png`` (0.1 m per pixel, black = occupied): a 16 m x 16 m hall with shelf rows;
  ``warehouse.yaml`` is its map_server YAML.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FREE, OCCUPIED, UNKNOWN = 254, 0, 205


def office(res: float = 0.05) -> np.ndarray:
    """Grey levels, top row first (as the picture is drawn)."""
    w_m, h_m, margin = 20.0, 12.0, 0.6
    px = lambda m: round(m / res)  # noqa: E731
    W, H = px(w_m + 2 * margin), px(h_m + 2 * margin)
    img = np.full((H, W), UNKNOWN, np.uint8)
    x0, y0 = px(margin), px(margin)  # the building's lower-left corner, in pixels from the left/bottom

    def box(x, y, w, h, value):  # metres from the building's lower-left corner, y up
        r1 = H - (y0 + px(y))
        img[max(r1 - px(h), 0):r1, x0 + px(x):x0 + px(x + w)] = value

    wall = 0.1
    box(0, 0, w_m, h_m, FREE)
    for x, y, w, h in ((0, 0, w_m, wall), (0, h_m - wall, w_m, wall), (0, 0, wall, h_m),
                       (w_m - wall, 0, wall, h_m)):  # fmt: skip
        box(x, y, w, h, OCCUPIED)
    corridor_lo, corridor_hi = 5.0, 7.0
    box(0, corridor_lo - wall, w_m, wall, OCCUPIED)  # the corridor's walls
    box(0, corridor_hi, w_m, wall, OCCUPIED)
    for x in np.arange(4.0, w_m, 4.0):  # offices 4 m wide on both sides
        box(x, 0, wall, corridor_lo, OCCUPIED)
        box(x, corridor_hi, wall, h_m - corridor_hi, OCCUPIED)
    for i, x in enumerate(np.arange(0.0, w_m, 4.0)):
        door = x + 1.5
        box(door, corridor_lo - wall, 1.0, wall, FREE)  # 1 m doors into the corridor
        box(door, corridor_hi, 1.0, wall, FREE)
        box(x + 0.6, 0.6, 1.4, 0.7, OCCUPIED)  # a desk in each office
        box(x + 2.3, h_m - 1.2, 1.2, 0.6, OCCUPIED)
        if i % 2:
            box(x + 3.2, 2.0, 0.5, 1.0, OCCUPIED)  # a cabinet
    box(9.0, corridor_lo + 0.3, 0.5, 0.5, OCCUPIED)  # a plant in the corridor
    return img


def warehouse(res: float = 0.1) -> np.ndarray:
    n = round(16.0 / res)
    img = np.full((n, n), 255, np.uint8)
    t = max(1, round(0.2 / res))
    img[:t], img[-t:], img[:, :t], img[:, -t:] = 0, 0, 0, 0
    for x in np.arange(2.5, 14.0, 2.5):  # shelf rows, 0.6 m deep, aisles between
        c0 = round(x / res)
        img[round(2.5 / res):round(13.5 / res), c0:c0 + round(0.6 / res)] = 0
    return img


def write_pgm(path: Path, grey: np.ndarray) -> None:
    h, w = grey.shape
    path.write_bytes(f"P5\n# CREATOR: quicknav examples/maps/make_maps.py\n{w} {h}\n255\n".encode()
                     + grey.tobytes())  # fmt: skip


def main() -> None:
    from PIL import Image

    write_pgm(HERE / "office.pgm", office())
    (HERE / "office.yaml").write_text(
        "image: office.pgm\nmode: trinary\nresolution: 0.05\norigin: [-0.6, -0.6, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    Image.fromarray(warehouse()).save(HERE / "warehouse.png")
    (HERE / "warehouse.yaml").write_text(
        "image: warehouse.png\nmode: trinary\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    print("wrote office.yaml, office.pgm, warehouse.png, warehouse.yaml in", HERE)


if __name__ == "__main__":
    main()
