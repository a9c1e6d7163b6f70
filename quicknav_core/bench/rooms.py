"""`quicknav bench rooms`: seconds to build the room banks (train, then test) per grid size.

Every grid builds the banks of the benchmark's env (``bench.env.env_config_for``: an 8 m room, a
robot small enough for the grid, the default carving, room counts and seed) the way a training job
does: the room source's ``bank("train")``, then ``"test"`` (which reuses that train bank to keep its
rooms out). The grid size is a compile-time shape, so each figure is a first call: tracing and
compiling the carver are included. No bank cache is set, so nothing is read from disk.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from quicknav_core.bench.env import BenchReport
from quicknav_core.bench.machine import machine_info
from quicknav_core.config import EnvConfig

DEFAULT_GRIDS = (8, 16, 32, 64, 128)
# The target: both default banks of any allowed grid, first call, on 2 CPU cores.
TARGET_BUILD_S = 10.0


@dataclass
class RoomsMeasurement:
    """One row of the table."""

    grid: int
    carver: str  # the carver that built the banks (``auto`` decided)
    train_rooms: int
    test_rooms: int
    train_s: float  # wall-clock of the train bank, compile included
    test_s: float  # wall-clock of the test bank after it
    total_s: float
    carve_target: int  # free cells per room
    free_cells: int  # free cells of the smallest room (at least carve_target)


@dataclass
class RoomsBenchConfig:
    grids: Sequence[int] = DEFAULT_GRIDS
    carver: str = "auto"
    room_size: float = 8.0
    seed: int = 0


# the same report shape as the env bench's (config, machine, results, targets)
RoomsBenchReport = BenchReport


def bench_grid(grid: int, cfg: RoomsBenchConfig) -> RoomsMeasurement:
    """Build the train bank, then the test bank, of the benchmark's env at ``grid``."""
    from quicknav_core.bench.env import BenchConfig, env_config_for
    from quicknav_core.env.room_sources import room_source

    env = env_config_for(grid, BenchConfig(room_size=cfg.room_size, seed=cfg.seed))
    config = EnvConfig.model_validate({**env.model_dump(), "carver": cfg.carver})
    rooms = room_source(config)  # one runtime: the test bank skips the train bank built first
    t0 = time.perf_counter()
    train = rooms.bank("train")
    t1 = time.perf_counter()
    test = rooms.bank("test")
    t2 = time.perf_counter()
    free = int(min((~train).sum(axis=(1, 2)).min(), (~test).sum(axis=(1, 2)).min()))
    return RoomsMeasurement(
        grid=grid, carver=config.resolved_carver, train_rooms=len(train), test_rooms=len(test),
        train_s=round(t1 - t0, 3), test_s=round(t2 - t1, 3), total_s=round(t2 - t0, 3),
        carve_target=config.carve_target, free_cells=free,
    )  # fmt: skip


def check_targets(results: Sequence[RoomsMeasurement]) -> list[dict[str, Any]]:
    """The issue's target against the measured figures."""
    if not results:
        return []
    worst = max(results, key=lambda r: r.total_s)
    return [{
        "target": f"train + test banks of every grid < {TARGET_BUILD_S:g} s (first call)",
        "measured": worst.total_s, "grid": worst.grid, "met": worst.total_s < TARGET_BUILD_S,
    }]  # fmt: skip


def run_rooms_bench(
    cfg: RoomsBenchConfig, progress: Callable[[str], None] | None = None
) -> RoomsBenchReport:
    """Build the banks of every grid of ``cfg``, smallest first."""
    say = progress or (lambda _msg: None)
    report = RoomsBenchReport(config=asdict(cfg), machine=machine_info())
    report.config["grids"] = list(cfg.grids)
    for grid in cfg.grids:
        say(f"grid {grid}: carving the train and test banks")
        report.results.append(bench_grid(grid, cfg))
    report.targets = check_targets(report.results)
    return report


def write_report(report: RoomsBenchReport, out_dir: Path) -> Path:
    """bench_rooms.json in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "bench_rooms.json"
    path.write_text(json.dumps(report.to_json(), indent=2))
    return path


def format_table(report: RoomsBenchReport) -> list[list[str]]:
    """Rows for the terminal table."""
    return [
        [f"{r.grid}x{r.grid}", r.carver, f"{r.train_rooms:,} + {r.test_rooms:,}",
         f"{r.carve_target:,}", f"{r.train_s:.2f}", f"{r.test_s:.2f}", f"{r.total_s:.2f}"]
        for r in report.results
    ]  # fmt: skip
